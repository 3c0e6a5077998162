"""Durable storage shared by detector replicas: one PostgreSQL database, change log and notices.

The shared record of every replica (``AESOP_EMBEDDING_STORE=postgresql://...``), each with
its own FAISS index.

The schema and the transactions are the SQLite store's (:mod:`.store`): a cache's header,
its experiences with their vectors, the versioned change log, detection vectors, the
calibration scores, proposals; a write is one transaction, answered 2xx only after COMMIT.
Two things are added for replicas:

* **Ordering.** A write is planned on the replica's copy of the cache at version ``v`` and
  committed only if the stored cache is still at ``v`` (its row locked ``FOR UPDATE``);
  otherwise nothing is written and :class:`~services.embedding.detector.errors.Behind`
  says so (the replica catches up; the caller may retry). Versions are therefore one total
  order shared by all.
* **Following.** Every write notifies channel ``aesop_embedding`` in its transaction
  (delivered on commit) with the cache and the version or proposal it wrote. A replica
  listens (:meth:`PostgresStore.listen`) and reads what it lacks: :meth:`changes_since`
  rebuilds the operations after its version from the change log and the rows they wrote,
  so its index is caught up the way a restart catches up an index file.

Index files stay on the replica's own disk (:mod:`.indexfiles`). PostgreSQL out of reach:
reads and writes raise ``StorageError`` (503 for a write), the in-memory caches go on
scoring, and the next call connects again.

Schema (table ``aesop_schema`` holds its version, 1; a database of another is refused)::

    caches(name PK, config, version, next_label, calibration|NULL, stale)
    experiences(cache, label, id, text|NULL, metadata, vector BYTEA <f4, version,
                detections)   PK (cache, label), UNIQUE (cache, id)
    detection_vectors(cache, phrase, vector BYTEA <f4, version)   PK (cache, phrase)
    calibration_scores(cache PK, observation, detection, pair|NULL BYTEA <f8)
    proposals(cache, id, state, count, first_at, last_at, decided_at|NULL, detail)
    changes(cache, version, op, detail, at)   PK (cache, version)

JSON columns are text, written as the SQLite store writes them.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import psycopg
from psycopg import errors as pgerrors

from ..detector.cache import (
    Add,
    Cache,
    CacheConfig,
    CalibrationScores,
    Delete,
    Header,
    Op,
    SetCalibration,
)
from ..detector.calibration import Calibration
from ..detector.errors import Behind, StorageCorrupt, StorageError, StorageFull
from ..detector.index import VectorIndex
from ..detector.proposals import Proposal
from . import records as rec
from .indexfiles import IndexFiles, WithIndexFiles
from .store import LOCK_NAME, take_lock

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
CHANNEL = "aesop_embedding"
_SCHEMA_LOCK = 0x4145534F50  # pg_advisory_xact_lock key while a replica creates the schema

_SCHEMA = """
CREATE TABLE aesop_schema (version INTEGER NOT NULL);
CREATE TABLE caches (
    name TEXT PRIMARY KEY, config TEXT NOT NULL, version BIGINT NOT NULL,
    next_label BIGINT NOT NULL, calibration TEXT, stale BOOLEAN NOT NULL
);
CREATE TABLE experiences (
    cache TEXT NOT NULL REFERENCES caches(name), label BIGINT NOT NULL, id TEXT NOT NULL,
    text TEXT, metadata TEXT NOT NULL, vector BYTEA NOT NULL, version BIGINT NOT NULL,
    detections TEXT NOT NULL DEFAULT '[]',
    PRIMARY KEY (cache, label), UNIQUE (cache, id)
);
CREATE INDEX experiences_by_version ON experiences (cache, version);
CREATE TABLE changes (
    cache TEXT NOT NULL REFERENCES caches(name), version BIGINT NOT NULL, op TEXT NOT NULL,
    detail TEXT NOT NULL, at DOUBLE PRECISION NOT NULL, PRIMARY KEY (cache, version)
);
CREATE TABLE detection_vectors (
    cache TEXT NOT NULL REFERENCES caches(name), phrase TEXT NOT NULL, vector BYTEA NOT NULL,
    version BIGINT NOT NULL, PRIMARY KEY (cache, phrase)
);
CREATE TABLE calibration_scores (
    cache TEXT PRIMARY KEY REFERENCES caches(name), observation BYTEA NOT NULL,
    detection BYTEA NOT NULL, pair BYTEA
);
CREATE TABLE proposals (
    cache TEXT NOT NULL REFERENCES caches(name), id TEXT NOT NULL, state TEXT NOT NULL,
    count BIGINT NOT NULL, first_at DOUBLE PRECISION NOT NULL,
    last_at DOUBLE PRECISION NOT NULL, decided_at DOUBLE PRECISION, detail TEXT NOT NULL,
    PRIMARY KEY (cache, id)
);
"""

# {"cache", "version", "origin"} or {"cache", "proposal", "origin"}; None: resync all
Notice = dict[str, Any]


class PostgresStore(WithIndexFiles):
    """The replica's view of the shared database at ``url`` and its own index files under
    ``data_dir`` (one process per data directory, as with SQLite). Thread-safe: one
    connection, used under a lock, opened again after a failure."""

    shared = True

    def __init__(self, url: str, data_dir: Path, *, fsync: bool = True,
                 connect_timeout: float = 5.0) -> None:
        self.url = url
        self.root = Path(data_dir)
        self.root.mkdir(mode=0o700, parents=True, exist_ok=True)
        self.root.chmod(0o700)
        self.indexes = IndexFiles(self.root, fsync=fsync)
        self._timeout = connect_timeout
        self.origin = uuid.uuid4().hex[:12]  # in this replica's notices, so it skips its own
        self._mutex = threading.Lock()
        self._db: psycopg.Connection[Any] | None = None
        self._closed = False
        self._said_bad_notice = False  # a notice no replica wrote is logged once
        self._lock_fd = take_lock(self.root / LOCK_NAME)
        try:
            with self._session("the schema") as db:
                _ensure_schema(db)
        except BaseException:
            self.close()
            raise

    def __repr__(self) -> str:  # the URL holds the password
        return f"PostgresStore({self.root})"

    # -- the connection ------------------------------------------------------------

    def _connect(self, **options: Any) -> psycopg.Connection[Any]:
        return psycopg.connect(self.url, connect_timeout=max(1, round(self._timeout)),
                               application_name="aesop-embedding", **options)

    @contextlib.contextmanager
    def _session(self, what: str) -> Iterator[psycopg.Connection[Any]]:
        """One transaction on the shared connection; PostgreSQL's errors as StorageError
        (rolled back: nothing of it is stored)."""
        with self._mutex:
            if self._closed:
                raise StorageError("the store is closed")
            try:
                if self._db is None or self._db.closed or self._db.broken:
                    self._db = self._connect()
                with self._db.transaction():
                    yield self._db
            except (pgerrors.DiskFull, pgerrors.OutOfMemory) as exc:
                raise StorageFull(f"PostgreSQL: {what} was not written ({exc})") from exc
            except psycopg.Error as exc:
                if self._db is not None and (self._db.closed or self._db.broken):
                    self._db = None
                raise StorageError(f"PostgreSQL: {what} failed ({_first_line(exc)})"
                                   ) from exc

    # -- reads ---------------------------------------------------------------------

    def names(self) -> list[str]:
        with self._session("listing the caches") as db:
            return [r[0] for r in db.execute("SELECT name FROM caches ORDER BY name")]

    def versions(self) -> dict[str, int]:
        """Every cache's stored version."""
        with self._session("reading the versions") as db:
            return {name: int(v) for name, v in db.execute("SELECT name, version FROM caches")}

    def history(self, name: str) -> list[tuple[int, str, dict[str, Any]]]:
        with self._session(f"reading cache {name!r}'s history") as db:
            rows = db.execute("SELECT version, op, detail FROM changes WHERE cache = %s "
                              "ORDER BY version", (name,)).fetchall()
        return [(int(v), op, json.loads(detail)) for v, op, detail in rows]

    def load(self, name: str) -> Cache:
        """Cache ``name`` as stored, its index from this replica's newest usable file."""
        with self._session(f"loading cache {name!r}") as db:
            db.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ")
            header = _header(db, name)
            experiences = {
                int(label): rec.experience_of(*row) for label, *row in db.execute(
                    "SELECT label, id, text, metadata, detections FROM experiences "
                    "WHERE cache = %s ORDER BY label", (name,))}
            config = header.config
            index = self.indexes.restore(
                header, set(experiences),
                lambda idx, since: _catch_up(db, idx, config, since),
                lambda idx: _add_stored(db, idx, config, -1))
            phrases = {p: rec.f4(v) for p, v in db.execute(
                "SELECT phrase, vector FROM detection_vectors WHERE cache = %s", (name,))}
            scores = _scores(db, name)
        return Cache.restored(header, experiences, index, phrases, scores)

    def changes_since(self, name: str, version: int) -> tuple[list[tuple[Op, float]], Header]:
        """The operations that brought cache ``name`` past ``version`` (with when each was
        written), and its stored header: applied in order to a copy at ``version``, then the
        header set, the copy is the stored cache. An add lists only its experiences still
        stored, a calibration the current scores (a later one replaced them)."""
        with self._session(f"following cache {name!r}") as db:
            db.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ")
            header = _header(db, name)
            rows = db.execute("SELECT version, op, detail, at FROM changes WHERE cache = %s "
                              "AND version > %s ORDER BY version", (name, version)).fetchall()
            ops = [(_op(db, name, header.config.dim, int(v), op, json.loads(detail)),
                    float(at))
                   for v, op, detail, at in rows if op != "create"]
        return ops, header

    def proposals(self, name: str) -> list[Proposal]:
        with self._session(f"reading cache {name!r}'s proposals") as db:
            rows = db.execute(
                "SELECT id, state, count, first_at, last_at, decided_at, detail FROM proposals "
                "WHERE cache = %s ORDER BY first_at", (name,)).fetchall()
        return [rec.proposal_of(row) for row in rows]

    def proposal(self, name: str, ident: str) -> Proposal | None:
        with self._session(f"reading proposal {ident!r}") as db:
            row = db.execute(
                "SELECT id, state, count, first_at, last_at, decided_at, detail FROM proposals "
                "WHERE cache = %s AND id = %s", (name, ident)).fetchone()
        return None if row is None else rec.proposal_of(row)

    # -- writes --------------------------------------------------------------------

    def create(self, config: CacheConfig) -> Header:
        """Create cache ``config.name``; ``Behind`` if another replica created it first."""
        header = Header(config)
        with self._session(f"creating cache {config.name!r}") as db:
            done = db.execute("INSERT INTO caches VALUES (%s, %s, %s, %s, %s, %s) "
                              "ON CONFLICT (name) DO NOTHING",
                              (config.name, *rec.header_row(header)))
            if done.rowcount == 0:
                stored = db.execute("SELECT version FROM caches WHERE name = %s",
                                    (config.name,)).fetchone()
                raise Behind(config.name, -1, int(stored[0]) if stored else 0)
            _change(db, config.name, 0, "create", asdict(config))
            _notify(db, {"cache": config.name, "version": 0, "origin": self.origin})
        return header

    def commit(self, name: str, op: Op, header: Header, proposal: Proposal | None = None
               ) -> None:
        """Make ``op`` durable with ``header`` and the ``proposal`` it accepts, if the
        stored cache is still at the version ``op`` was planned on; else ``Behind``."""
        with self._session(f"cache {name!r} version {op.version}") as db:
            row = db.execute("SELECT version FROM caches WHERE name = %s FOR UPDATE",
                             (name,)).fetchone()
            if row is None:
                raise StorageError(f"cache {name!r} is not in the database")
            if int(row[0]) != op.version - 1:
                raise Behind(name, op.version - 1, int(row[0]))
            _write_op(db, name, op)
            _update_header(db, name, header)
            if proposal is not None:
                _write_proposal(db, name, proposal)
                _notify(db, {"cache": name, "proposal": proposal.id, "origin": self.origin})
            _notify(db, {"cache": name, "version": op.version, "origin": self.origin})

    def save_proposal(self, name: str, proposal: Proposal) -> None:
        with self._session(f"proposal {proposal.id} of cache {name!r}") as db:
            _write_proposal(db, name, proposal)
            _notify(db, {"cache": name, "proposal": proposal.id, "origin": self.origin})

    # -- following -----------------------------------------------------------------

    def listen(self, stop: threading.Event, notice: Callable[[Notice | None], None],
               retry_s: float = 1.0) -> None:
        """Until ``stop`` is set, pass each write's notice to ``notice``; ``notice(None)``
        once listening starts and after every reconnection (whatever was written while
        not listening must be read whole). Blocks: run it on a thread of its own."""
        said = False
        while not stop.is_set():
            try:
                with self._connect(autocommit=True) as db:
                    db.execute(f"LISTEN {CHANNEL}")
                    notice(None)
                    said = False
                    while not stop.is_set():
                        for n in db.notifies(timeout=0.5):
                            parsed = parse_notice(n.payload)
                            if parsed is not None:
                                notice(parsed)
                            elif not self._said_bad_notice:  # once: the poll catches up
                                log.warning("dropped a notice on %s that no replica wrote: "
                                            "%.80r", CHANNEL, n.payload)
                                self._said_bad_notice = True
            except psycopg.Error as exc:
                if not said:
                    log.warning("not following the other replicas' writes (%s); trying "
                                "again every %.0f s", _first_line(exc), retry_s)
                    said = True
                stop.wait(retry_s)

    # -- lifecycle -----------------------------------------------------------------

    def close(self) -> None:
        """Close the connection and release the data directory; safe to call twice."""
        with self._mutex:
            if self._closed:
                return
            self._closed = True
            try:
                if self._db is not None:
                    self._db.close()
            finally:
                os.close(self._lock_fd)


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def _ensure_schema(db: psycopg.Connection[Any]) -> None:
    db.execute("SELECT pg_advisory_xact_lock(%s)", (_SCHEMA_LOCK,))
    found = db.execute("SELECT to_regclass('aesop_schema')").fetchone()
    if found is None or found[0] is None:
        db.execute(_SCHEMA)
        db.execute("INSERT INTO aesop_schema VALUES (%s)", (SCHEMA_VERSION,))
        return
    row = db.execute("SELECT version FROM aesop_schema").fetchone()
    if row is None or row[0] != SCHEMA_VERSION:
        raise StorageCorrupt(Path("postgresql"), f"schema version {row and row[0]}; this build "
                                                  f"reads {SCHEMA_VERSION}")


def _header(db: psycopg.Connection[Any], name: str) -> Header:
    row = db.execute("SELECT config, version, next_label, calibration, stale FROM caches "
                     "WHERE name = %s", (name,)).fetchone()
    if row is None:
        raise KeyError(name)
    return rec.header_of(*row)


def _scores(db: psycopg.Connection[Any], name: str) -> CalibrationScores | None:
    return rec.scores_of(db.execute("SELECT observation, detection, pair FROM "
                                    "calibration_scores WHERE cache = %s", (name,)).fetchone())


def _catch_up(db: psycopg.Connection[Any], index: VectorIndex, config: CacheConfig,
              since: int) -> None:
    deleted = [json.loads(d)["label"] for (d,) in db.execute(
        "SELECT detail FROM changes WHERE cache = %s AND op = 'delete' AND version > %s",
        (config.name, since))]
    if deleted:
        index.remove(np.array(deleted, dtype=np.int64))
    _add_stored(db, index, config, since)


def _add_stored(db: psycopg.Connection[Any], index: VectorIndex, config: CacheConfig,
                since: int) -> None:
    with db.cursor() as cur:
        cur.execute("SELECT label, vector FROM experiences WHERE cache = %s AND version > %s "
                    "ORDER BY label", (config.name, since))
        while batch := cur.fetchmany(65536):
            labels = np.fromiter((r[0] for r in batch), dtype=np.int64, count=len(batch))
            vectors = np.frombuffer(b"".join(r[1] for r in batch), dtype="<f4")
            index.add(vectors.reshape(len(batch), config.dim), labels)


