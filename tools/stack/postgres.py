"""A PostgreSQL server of the stack's own, in one directory: the detector replicas' record.

The shared record of detector replicas on one machine (``aesop up --replicas``), the fleet
benchmark and the tests.

Debian's PostgreSQL binaries (``/usr/lib/postgresql/<major>/bin``) run it: ``initdb``
once (:meth:`PostgresServer.init`), then the server in the foreground as a child of
``aesop up`` (:meth:`PostgresServer.argv`) or in the background (``start``/``stop``). It
listens on 127.0.0.1 only, and on its socket in the directory, which is made 0700 at every
start whatever it was. The detectors' role ``aesop`` is no superuser (it owns the stack's
database, nothing more); it logs in over TCP with a password (SCRAM, written to
``<dir>/password``, 0600: ``url``) and over the socket without one (``socket_url``):
reaching the socket already takes the directory's owner. The cluster's superuser
(``postgres``) logs in over the socket only, to create the role and the databases.
PostgreSQL refuses to run as root: as root, the directory is given to the ``postgres``
system user and every command runs as that user (``setpriv``).
"""

from __future__ import annotations

import glob
import os
import pwd
import secrets
import shutil
import subprocess
from pathlib import Path

import psycopg
from psycopg import sql

DATABASE = "aesop"
ROLE = "aesop"  # the detectors': no superuser, the stack's database's owner
ADMIN = "postgres"  # the cluster's superuser: over the socket only


class PostgresError(RuntimeError):
    """The server could not be set up or started; the message says why (its log's tail)."""


def _binary(name: str) -> str:
    found = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"), reverse=True)
    if found:
        return found[0]
    path = shutil.which(name)
    if path is None:
        raise PostgresError(f"{name} not found: install PostgreSQL (Debian: apt-get install "
                            "postgresql)")
    return path


class PostgresServer:
    """One server in ``root`` on ``port``. ``fsync=False`` (tests, benchmarks of the
    stack rather than of the disk) survives a crash of the server but not of the machine."""

    def __init__(self, root: Path, port: int, *, fsync: bool = True) -> None:
        self.root = Path(root).absolute()
        self.port = port
        self.fsync = fsync
        self.data = self.root / "data"
        self.log = self.root / "server.log"
        self._as_postgres = os.geteuid() == 0

    @property
    def password(self) -> str:
        return (self.root / "password").read_text().strip()

    @property
    def url(self) -> str:
        """The connection string of the stack's database (it holds the password)."""
        return self.url_of(DATABASE)

    @property
    def socket_url(self) -> str:
        """The stack's database over the server's socket (no password)."""
        return f"postgresql://{ROLE}@/{DATABASE}?host={self.root}&port={self.port}"

    def url_of(self, database: str) -> str:
        return f"postgresql://{ROLE}:{self.password}@127.0.0.1:{self.port}/{database}"

    @property
    def _admin_url(self) -> str:
        return f"postgresql://{ADMIN}@/postgres?host={self.root}&port={self.port}"

    def create_database(self, name: str) -> str:
        """A new, empty database ``name`` (letters, digits, '_'), the detectors' role its
        owner; its URL."""
        if not name.replace("_", "").isalnum():
            raise PostgresError(f"database names here are letters, digits and '_': {name!r}")
        with psycopg.connect(self._admin_url, autocommit=True) as db:
            db.execute(sql.SQL("CREATE DATABASE {} OWNER {}").format(
                sql.Identifier(name), sql.Identifier(ROLE)))
        return self.url_of(name)

    def _as_owner(self, *args: str) -> tuple[str, ...]:
        """``args`` as the ``postgres`` user when this is root: ``setpriv`` executes the
        command in its own place (no process in between, so the server is the child that is
        signalled and reaped, and nothing is orphaned when it is killed)."""
        if not self._as_postgres:
            return args
        return ("setpriv", "--reuid=postgres", "--regid=postgres", "--init-groups",
                "--reset-env", "--", *args)

    def _run(self, *args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(self._as_owner(*args), capture_output=True, text=True,
                              check=False, stdin=subprocess.DEVNULL)

    def _options(self) -> tuple[str, ...]:
        return ("-p", str(self.port), "-k", str(self.root), "-c", "listen_addresses=127.0.0.1",
                *(() if self.fsync else ("-c", "fsync=off", "-c", "full_page_writes=off")))

    def argv(self) -> tuple[str, ...]:
        """The server in the foreground (after :meth:`init`): stopped by SIGTERM once its
        clients are gone, by SIGINT at once."""
        return self._as_owner(_binary("postgres"), "-D", str(self.data), *self._options())

    def init(self) -> None:
        """Make ``root`` private (0700, the server's owner's: whatever it was), then create
        the cluster, the detectors' role and their database unless it holds one already;
        the server is left stopped."""
        self.root.mkdir(mode=0o700, parents=True, exist_ok=True)
        self.root.chmod(0o700)
        owner = pwd.getpwnam("postgres") if self._as_postgres else None
        if owner is not None:
            os.chown(self.root, owner.pw_uid, owner.pw_gid)
        if (self.data / "PG_VERSION").exists():
            return
        secret = self.root / "password"
        admin = self.root / "admin-password"  # initdb's, for the superuser: read once
        for path in (secret, admin):
            path.write_text(secrets.token_urlsafe(24) + "\n")
            path.chmod(0o600)
            if owner is not None:
                os.chown(path, owner.pw_uid, owner.pw_gid)
        if owner is not None and self._run("test", "-r", str(secret)).returncode != 0:
            raise PostgresError(f"the postgres user cannot reach {self.root}: every "
                                "folder above it must be searchable by others (o+x)")
        try:
            done = self._run(_binary("initdb"), "-D", str(self.data), "-U", ADMIN,
                             f"--pwfile={admin}", "--auth-host=scram-sha-256",
                             "--auth-local=trust", "-E", "UTF8",
                             "--locale=C.UTF-8", *([] if self.fsync else ["--no-sync"]))
        finally:
            admin.unlink(missing_ok=True)
        if done.returncode != 0:
            raise PostgresError(f"initdb in {self.data} failed: {done.stderr.strip()}")
        self.start()
        try:
            with psycopg.connect(self._admin_url, autocommit=True) as db:
                db.execute(sql.SQL("CREATE ROLE {} LOGIN NOSUPERUSER NOCREATEDB NOCREATEROLE "
                                   "PASSWORD {}").format(sql.Identifier(ROLE),
                                                         sql.Literal(self.password)))
            self.create_database(DATABASE)
        finally:
            self.stop()

    def start(self, timeout: float = 60.0) -> None:
        """The server in the background (``pg_ctl``), once it accepts connections."""
        done = self._run(_binary("pg_ctl"), "-D", str(self.data), "-l", str(self.log),
                         "-o", " ".join(self._options()), "-w", "-t", str(int(timeout)),
                         "start")
        if done.returncode != 0:
            tail = self.log.read_text()[-2000:] if self.log.exists() else done.stderr
            raise PostgresError(f"PostgreSQL in {self.data} did not start: {tail.strip()}")

    def stop(self, *, immediate: bool = False) -> None:
        """Stop the server: cleanly, or as a crash would (``immediate``: no checkpoint,
        the next start replays the write-ahead log)."""
        self._run(_binary("pg_ctl"), "-D", str(self.data), "-m",
                  "immediate" if immediate else "fast", "-w", "stop")

    def running(self) -> bool:
        return self._run(_binary("pg_ctl"), "-D", str(self.data), "status").returncode == 0
