"""The cache store: WAL + snapshot round trips, crash recovery and corruption, on real files."""

from __future__ import annotations

import logging
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from services.embedding.storage import (
    Array,
    CacheStore,
    Record,
    StorageCorrupt,
    StorageError,
)

WRITER = Path(__file__).with_name("storage_writer.py")
LOGGER = "services.embedding.storage"


def assert_same(got: Array, want: Array) -> None:
    """Same dtype, shape and bytes: exact, NaN payloads included."""
    assert got.dtype == want.dtype
    assert got.shape == want.shape
    assert got.tobytes() == want.tobytes()


def numbered(k: int) -> Record:
    return Record(op={"k": k}, arrays={"v": np.arange(3, dtype=np.float32) + k})


def ks(records: list[Record]) -> list[int]:
    return [r.op["k"] for r in records]


@pytest.fixture
def store(tmp_path: Path) -> Iterator[CacheStore]:
    with CacheStore(tmp_path) as s:
        s.load()
        yield s


def reopen(directory: Path) -> tuple[CacheStore, list[Record]]:
    s = CacheStore(directory)
    return s, s.load().records


def wal_with_three_records(directory: Path) -> list[int]:
    """Appends records 1..3 one per call; returns the byte offset of each."""
    with CacheStore(directory) as s:
        s.load()
        offsets = []
        for k in (1, 2, 3):
            offsets.append(s.wal_bytes)
            s.append([numbered(k)])
    return offsets


# --- round trips -------------------------------------------------------------------------------

ARRAYS: dict[str, Array] = {
    "f32_2d": np.array([[1.5, np.nan], [-0.0, np.inf]], dtype=np.float32),
    "f64_0d": np.array(3.25),
    "f16": np.array([1.0, 2.5, -7.0], dtype=np.float16),
    "i8_3d": np.arange(24, dtype=np.int8).reshape(2, 3, 4),
    "u64": np.array([0, 2**64 - 1], dtype=np.uint64),
    "bool": np.array([True, False, True]),
    "c128": np.array([1 + 2j, -3.5j]),
    "unicode": np.array(["ab", "ünï", ""]),
    "bytes": np.array([b"xy", b"\x00\xff"]),
    "datetime": np.array(["2024-01-01T00:00:00.123"], dtype="datetime64[ms]"),
    "empty": np.zeros((0, 384), dtype=np.float32),
    "fortran": np.asfortranarray(np.arange(6, dtype=np.int32).reshape(2, 3)),
    "strided": np.arange(10, dtype=np.int64)[::3],
}


def test_records_round_trip_with_arrays_of_many_dtypes_and_shapes(tmp_path: Path) -> None:
    with CacheStore(tmp_path) as s:
        assert s.load().records == []
        assert s.append([Record(op={"op": "add", "ids": [1, 2]}, arrays=ARRAYS)]) == 1
        assert s.append([Record(op={"op": "clear", "nested": {"x": None}})]) == 2

    s, records = reopen(tmp_path)
    s.close()
    assert [r.op for r in records] == [
        {"op": "add", "ids": [1, 2]},
        {"op": "clear", "nested": {"x": None}},
    ]
    assert list(records[0].arrays) == list(ARRAYS)
    for name, want in ARRAYS.items():
        assert_same(records[0].arrays[name], want)
    assert records[1].arrays == {}


def test_big_endian_arrays_come_back_little_endian_with_the_same_values(store: CacheStore) -> None:
    store.append([Record(op={}, arrays={"be": np.array([1, 256, -2], dtype=">i4")})])
    store.close()
    s, records = reopen(store.directory)
    s.close()
    assert_same(records[0].arrays["be"], np.array([1, 256, -2], dtype="<i4"))


def test_append_is_a_group_commit_returning_the_last_seq(store: CacheStore) -> None:
    assert store.append([numbered(1), numbered(2)]) == 2
    assert store.append([]) == 2
    assert store.append([numbered(3), numbered(4), numbered(5)]) == 5
    assert store.wal_bytes > 0
    store.close()
    s, records = reopen(store.directory)
    s.close()
    assert ks(records) == [1, 2, 3, 4, 5]


def test_records_that_cannot_be_stored_without_pickle_are_refused() -> None:
    with pytest.raises(TypeError, match="pickle"):
        Record(op={}, arrays={"o": np.array([{}], dtype=object)})
    with pytest.raises(TypeError, match="pickle"):
        Record(op={}, arrays={"s": np.zeros(2, dtype=[("a", "i4"), ("b", "f8")])})


def test_an_op_that_is_not_json_fails_before_anything_is_written(store: CacheStore) -> None:
    store.append([numbered(1)])
    with pytest.raises(TypeError):
        store.append([numbered(2), Record(op={"bad": object()})])
    assert store.append([numbered(2)]) == 2
    store.close()
    s, records = reopen(store.directory)
    s.close()
    assert ks(records) == [1, 2]


# --- snapshots ---------------------------------------------------------------------------------


def test_snapshot_then_appends_loads_the_snapshot_and_only_later_records(store: CacheStore) -> None:
    store.append([numbered(1), numbered(2)])
    store.append([numbered(3)])
    vectors = np.random.default_rng(0).standard_normal((3, 8)).astype(np.float32)
    store.write_snapshot({"name": "nominal", "n": 3}, {"vectors": vectors, "ids": np.arange(3)})
    assert store.wal_bytes == 0
    assert store.append([numbered(4), numbered(5)]) == 5
    store.close()

    s = CacheStore(store.directory)
    loaded = s.load()
    s.close()
    assert loaded.snapshot is not None
    assert loaded.snapshot.seq == 3
    assert loaded.snapshot.meta == {"name": "nominal", "n": 3}
    assert_same(loaded.snapshot.arrays["vectors"], vectors)
    assert_same(loaded.snapshot.arrays["ids"], np.arange(3))
    assert ks(loaded.records) == [4, 5]


def test_a_second_snapshot_replaces_the_first(store: CacheStore) -> None:
    store.append([numbered(1)])
    store.write_snapshot({"v": 1}, {})
    store.append([numbered(2)])
    store.write_snapshot({"v": 2}, {"a": np.ones(2)})
    store.close()
    s = CacheStore(store.directory)
    loaded = s.load()
    s.close()
    assert loaded.snapshot is not None
    assert (loaded.snapshot.meta, loaded.snapshot.seq, loaded.records) == ({"v": 2}, 2, [])
    assert not (store.directory / "snapshot.bin.tmp").exists()


@pytest.mark.parametrize("copied_after", [3, 2], ids=["wal-at-snapshot", "older-wal"])
def test_crash_between_snapshot_and_wal_reset_duplicates_nothing(
    tmp_path: Path, copied_after: int
) -> None:
    with CacheStore(tmp_path) as s:
        s.load()
        for k in (1, 2, 3):
            s.append([numbered(k)])
            if k == copied_after:
                old_wal = s.wal_path.read_bytes()
        s.write_snapshot({"k": 3}, {})
    (tmp_path / "wal.log").write_bytes(old_wal)  # the WAL as it was before the reset

    s = CacheStore(tmp_path)
    loaded = s.load()
    assert loaded.snapshot is not None and loaded.snapshot.seq == 3
    assert loaded.records == []
    assert s.append([numbered(4)]) == 4
    s.close()
    s, records = reopen(tmp_path)
    s.close()
    assert ks(records) == [4]


def test_a_leftover_temporary_snapshot_is_ignored_and_removed(tmp_path: Path) -> None:
    tmp = tmp_path / "snapshot.bin.tmp"
    tmp.write_bytes(b"half a snapshot")
    with CacheStore(tmp_path) as s:
        assert s.load().snapshot is None
    assert not tmp.exists()


# --- torn tails --------------------------------------------------------------------------------


@pytest.mark.parametrize("damage", ["cut-last-record", "cut-in-header", "garbage", "zeros"])
def test_a_torn_tail_is_a_warning_and_is_cut_at_the_next_append(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, damage: str
) -> None:
    offsets = wal_with_three_records(tmp_path)
    wal = tmp_path / "wal.log"
    data = wal.read_bytes()
    torn, survivors = {
        "cut-last-record": (data[:-5], [1, 2]),
        "cut-in-header": (data[: offsets[2] + 7], [1, 2]),
        "garbage": (data + b"\x89WL1 not a record", [1, 2, 3]),
        "zeros": (data + bytes(4096), [1, 2, 3]),
    }[damage]
    wal.write_bytes(torn)
    torn_at = offsets[2] if survivors == [1, 2] else len(data)

    with caplog.at_level(logging.WARNING, logger=LOGGER):
        s, records = reopen(tmp_path)
    assert ks(records) == survivors
    assert [r.levelno for r in caplog.records] == [logging.WARNING]
    assert str(wal) in caplog.text and f"byte offset {torn_at}" in caplog.text
    assert wal.read_bytes() == torn  # load itself writes nothing
    assert s.wal_bytes == torn_at

    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        assert s.append([numbered(len(survivors) + 1)]) == len(survivors) + 1
    assert "truncating" in caplog.text and f"byte offset {torn_at}" in caplog.text
    s.close()

    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        s, records = reopen(tmp_path)
    s.close()
    assert caplog.records == []
    assert ks(records) == [*survivors, len(survivors) + 1]
    assert_same(records[-1].arrays["v"], numbered(len(survivors) + 1).arrays["v"])


# --- corruption --------------------------------------------------------------------------------


@pytest.mark.parametrize("where", ["payload", "magic", "length"])
def test_a_bad_record_followed_by_good_ones_is_corruption(tmp_path: Path, where: str) -> None:
    offsets = wal_with_three_records(tmp_path)
    wal = tmp_path / "wal.log"
    data = bytearray(wal.read_bytes())
    at = offsets[1] + {"payload": 30, "magic": 1, "length": 12}[where]
    data[at] ^= 0x40
    wal.write_bytes(data)

    s = CacheStore(tmp_path)
    with pytest.raises(StorageCorrupt) as info:
        s.load()
    s.close()
    assert info.value.path == wal
    assert str(wal) in str(info.value) and f"byte offset {offsets[1]}" in str(info.value)
    assert wal.read_bytes() == data


def test_seqs_going_backwards_is_corruption(tmp_path: Path) -> None:
    offsets = wal_with_three_records(tmp_path)
    wal = tmp_path / "wal.log"
    data = wal.read_bytes()
    wal.write_bytes(data + data[: offsets[1]])  # record 1 again, intact

    with (
        CacheStore(tmp_path) as s,
        pytest.raises(StorageCorrupt, match="seq 1 after seq 3") as info,
    ):
        s.load()
    assert info.value.path == wal
    assert wal.read_bytes() == data + data[: offsets[1]]


def test_records_missing_before_the_wal_is_corruption(tmp_path: Path) -> None:
    with CacheStore(tmp_path) as s:
        s.load()
        s.append([numbered(1)])
        s.write_snapshot({}, {})
        s.append([numbered(2)])
    (tmp_path / "snapshot.bin").unlink()

    with CacheStore(tmp_path) as s, pytest.raises(StorageCorrupt, match="missing") as info:
        s.load()
    assert info.value.path == tmp_path / "wal.log"


@pytest.mark.parametrize("damage", ["flip", "truncate", "garbage", "empty"])
def test_a_corrupt_snapshot_is_corruption_naming_the_snapshot(tmp_path: Path, damage: str) -> None:
    with CacheStore(tmp_path) as s:
        s.load()
        s.append([numbered(1)])
        s.write_snapshot({"k": 1}, {"a": np.arange(100, dtype=np.float64)})
        s.append([numbered(2)])
    snapshot, wal = tmp_path / "snapshot.bin", tmp_path / "wal.log"
    data = bytearray(snapshot.read_bytes())
    if damage == "flip":
        data[len(data) // 2] ^= 0x01
    damaged = {
        "flip": bytes(data),
        "truncate": bytes(data[:-8]),
        "garbage": b"PK\x03\x04 not a snapshot at all",
        "empty": b"",
    }[damage]
    snapshot.write_bytes(damaged)
    wal_before = wal.read_bytes()

    with CacheStore(tmp_path) as s, pytest.raises(StorageCorrupt) as info:
        s.load()
    assert info.value.path == snapshot
    assert str(snapshot) in str(info.value)
    assert snapshot.read_bytes() == damaged
    assert wal.read_bytes() == wal_before


# --- locking and misuse ------------------------------------------------------------------------


def test_a_second_store_on_the_same_directory_is_refused(tmp_path: Path) -> None:
    first = CacheStore(tmp_path)
    with pytest.raises(StorageError, match="in use"):
        CacheStore(tmp_path)
    first.close()
    CacheStore(tmp_path).close()


def test_writes_need_load_first_and_an_open_store(tmp_path: Path) -> None:
    s = CacheStore(tmp_path / "a" / "b")  # parents are created
    with pytest.raises(StorageError, match="load"):
        s.append([numbered(1)])
    s.load()
    with pytest.raises(StorageError, match="already"):
        s.load()
    s.close()
    s.close()
    with pytest.raises(StorageError, match="closed"):
        s.append([numbered(1)])


def test_fsync_off_still_round_trips(tmp_path: Path) -> None:
    with CacheStore(tmp_path, fsync=False) as s:
        s.load()
        s.append([numbered(1)])
        s.write_snapshot({}, {})
        s.append([numbered(2)])
    s, records = reopen(tmp_path)
    s.close()
    assert ks(records) == [2]


# --- a real crash ------------------------------------------------------------------------------

ACKS_BEFORE_KILL = 200


def test_acknowledged_records_survive_sigkill(tmp_path: Path) -> None:
    child = subprocess.Popen(
        [sys.executable, str(WRITER), str(tmp_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    watchdog = threading.Timer(60, child.kill)  # a hung child ends the read loop below
    watchdog.start()
    acks: list[int] = []
    try:
        assert child.stdout is not None
        for line in child.stdout:
            acks.append(int(line))
            if len(acks) == ACKS_BEFORE_KILL:
                child.send_signal(signal.SIGKILL)  # while it is still appending
                break
    finally:
        watchdog.cancel()
        child.kill()
        _, stderr = child.communicate()
    assert len(acks) == ACKS_BEFORE_KILL, stderr
    assert child.returncode == -signal.SIGKILL

    with CacheStore(tmp_path) as s:
        loaded = s.load()
        base = loaded.snapshot.seq if loaded.snapshot else 0
        if loaded.snapshot:
            assert loaded.snapshot.meta == {"k": base}
            assert_same(loaded.snapshot.arrays["ks"], np.arange(1, base + 1))
        for seq, record in enumerate(loaded.records, start=base + 1):  # no gaps
            assert record.op == {"k": seq}
            assert_same(record.arrays["v"], np.full(4096, seq, dtype=np.int64))
        last = base + len(loaded.records)
        assert last >= acks[-1]
        assert s.append([Record(op={"k": last + 1})]) == last + 1

    s, records = reopen(tmp_path)
    s.close()
    assert records[-1].op == {"k": last + 1}