def _op(db: psycopg.Connection[Any], name: str, dim: int, version: int, op: str,
        detail: dict[str, Any]) -> Op:
    """The operation that wrote ``version``, rebuilt from what it stored."""
    if op == "add":
        rows = db.execute("SELECT label, id, text, metadata, detections, vector FROM "
                          "experiences WHERE cache = %s AND version = %s ORDER BY label",
                          (name, version)).fetchall()
        phrases = {p: rec.f4(v) for p, v in db.execute(
            "SELECT phrase, vector FROM detection_vectors WHERE cache = %s AND version = %s",
            (name, version))}
        vectors = np.array([rec.f4(r[5]) for r in rows], dtype=np.float32).reshape(len(rows), dim)
        return Add(tuple(int(r[0]) for r in rows),
                   tuple(rec.experience_of(*r[1:5]) for r in rows), vectors, version, phrases)
    if op == "delete":
        return rec.delete_op(detail, version)
    if op == "calibrate":
        return SetCalibration(Calibration(**detail), version, _scores(db, name))
    if op == "configure":
        return rec.configure_op(detail, version)
    raise StorageCorrupt(Path("postgresql"), f"cache {name!r} version {version}: unknown "
                                             f"change {op!r}")


def _update_header(db: psycopg.Connection[Any], name: str, header: Header) -> None:
    config, version, next_label, cal, stale = rec.header_row(header)
    db.execute("UPDATE caches SET config = %s, version = %s, next_label = %s, "
               "calibration = %s, stale = %s WHERE name = %s",
               (config, version, next_label, cal, stale, name))


def _change(db: psycopg.Connection[Any], name: str, version: int, op: str,
            detail: dict[str, Any]) -> None:
    db.execute("INSERT INTO changes VALUES (%s, %s, %s, %s, %s)",
               (name, version, op, json.dumps(detail), time.time()))


def parse_notice(payload: str) -> Notice | None:
    """A write's notice as the replicas send it (:func:`_notify`): a JSON object naming its
    cache and either the version written or the proposal, with its origin; None for
    anything else (a payload a database role sent by hand must not stop the following)."""
    try:
        notice = json.loads(payload)
    except ValueError:
        return None
    if not isinstance(notice, dict) or not isinstance(notice.get("cache"), str) \
            or not isinstance(notice.get("origin", ""), str):
        return None
    version, proposal = notice.get("version"), notice.get("proposal")
    if (isinstance(version, int) and not isinstance(version, bool)) == isinstance(proposal, str):
        return None  # exactly one of the two
    return notice


def _notify(db: psycopg.Connection[Any], payload: Notice) -> None:
    db.execute("SELECT pg_notify(%s, %s)", (CHANNEL, json.dumps(payload)))


def _write_proposal(db: psycopg.Connection[Any], name: str, proposal: Proposal) -> None:
    db.execute(
        "INSERT INTO proposals VALUES (%s, %s, %s, %s, %s, %s, %s, %s) "
        "ON CONFLICT (cache, id) DO UPDATE SET state = EXCLUDED.state, count = "
        "EXCLUDED.count, first_at = EXCLUDED.first_at, last_at = EXCLUDED.last_at, "
        "decided_at = EXCLUDED.decided_at, detail = EXCLUDED.detail",
        rec.proposal_row(name, proposal))


def _write_op(db: psycopg.Connection[Any], name: str, op: Op) -> None:
    if isinstance(op, Add):
        with db.cursor() as cur:
            cur.executemany("INSERT INTO experiences VALUES (%s, %s, %s, %s, %s, %s, %s, %s)",
                            rec.experience_rows(name, op))
            cur.executemany("INSERT INTO detection_vectors VALUES (%s, %s, %s, %s)",
                            [(name, *row, op.version) for row in rec.phrase_rows(op)])
    elif isinstance(op, Delete):
        db.execute("DELETE FROM experiences WHERE cache = %s AND label = %s", (name, op.label))
    elif isinstance(op, SetCalibration):
        db.execute("DELETE FROM calibration_scores WHERE cache = %s", (name,))
        if op.scores is not None:
            db.execute("INSERT INTO calibration_scores VALUES (%s, %s, %s, %s)",
                       (name, *rec.score_blobs(op.scores)))
    _change(db, name, op.version, *rec.change_of(op))
