"""Read-only import of the storage format before SQLite (a WAL and a snapshot per cache).

``<data_dir>/caches/<name>/`` held ``snapshot.bin`` (the cache as of WAL seq N)
and ``wal.log`` (the records after it). The service imports each such directory
into its database once, on its first start, and leaves the files in place.

Formats (integers little-endian)::

    WAL record  = b"\\x89WL1" | seq u64 | payload length u32 | CRC32(payload) u32 | payload
    snapshot    = b"\\x89SNAP1\\r\\n" | payload length u64 | CRC32(payload) u32 | payload
    payload     = header length u32 | header JSON | raw array bytes

A snapshot's header is ``{"seq", "meta", "arrays"}``; a record's ``{"op", "arrays"}``;
``arrays`` describes each array (``name``, ``dtype``, ``shape``, ``offset``, ``nbytes``).
A bad last record with nothing intact after it is the torn tail of a crash and is
ignored; anything else that does not parse is ``StorageCorrupt``.
"""

from __future__ import annotations

import json
import logging
import math
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from .cache import Add, Cache, CacheConfig, Calibrate, Configure, Delete, Experience, Header, Op
from .calibration import Calibration
from .index import VectorIndex
from .store import StorageCorrupt

log = logging.getLogger(__name__)

LEGACY_DIR = "caches"
_WAL_MAGIC = b"\x89WL1"
_SNAPSHOT_MAGIC = b"\x89SNAP1\r\n"
_WAL_FRAME = struct.Struct("<4sQII")
_SNAPSHOT_FRAME = struct.Struct("<8sQI")
_U32 = struct.Struct("<I")
_MALFORMED = (ValueError, TypeError, KeyError, AttributeError, struct.error)

Payload = tuple[dict[str, Any], dict[str, np.ndarray]]


def legacy_caches(data_dir: Path) -> list[Path]:
    """The legacy cache directories under ``data_dir`` (those with a snapshot)."""
    root = Path(data_dir) / LEGACY_DIR
    if not root.is_dir():
        return []
    return sorted(d for d in root.iterdir() if (d / "snapshot.bin").is_file())


def read_legacy(directory: Path) -> Cache:
    """The cache in a legacy directory: its snapshot, then the WAL records after it."""
    snapshot_path, wal_path = directory / "snapshot.bin", directory / "wal.log"
    seq, meta, arrays = _read_snapshot(snapshot_path)
    try:
        cache = _from_snapshot(meta, arrays)
        for frame_seq, offset, payload in _scan_wal(wal_path):
            if frame_seq <= seq:
                continue
            if frame_seq != seq + 1:
                raise StorageCorrupt(wal_path, f"record at byte offset {offset} has seq "
                                               f"{frame_seq} after seq {seq}")
            head, rec_arrays = _decode(payload)
            cache.apply(_op(cache, head["op"], rec_arrays))
            seq = frame_seq
    except _MALFORMED as exc:
        raise StorageCorrupt(wal_path, f"a record is malformed: {exc}") from exc
    return cache


def _from_snapshot(meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> Cache:
    config = CacheConfig(**meta["config"])
    labels = arrays["labels"]
    index = VectorIndex(config.dim, config.index)
    if len(labels):
        index.add(arrays["vectors"], labels)
    experiences = {int(label): Experience(r["id"], r["text"], r["metadata"])
                   for label, r in zip(labels.tolist(), meta["experiences"], strict=True)}
    cal = meta["calibration"]
    header = Header(config, int(meta["version"]), int(meta["next_label"]),
                    None if cal is None else Calibration(**cal), bool(meta["stale"]))
    return Cache.restored(header, experiences, index)


def _op(cache: Cache, op: dict[str, Any], arrays: dict[str, np.ndarray]) -> Op:
    version = int(op["version"])
    kind = op["op"]
    if kind == "add":
        items = op["items"]
        return Add(tuple(int(it["label"]) for it in items),
                   tuple(Experience(it["id"], it["text"], it["metadata"]) for it in items),
                   arrays["vectors"], version)
    if kind == "delete":
        return Delete(op["id"], cache.labels_by_id[op["id"]], version)
    if kind == "calibrate":
        return Calibrate(Calibration(**op["calibration"]), version)
    if kind == "configure":
        return Configure(int(op["k"]), op["score"], version)
    raise ValueError(f"unknown operation {kind!r}")


def _decode(payload: bytes) -> Payload:
    (header_len,) = _U32.unpack_from(payload)
    start = _U32.size + header_len
    if start > len(payload):
        raise ValueError(f"header of {header_len} bytes runs past the payload")
    head = json.loads(payload[_U32.size:start])
    data = memoryview(payload)[start:]
    arrays: dict[str, np.ndarray] = {}
    for d in head.pop("arrays"):
        dtype, shape = np.dtype(d["dtype"]), tuple(map(int, d["shape"]))
        offset, nbytes = int(d["offset"]), int(d["nbytes"])
        if dtype.hasobject or nbytes != math.prod(shape) * dtype.itemsize \
                or offset < 0 or offset + nbytes > len(data):
            raise ValueError(f"array {d['name']!r} does not fit its descriptor")
        arrays[str(d["name"])] = np.frombuffer(data[offset:offset + nbytes], dtype=dtype
                                               ).reshape(shape).copy()
    return head, arrays


def _read_snapshot(path: Path) -> tuple[int, dict[str, Any], dict[str, np.ndarray]]:
    data = path.read_bytes()
    if len(data) < _SNAPSHOT_FRAME.size:
        raise StorageCorrupt(path, f"snapshot of {len(data)} bytes is shorter than its header")
    magic, length, crc = _SNAPSHOT_FRAME.unpack_from(data)
    payload = data[_SNAPSHOT_FRAME.size:]
    if magic != _SNAPSHOT_MAGIC or length != len(payload) or zlib.crc32(payload) != crc:
        raise StorageCorrupt(path, "bad magic, length or CRC: not an intact snapshot")
    try:
        head, arrays = _decode(payload)
        return int(head["seq"]), head["meta"], arrays
    except _MALFORMED as exc:
        raise StorageCorrupt(path, f"snapshot payload is malformed: {exc}") from exc


def _frame(data: bytes, offset: int) -> tuple[int, bytes] | None:
    """(seq, payload) of the intact record at ``offset``, or None."""
    if len(data) - offset < _WAL_FRAME.size:
        return None
    magic, seq, length, crc = _WAL_FRAME.unpack_from(data, offset)
    start = offset + _WAL_FRAME.size
    payload = data[start:start + length]
    if magic != _WAL_MAGIC or len(payload) != length or zlib.crc32(payload) != crc:
        return None
    return seq, payload


def _scan_wal(path: Path) -> list[tuple[int, int, bytes]]:
    """(seq, byte offset, payload) of the WAL's intact records; a torn tail is ignored."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return []
    records, offset = [], 0
    while offset < len(data):
        frame = _frame(data, offset)
        if frame is None:
            hit = data.find(_WAL_MAGIC, offset + 1)
            while hit != -1:
                if _frame(data, hit) is not None:
                    raise StorageCorrupt(path, f"bad record at byte offset {offset} is "
                                               f"followed by an intact one at {hit}")
                hit = data.find(_WAL_MAGIC, hit + 1)
            log.warning("%s: ignoring the torn tail at byte offset %d (%d bytes)",
                        path, offset, len(data) - offset)
            break
        records.append((frame[0], offset, frame[1]))
        offset += _WAL_FRAME.size + len(frame[1])
    return records
