"""Durable storage of the vector-cache service: one SQLite database, and index files.

The database ``<data_dir>/embedding.sqlite3`` (WAL journal, ``synchronous=FULL``)
is the source of truth: every cache's header, experiences (vectors included),
and the history of its versions. A write is one transaction; the service answers
2xx only after its COMMIT returned, so a 2xx means durable, and a write that
fails (a full disk: ``StorageFull``) is rolled back whole, in the file and in
memory alike.

A cache's FAISS index is derived data, saved now and then to index files
(:mod:`.indexfiles`) and caught up from the database on open.

Schema (``PRAGMA user_version`` = 3; a database of another version is refused, naming
it)::

    caches(name PK, config JSON, version, next_label, calibration JSON|NULL, stale)
    experiences(cache, label, id, text|NULL, metadata JSON, vector BLOB <f4, version,
                detections JSON)
        PK (cache, label), UNIQUE (cache, id); ``version``: the one that added it;
        ``detections``: [{"label", "where"?, "confidence"?}]
    detection_vectors(cache, phrase, vector BLOB <f4)   PK (cache, phrase): every
        detection phrase the cache's experiences brought, written with them
    calibration_scores(cache PK, observation BLOB <f8, detection BLOB <f8, pair BLOB <f8
        |NULL): the sorted nominal scores behind the current calibration's p-values
        (``pair`` NULL when the calibration did not ask for pairs)
    proposals(cache, id, state, count, first_at, last_at, decided_at|NULL, detail JSON)
        PK (cache, id): scenes the slow reasoner answered "continue" for; accepting one
        is written with its experience, in one transaction
    changes(cache, version, op, detail JSON, at)   one row per version of each cache:
        op is create | add | delete | calibrate | configure

One process per data directory: an flock on ``<data_dir>/embedding.lock``.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import sqlite3
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from ..detector.cache import (
    Add,
    Cache,
    CacheConfig,
    Delete,
    Header,
    Op,
    SetCalibration,
)
from ..detector.errors import StorageCorrupt, StorageError, StorageFull
from ..detector.index import VectorIndex
from ..detector.proposals import Proposal
from . import records as rec
from .indexfiles import IndexFiles, WithIndexFiles

log = logging.getLogger(__name__)

DB_NAME = "embedding.sqlite3"
LOCK_NAME = "embedding.lock"
SCHEMA_VERSION = 3

_SCHEMA = """
CREATE TABLE caches (
    name TEXT PRIMARY KEY, config TEXT NOT NULL, version INTEGER NOT NULL,
    next_label INTEGER NOT NULL, calibration TEXT, stale INTEGER NOT NULL
) STRICT;
CREATE TABLE experiences (
    cache TEXT NOT NULL REFERENCES caches(name), label INTEGER NOT NULL, id TEXT NOT NULL,
    text TEXT, metadata TEXT NOT NULL, vector BLOB NOT NULL, version INTEGER NOT NULL,
    detections TEXT NOT NULL DEFAULT '[]',
    PRIMARY KEY (cache, label), UNIQUE (cache, id)
) STRICT;
CREATE INDEX experiences_by_version ON experiences (cache, version);
CREATE TABLE changes (
    cache TEXT NOT NULL REFERENCES caches(name), version INTEGER NOT NULL, op TEXT NOT NULL,
    detail TEXT NOT NULL, at REAL NOT NULL, PRIMARY KEY (cache, version)
) STRICT;
CREATE TABLE detection_vectors (
    cache TEXT NOT NULL REFERENCES caches(name), phrase TEXT NOT NULL, vector BLOB NOT NULL,
    PRIMARY KEY (cache, phrase)
) STRICT;
CREATE TABLE calibration_scores (
    cache TEXT PRIMARY KEY REFERENCES caches(name), observation BLOB NOT NULL,
    detection BLOB NOT NULL, pair BLOB
) STRICT;
CREATE TABLE proposals (
    cache TEXT NOT NULL REFERENCES caches(name), id TEXT NOT NULL, state TEXT NOT NULL,
    count INTEGER NOT NULL, first_at REAL NOT NULL, last_at REAL NOT NULL, decided_at REAL,
    detail TEXT NOT NULL, PRIMARY KEY (cache, id)
) STRICT;
"""


class Store(WithIndexFiles):
    """The service's database and index files under ``data_dir``.

    Thread-safe: one connection, used under a lock. ``fsync=False`` runs SQLite
    with ``synchronous=OFF`` and skips the index files' fsync: faster, but a 2xx
    then survives only a process crash, not a power cut.
    """

    shared = False  # the only writer of its database: nothing to follow

    def __init__(self, data_dir: Path, *, fsync: bool = True, max_bytes: int = 0) -> None:
        """``max_bytes``: the most the database may grow to (0: the disk's size); a write
        past it is refused with ``StorageFull``, as on a full disk."""
        self.root = Path(data_dir)
        self.root.mkdir(mode=0o700, parents=True, exist_ok=True)
        self.root.chmod(0o700)  # the service's alone, an existing directory too
        self.path = self.root / DB_NAME
        self._fsync = fsync
        self.indexes = IndexFiles(self.root, fsync=fsync)
        self._max_bytes = max_bytes
        self._mutex = threading.Lock()
        self._lock_fd = take_lock(self.root / LOCK_NAME)
        try:
            self._db = self._connect()
        except BaseException:
            os.close(self._lock_fd)
            raise
        self._closed = False

    def _connect(self) -> sqlite3.Connection:
        # SQLite gives its -wal and -shm files the database file's mode: made 0600 first
        os.close(os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600))
        for path in (self.path, *(self.path.with_name(self.path.name + s)
                                  for s in ("-wal", "-shm"))):
            with contextlib.suppress(FileNotFoundError):
                path.chmod(0o600)
        db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        try:
            db.execute("PRAGMA journal_mode=WAL")
            db.execute(f"PRAGMA synchronous={'FULL' if self._fsync else 'OFF'}")
            db.execute("PRAGMA foreign_keys=ON")
            if self._max_bytes:
                page = db.execute("PRAGMA page_size").fetchone()[0]
                db.execute(f"PRAGMA max_page_count={max(1, self._max_bytes // page)}")
            check = db.execute("PRAGMA quick_check").fetchone()[0]
            if check != "ok":
                raise StorageCorrupt(self.path, f"integrity check failed: {check}")
            schema = db.execute("PRAGMA user_version").fetchone()[0]
            if schema == 0:
                db.executescript(f"BEGIN; {_SCHEMA} PRAGMA user_version={SCHEMA_VERSION}; COMMIT;")
            elif schema != SCHEMA_VERSION:
                raise StorageCorrupt(self.path, f"schema version {schema}; this build reads "
                                                f"{SCHEMA_VERSION} (start a new data directory "
                                                "and build the caches again, e.g. with aesop "
                                                "cache import)")
        except sqlite3.DatabaseError as exc:
            db.close()
            raise StorageCorrupt(self.path, str(exc)) from exc
        except BaseException:
            db.close()
            raise
        return db

    # -- reads -------------------------------------------------------------------

    def names(self) -> list[str]:
        with self._mutex:
            return [r[0] for r in self._db.execute("SELECT name FROM caches ORDER BY name")]

    def history(self, name: str) -> list[tuple[int, str, dict[str, Any]]]:
        """(version, op, detail) of every version of cache ``name``, oldest first."""
        with self._mutex:
            rows = self._db.execute("SELECT version, op, detail FROM changes WHERE cache = ? "
                                    "ORDER BY version", (name,)).fetchall()
        return [(v, op, json.loads(detail)) for v, op, detail in rows]

    def load(self, name: str) -> Cache:
        """Cache ``name`` as stored, its index from the newest usable index file."""
        with self._mutex:
            header = self._header(name)
            experiences = {
                label: rec.experience_of(*row) for label, *row in self._db.execute(
                    "SELECT label, id, text, metadata, detections FROM experiences "
                    "WHERE cache = ? ORDER BY label", (name,))
            }
            index = self._index(header, set(experiences))
            phrases = {phrase: rec.f4(vector) for phrase, vector in self._db.execute(
                "SELECT phrase, vector FROM detection_vectors WHERE cache = ?", (name,))}
            scores = rec.scores_of(self._db.execute(
                "SELECT observation, detection, pair FROM calibration_scores WHERE cache = ?",
                (name,)).fetchone())
        return Cache.restored(header, experiences, index, phrases, scores)

    def _header(self, name: str) -> Header:
        row = self._db.execute("SELECT config, version, next_label, calibration, stale "
                               "FROM caches WHERE name = ?", (name,)).fetchone()
        if row is None:
            raise KeyError(name)
        return rec.header_of(*row)

    def _index(self, header: Header, labels: set[int]) -> VectorIndex:
        config = header.config
        return self.indexes.restore(
            header, labels, lambda index, since: self._catch_up(index, config, since),
            lambda index: self._add_stored(index, config, ""))

    def _catch_up(self, index: VectorIndex, config: CacheConfig, since: int) -> None:
        """Bring an index saved at version ``since`` to the stored experiences."""
        deleted = [json.loads(d)["label"] for (d,) in self._db.execute(
            "SELECT detail FROM changes WHERE cache = ? AND op = 'delete' AND version > ?",
            (config.name, since))]
        if deleted:
            index.remove(np.array(deleted, dtype=np.int64))
        self._add_stored(index, config, f"AND version > {int(since)}")

    def _add_stored(self, index: VectorIndex, config: CacheConfig, where: str) -> None:
        rows = self._db.execute(f"SELECT label, vector FROM experiences WHERE cache = ? {where} "
                                "ORDER BY label", (config.name,))
        while batch := rows.fetchmany(65536):
            labels = np.fromiter((r[0] for r in batch), dtype=np.int64, count=len(batch))
            vectors = np.frombuffer(b"".join(r[1] for r in batch), dtype="<f4")
            index.add(vectors.reshape(len(batch), config.dim), labels)

    # -- writes ------------------------------------------------------------------

    def create(self, config: CacheConfig) -> Header:
        header = Header(config)
        with self._transaction(f"creating cache {config.name!r}") as db:
            db.execute("INSERT INTO caches VALUES (?, ?, ?, ?, ?, ?)",
                       (config.name, *_header_row(header)))
            _change(db, config.name, 0, "create", asdict(config))
        return header

    def commit(self, name: str, op: Op, header: Header, proposal: Proposal | None = None
               ) -> None:
        """Make ``op`` durable, with ``header`` (the cache's header once it is applied)
        and the ``proposal`` it accepts, if any."""
        with self._transaction(f"cache {name!r} version {op.version}") as db:
            _write_op(db, name, op)
            _update_header(db, name, header)
            if proposal is not None:
                _write_proposal(db, name, proposal)

    def save_proposal(self, name: str, proposal: Proposal) -> None:
        with self._transaction(f"proposal {proposal.id} of cache {name!r}") as db:
            _write_proposal(db, name, proposal)

    def proposals(self, name: str) -> list[Proposal]:
        """Cache ``name``'s proposals, oldest first."""
        with self._mutex:
            rows = self._db.execute(
                "SELECT id, state, count, first_at, last_at, decided_at, detail FROM proposals "
                "WHERE cache = ? ORDER BY first_at", (name,)).fetchall()
        return [rec.proposal_of(row) for row in rows]

    @contextlib.contextmanager
    def _transaction(self, what: str) -> Iterator[sqlite3.Connection]:
        with self._mutex:
            if self._closed:
                raise StorageError(f"{self.path}: the store is closed")
            try:
                self._db.execute("BEGIN IMMEDIATE")
                yield self._db
                self._db.execute("COMMIT")
            except sqlite3.Error as exc:
                with contextlib.suppress(sqlite3.Error):
                    self._db.execute("ROLLBACK")
                full = getattr(exc, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL
                kind = StorageFull if full else StorageError
                raise kind(f"{self.path}: {what} was not written ({exc})") from exc
            except BaseException:
                with contextlib.suppress(sqlite3.Error):
                    self._db.execute("ROLLBACK")
                raise

    # -- lifecycle -----------------------------------------------------------------

    def close(self) -> None:
        """Close the database and release the data directory; safe to call twice."""
        with self._mutex:
            if self._closed:
                return
            self._closed = True
            try:
                self._db.close()
            finally:
                os.close(self._lock_fd)


def _header_row(header: Header) -> tuple[str, int, int, str | None, int]:
    config, version, next_label, cal, stale = rec.header_row(header)
    return config, version, next_label, cal, int(stale)


def _update_header(db: sqlite3.Connection, name: str, header: Header) -> None:
    config, version, next_label, cal, stale = _header_row(header)
    db.execute("UPDATE caches SET config = ?, version = ?, next_label = ?, calibration = ?, "
               "stale = ? WHERE name = ?", (config, version, next_label, cal, stale, name))


def _change(db: sqlite3.Connection, name: str, version: int, op: str,
            detail: dict[str, Any]) -> None:
    db.execute("INSERT INTO changes VALUES (?, ?, ?, ?, ?)",
               (name, version, op, json.dumps(detail), time.time()))


def _write_proposal(db: sqlite3.Connection, name: str, proposal: Proposal) -> None:
    db.execute("INSERT OR REPLACE INTO proposals VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
               rec.proposal_row(name, proposal))


def _write_op(db: sqlite3.Connection, name: str, op: Op) -> None:
    if isinstance(op, Add):
        db.executemany("INSERT INTO experiences VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                       rec.experience_rows(name, op))
        db.executemany("INSERT INTO detection_vectors VALUES (?, ?, ?)",
                       ((name, *row) for row in rec.phrase_rows(op)))
    elif isinstance(op, Delete):
        db.execute("DELETE FROM experiences WHERE cache = ? AND label = ?", (name, op.label))
    elif isinstance(op, SetCalibration):
        db.execute("DELETE FROM calibration_scores WHERE cache = ?", (name,))
        if op.scores is not None:
            db.execute("INSERT INTO calibration_scores VALUES (?, ?, ?, ?)",
                       (name, *rec.score_blobs(op.scores)))
    _change(db, name, op.version, *rec.change_of(op))


def take_lock(path: Path) -> int:
    """An fd holding an exclusive flock on ``path``, or ``StorageError`` if it is held."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    os.fchmod(fd, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise StorageError(f"{path.parent} is in use by another process (pid {holder})"
                           ) from None
    except BaseException:
        os.close(fd)
        raise
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd
