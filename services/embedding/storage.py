"""Durable storage for one named cache: a write-ahead log plus atomic snapshots.

The store is generic: it keeps opaque records (a JSON-able ``op`` plus named
numpy arrays) and snapshots (JSON-able ``meta`` plus named arrays), and knows
nothing about caches. One directory per cache, one writer per directory.

Exceptions::

    StorageError        misuse, a lock held elsewhere, or a failed write
    └── StorageCorrupt  a file that cannot be trusted; ``.path`` names it

Files in the directory::

    LOCK                 flock'd by the single writer (holds its pid)
    wal.log              the records appended since the last snapshot
    snapshot.bin         the latest snapshot
    snapshot.bin.tmp     a snapshot being written (a crash leftover; removed by load)

Formats (integers little-endian)::

    WAL record  = b"\\x89WL1" | seq u64 | payload length u32 | CRC32(payload) u32 | payload
    snapshot    = b"\\x89SNAP1\\r\\n" | payload length u64 | CRC32(payload) u32 | payload
    payload     = header length u32 | header JSON (UTF-8) | raw array bytes

The header is ``{"op": ...}`` in a WAL record and ``{"seq": ..., "meta": ...}``
in a snapshot, plus ``"arrays": [{"name", "dtype", "shape", "offset",
"nbytes"}, ...]``: ``dtype`` is numpy's dtype string, always little-endian;
``offset`` counts from the first byte after the header; bytes are in C order.
No pickle anywhere: object and structured dtypes are refused.

Crash safety: ``append`` writes its records with one ``write`` and one
``fsync`` (group commit) before it returns. A snapshot records the last seq
it covers, goes to a temporary file that is fsync'd and renamed over the old
one (then the directory is fsync'd), and only then is the WAL truncated; on
load, WAL records with ``seq <= snapshot.seq`` are skipped, so a crash between
the rename and the truncation loses and duplicates nothing. A torn tail (a bad
last record with nothing intact after it) is what a crash during ``append``
leaves: ``load`` logs a warning and the next write cuts it off. Anything else
that fails to parse, or seqs that do not count up by one, is corruption:
``StorageCorrupt`` is raised and the files are left untouched.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import math
import os
import struct
import threading
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO, NoReturn

import numpy as np
import numpy.typing as npt

log = logging.getLogger(__name__)

Array = npt.NDArray[Any]

LOCK_NAME = "LOCK"
WAL_NAME = "wal.log"
SNAPSHOT_NAME = "snapshot.bin"

_WAL_MAGIC = b"\x89WL1"
_SNAPSHOT_MAGIC = b"\x89SNAP1\r\n"
_WAL_FRAME = struct.Struct("<4sQII")  # magic, seq, payload length, CRC32 of payload
_SNAPSHOT_FRAME = struct.Struct("<8sQI")  # magic, payload length, CRC32 of payload
_U32 = struct.Struct("<I")


class StorageError(Exception):
    """Misuse of a store, a lock held by another writer, or a failed write."""


class StorageCorrupt(StorageError):
    """A file on disk that cannot be trusted; it is left as it is for inspection."""

    def __init__(self, path: Path, detail: str) -> None:
        super().__init__(f"{path}: {detail}")
        self.path = path


@dataclass(frozen=True, eq=False)
class Record:
    """One WAL entry: a JSON-able ``op`` and named arrays stored as raw bytes."""

    op: dict[str, Any]
    arrays: Mapping[str, Array] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.op, dict):
            raise TypeError(f"Record.op must be a dict, not {type(self.op).__name__}")
        _check_arrays(self.arrays)


@dataclass(frozen=True, eq=False)
class Snapshot:
    """The caller's state as of WAL sequence number ``seq`` (0: before any record)."""

    meta: dict[str, Any]
    arrays: dict[str, Array]
    seq: int


@dataclass(frozen=True)
class Loaded:
    """What ``load`` found: the snapshot, then the WAL records after it, in order."""

    snapshot: Snapshot | None
    records: list[Record]


class CacheStore:
    """The WAL and snapshot of one cache, in its own directory.

    Takes an exclusive lock on the directory; call :meth:`load` once, then
    :meth:`append` and :meth:`write_snapshot`; :meth:`close` (or ``with``)
    releases the lock. ``fsync=False`` skips every fsync: faster, but an
    acknowledged record then survives only a process crash, not a power cut.
    """

    def __init__(self, directory: Path, *, fsync: bool = True) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self._fsync = fsync
        self._lock_fd = _take_lock(self.directory / LOCK_NAME)
        self._mutex = threading.Lock()
        self._wal: BinaryIO | None = None  # opened by load()
        self._last_seq = 0
        self._wal_bytes = 0
        self._cut: tuple[int, str] | None = None  # WAL offset to cut back to, and why
        self._failure: OSError | None = None
        self._closed = False

    @property
    def wal_path(self) -> Path:
        return self.directory / WAL_NAME

    @property
    def snapshot_path(self) -> Path:
        return self.directory / SNAPSHOT_NAME

    @property
    def wal_bytes(self) -> int:
        """Size of the WAL's intact records, torn or superseded bytes excluded."""
        return self._wal_bytes

    def load(self) -> Loaded:
        """Read the snapshot and the WAL records after it; raises ``StorageCorrupt``."""
        with self._mutex:
            self._check_usable()
            if self._wal is not None:
                raise StorageError(f"{self.directory}: load() was already called")
            snapshot = _read_snapshot(self.snapshot_path)
            base = snapshot.seq if snapshot else 0
            frames, end, size = _scan_wal(self.wal_path)
            _check_seqs(frames, base, self.wal_path)
            records = [_decode_record(f, self.wal_path) for f in frames if f.seq > base]
            self._last_seq = max([base, *(f.seq for f in frames)])
            if frames and frames[-1].seq <= base:
                self._cut = (0, "records the snapshot already covers")
            elif end < size:
                self._cut = (end, f"the torn tail at byte offset {end}")
            self._wal_bytes = self._cut[0] if self._cut else end
            self._open_wal()
            _remove_leftover(self.snapshot_path.with_name(SNAPSHOT_NAME + ".tmp"))
            return Loaded(snapshot, records)

    def append(self, records: Sequence[Record]) -> int:
        """Write ``records`` and fsync once; returns the seq of the last one."""
        with self._mutex:
            wal = self._writable()
            first = self._last_seq + 1
            data = b"".join(_wal_frame(seq, r) for seq, r in enumerate(records, first))
            if not data:
                return self._last_seq
            try:
                self._apply_cut(wal)
                wal.write(data)
                wal.flush()
                self._sync(wal.fileno())
            except OSError as exc:
                self._fail(exc, "append failed")
            self._last_seq += len(records)
            self._wal_bytes += len(data)
            return self._last_seq

    def write_snapshot(self, meta: dict[str, Any], arrays: Mapping[str, Array]) -> None:
        """Atomically replace the snapshot with one covering every record so far, reset the WAL."""
        with self._mutex:
            wal = self._writable()
            if not isinstance(meta, dict):
                raise TypeError(f"snapshot meta must be a dict, not {type(meta).__name__}")
            _check_arrays(arrays)
            parts = _encode({"seq": self._last_seq, "meta": meta}, arrays)
            tmp = self.snapshot_path.with_name(SNAPSHOT_NAME + ".tmp")
            try:
                self._replace_file(self.snapshot_path, tmp, parts)
            except OSError as exc:
                with contextlib.suppress(OSError):
                    tmp.unlink(missing_ok=True)
                raise StorageError(f"{self.snapshot_path}: snapshot failed, WAL kept") from exc
            try:
                self._apply_cut(wal)  # logs a torn tail it drops, if one is pending
                os.ftruncate(wal.fileno(), 0)
                self._sync(wal.fileno())
            except OSError as exc:
                self._fail(exc, "resetting the WAL after a snapshot failed")
            self._cut = None
            self._wal_bytes = 0

    def close(self) -> None:
        """Close the WAL and release the directory lock; safe to call twice."""
        with self._mutex:
            if self._closed:
                return
            self._closed = True
            try:
                if self._wal is not None:
                    self._wal.close()
            finally:
                os.close(self._lock_fd)

    def __enter__(self) -> CacheStore:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _check_usable(self) -> None:
        if self._closed:
            raise StorageError(f"{self.directory}: the store is closed")
        if self._failure is not None:
            raise StorageError(
                f"{self.directory}: an earlier write failed ({self._failure}); reopen the store"
            )

    def _writable(self) -> BinaryIO:
        self._check_usable()
        if self._wal is None:
            raise StorageError(f"{self.directory}: call load() before writing")
        return self._wal

    def _fail(self, exc: OSError, what: str) -> NoReturn:
        """Refuse further writes: the WAL's tail is unknown after a failed write."""
        self._failure = exc
        raise StorageError(f"{self.wal_path}: {what}; the store must be reopened") from exc

    def _open_wal(self) -> None:
        created = not self.wal_path.exists()
        self._wal = open(self.wal_path, "ab")  # noqa: SIM115 - held until close()
        if created:
            self._sync_directory()

    def _apply_cut(self, wal: BinaryIO) -> None:
        if self._cut is None:
            return
        offset, why = self._cut
        log.warning(
            "%s: truncating %s (cutting back to byte offset %d)", self.wal_path, why, offset
        )
        os.ftruncate(wal.fileno(), offset)
        self._cut = None

    def _replace_file(self, path: Path, tmp: Path, parts: list[bytes | memoryview]) -> None:
        crc = 0
        for part in parts:
            crc = zlib.crc32(part, crc)
        with open(tmp, "wb") as f:
            f.write(_SNAPSHOT_FRAME.pack(_SNAPSHOT_MAGIC, sum(len(p) for p in parts), crc))
            for part in parts:
                f.write(part)
            f.flush()
            self._sync(f.fileno())
        os.replace(tmp, path)
        self._sync_directory()

    def _sync(self, fd: int) -> None:
        if self._fsync:
            os.fsync(fd)

    def _sync_directory(self) -> None:
        if not self._fsync:
            return
        fd = os.open(self.directory, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@dataclass(frozen=True)
class _Frame:
    """One intact WAL record as read from disk."""

    offset: int
    seq: int
    payload: bytes

    @property
    def end(self) -> int:
        return self.offset + _WAL_FRAME.size + len(self.payload)


def _take_lock(path: Path) -> int:
    """An fd holding an exclusive flock on ``path``, or ``StorageError`` if it is held."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise StorageError(
            f"{path.parent} is in use: another CacheStore (pid {holder}) holds {path}"
        ) from None
    except BaseException:
        os.close(fd)
        raise
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd


def _check_arrays(arrays: Mapping[str, Array]) -> None:
    for name, array in arrays.items():
        if not isinstance(name, str):
            raise TypeError(f"array names must be str, not {name!r}")
        if not isinstance(array, np.ndarray):
            raise TypeError(f"array {name!r} is a {type(array).__name__}, not a numpy array")
        if array.dtype.hasobject or array.dtype.fields is not None or array.dtype.itemsize == 0:
            raise TypeError(f"array {name!r}: dtype {array.dtype} cannot be stored without pickle")


def _encode(head: dict[str, Any], arrays: Mapping[str, Array]) -> list[bytes | memoryview]:
    """A payload in parts: header length, header JSON, each array's raw bytes."""
    descriptors: list[dict[str, Any]] = []
    blobs: list[bytes | memoryview] = []
    offset = 0
    for name, array in arrays.items():
        little = array.astype(array.dtype.newbyteorder("<"), order="C", copy=False)
        blob = little.reshape(-1).view(np.uint8).data  # a memoryview of the bytes
        descriptors.append(
            {
                "name": name,
                "dtype": little.dtype.str,
                "shape": list(array.shape),
                "offset": offset,
                "nbytes": blob.nbytes,
            }
        )
        blobs.append(blob)
        offset += blob.nbytes
    header = json.dumps({**head, "arrays": descriptors}, separators=(",", ":")).encode()
    return [_U32.pack(len(header)), header, *blobs]


def _decode(payload: bytes) -> tuple[dict[str, Any], dict[str, Array]]:
    """Inverse of ``_encode``; raises ValueError, TypeError, KeyError... when malformed."""
    (header_len,) = _U32.unpack_from(payload)
    data_start = _U32.size + header_len
    if data_start > len(payload):
        raise ValueError(f"header of {header_len} bytes runs past the payload")
    head = json.loads(payload[_U32.size : data_start])
    data = memoryview(payload)[data_start:]
    arrays: dict[str, Array] = {}
    for d in head.pop("arrays"):
        name, dtype, shape = str(d["name"]), np.dtype(d["dtype"]), tuple(map(int, d["shape"]))
        start, nbytes = int(d["offset"]), int(d["nbytes"])
        if dtype.hasobject or dtype.fields is not None:
            raise ValueError(f"array {name!r} has dtype {dtype}, which is never written")
        if nbytes != math.prod(shape) * dtype.itemsize or start < 0 or start + nbytes > len(data):
            raise ValueError(f"array {name!r} does not fit its descriptor or the payload")
        raw = data[start : start + nbytes]
        arrays[name] = np.frombuffer(raw, dtype=dtype).reshape(shape).copy()
    return head, arrays


_MALFORMED = (ValueError, TypeError, KeyError, AttributeError, struct.error)


def _wal_frame(seq: int, record: Record) -> bytes:
    payload = b"".join(_encode({"op": record.op}, record.arrays))
    if len(payload) >= 2**32:
        raise ValueError(f"record of {len(payload)} bytes is too large for one WAL frame")
    return _WAL_FRAME.pack(_WAL_MAGIC, seq, len(payload), zlib.crc32(payload)) + payload


def _read_frame(data: bytes, offset: int) -> _Frame | str:
    """The intact WAL record at ``offset``, or why there is none."""
    if len(data) - offset < _WAL_FRAME.size:
        return "incomplete record header"
    magic, seq, length, crc = _WAL_FRAME.unpack_from(data, offset)
    if magic != _WAL_MAGIC:
        return "bad magic"
    start = offset + _WAL_FRAME.size
    if start + length > len(data):
        return f"payload of {length} bytes runs past the end of the file"
    payload = data[start : start + length]
    if zlib.crc32(payload) != crc:
        return "CRC mismatch"
    return _Frame(offset, seq, payload)


def _scan_wal(path: Path) -> tuple[list[_Frame], int, int]:
    """The WAL's intact records, the offset where they end, and the file size."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return [], 0, 0
    frames: list[_Frame] = []
    offset = 0
    while offset < len(data):
        frame = _read_frame(data, offset)
        if isinstance(frame, str):
            _refuse_if_intact_after(data, offset, frame, path)
            log.warning(
                "%s: torn tail at byte offset %d (%s; %d bytes), cut off at the next write",
                path,
                offset,
                frame,
                len(data) - offset,
            )
            break
        frames.append(frame)
        offset = frame.end
    return frames, offset, len(data)


def _refuse_if_intact_after(data: bytes, bad: int, why: str, path: Path) -> None:
    """A bad record is a torn tail only if no intact record follows it."""
    hit = data.find(_WAL_MAGIC, bad + 1)
    while hit != -1:
        if isinstance(_read_frame(data, hit), _Frame):
            raise StorageCorrupt(
                path,
                f"bad record at byte offset {bad} ({why}) "
                f"is followed by an intact record at byte offset {hit}",
            )
        hit = data.find(_WAL_MAGIC, hit + 1)


def _check_seqs(frames: list[_Frame], base: int, path: Path) -> None:
    """Seqs count up by one and leave no gap after the snapshot's ``base``."""
    if frames and not 1 <= frames[0].seq <= base + 1:
        raise StorageCorrupt(
            path,
            f"first record (byte offset 0) has seq {frames[0].seq}, but the snapshot "
            f"covers seqs up to {base}: records are missing",
        )
    for before, frame in zip(frames, frames[1:], strict=False):
        if frame.seq != before.seq + 1:
            raise StorageCorrupt(
                path,
                f"record at byte offset {frame.offset} has seq {frame.seq} after seq {before.seq}",
            )


def _decode_record(frame: _Frame, path: Path) -> Record:
    try:
        head, arrays = _decode(frame.payload)
        return Record(op=head["op"], arrays=arrays)
    except _MALFORMED as exc:
        raise StorageCorrupt(
            path, f"record at byte offset {frame.offset} is malformed: {exc}"
        ) from exc


def _read_snapshot(path: Path) -> Snapshot | None:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None
    if len(data) < _SNAPSHOT_FRAME.size:
        raise StorageCorrupt(path, f"snapshot of {len(data)} bytes is shorter than its header")
    magic, length, crc = _SNAPSHOT_FRAME.unpack_from(data)
    payload = data[_SNAPSHOT_FRAME.size :]
    if magic != _SNAPSHOT_MAGIC:
        raise StorageCorrupt(path, "bad magic at byte offset 0: not a snapshot")
    if length != len(payload):
        raise StorageCorrupt(path, f"header says {length} payload bytes, file has {len(payload)}")
    if zlib.crc32(payload) != crc:
        raise StorageCorrupt(path, "CRC mismatch in the payload")
    try:
        head, arrays = _decode(payload)
        seq, meta = head["seq"], head["meta"]
        if not isinstance(seq, int) or seq < 0 or not isinstance(meta, dict):
            raise ValueError(f"bad seq {seq!r} or meta of type {type(meta).__name__}")
    except _MALFORMED as exc:
        raise StorageCorrupt(path, f"snapshot payload is malformed: {exc}") from exc
    return Snapshot(meta=meta, arrays=arrays, seq=seq)


def _remove_leftover(tmp: Path) -> None:
    if tmp.exists():
        log.info("%s: removing a snapshot left half-written by a crash", tmp)
        tmp.unlink()
