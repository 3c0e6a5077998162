"""The SQLite store: round trips, version history, index files, limits, corruption, schema."""

from __future__ import annotations

import logging
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from services.embedding.detector.cache import Cache, CacheConfig, CalibrationScores, Op
from services.embedding.detector.calibration import loo_quantile
from services.embedding.schemas import CacheInfo
from services.embedding.storage.store import (
    DB_NAME,
    StorageCorrupt,
    StorageError,
    StorageFull,
    Store,
)
from shared.messages import Detection

LOGGER = "services.embedding"  # the store and its index files (.indexfiles)


def vectors(n: int, dim: int = 4, seed: int = 0) -> np.ndarray:
    """Unit rows (the cache normalises what it stores; queries come normalised)."""
    x = np.random.default_rng(seed).standard_normal((n, dim)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def commit_add(store: Store, cache: Cache, n: int, seed: int, prefix: str = "e") -> None:
    op = cache.plan_add(vectors(n, cache.config.dim, seed),
                        ids=[f"{prefix}{seed}-{i}" for i in range(n)],
                        texts=[f"text {i}" for i in range(n)],
                        metadata=[{"i": i} for i in range(n)])
    store.commit(cache.name, op, cache.header.after(op))
    cache.apply(op)


def commit(store: Store, cache: Cache, op: Op | None) -> None:
    assert op is not None
    store.commit(cache.name, op, cache.header.after(op))
    cache.apply(op)


def same(a: Cache, b: Cache) -> None:
    assert CacheInfo.of(a) == CacheInfo.of(b)
    assert a.experiences == b.experiences
    q = vectors(5, a.config.dim, 99)
    assert [r.score for r in a.score(q, 2)] == pytest.approx([r.score for r in b.score(q, 2)])


@pytest.fixture
def cache(tmp_path: Path) -> Cache:
    with Store(tmp_path) as store:
        cache = Cache(CacheConfig("c", None, 4, k=1))
        store.create(cache.config)
        commit_add(store, cache, 6, seed=1)
        commit(store, cache, cache.plan_delete("e1-2"))
        commit(store, cache, cache.plan_calibration(loo_quantile(cache.loo_scores(), 0.9)))
        commit(store, cache, cache.plan_configure(k=2, score="topk"))
        return cache


def test_a_cache_round_trips_with_its_header_and_history(tmp_path: Path, cache: Cache) -> None:
    with Store(tmp_path) as store:
        assert store.names() == ["c"]
        loaded = store.load("c")
        same(loaded, cache)
        assert loaded.header == cache.header
        assert [(v, op) for v, op, _ in store.history("c")] == [
            (0, "create"), (1, "add"), (2, "delete"), (3, "calibrate"), (4, "configure")]
        commit_add(store, loaded, 1, seed=2)  # labels are never reused after a delete
        assert len(set(loaded.labels_by_id.values())) == loaded.size == 6
        assert max(loaded.labels_by_id.values()) == 6


def test_a_saved_index_is_loaded_and_caught_up_from_the_database(
        tmp_path: Path, cache: Cache, caplog: pytest.LogCaptureFixture) -> None:
    with Store(tmp_path) as store:
        store.save_index(cache)
        commit_add(store, cache, 3, seed=3)  # after the save: added and deleted
        commit(store, cache, cache.plan_delete("e1-0"))
        commit(store, cache, cache.plan_delete("e3-1"))
    with caplog.at_level(logging.INFO, LOGGER), Store(tmp_path) as store:
        loaded = store.load("c")
        assert store.saved_index("c") == (4, False)
    assert "caught up from version 4" in caplog.text
    same(loaded, cache)
    assert set(loaded.index.labels().tolist()) == set(cache.experiences)


def test_a_current_index_file_replaces_older_ones(tmp_path: Path, cache: Cache) -> None:
    with Store(tmp_path) as store:
        first = store.save_index(cache)
        commit_add(store, cache, 2, seed=4)
        second = store.save_index(cache)
        assert not first.exists() and second.name == f"v{cache.version}.faiss"
        assert store.saved_index("c") == (cache.version, False)


def test_a_damaged_index_file_is_ignored_and_the_index_rebuilt(
        tmp_path: Path, cache: Cache, caplog: pytest.LogCaptureFixture) -> None:
    with Store(tmp_path) as store:
        path = store.save_index(cache)
    path.write_bytes(path.read_bytes()[:40])
    (path.parent / "v9.faiss.tmp").write_bytes(b"half written")
    with caplog.at_level(logging.WARNING, LOGGER), Store(tmp_path) as store:
        same(store.load("c"), cache)
    assert f"not using {path}" in caplog.text
    assert not (path.parent / "v9.faiss.tmp").exists()


def test_an_hnsw_graph_is_saved_and_not_rebuilt_on_load(tmp_path: Path) -> None:
    with Store(tmp_path) as store:
        cache = Cache(CacheConfig("h", None, 8, index="hnsw"))
        store.create(cache.config)
        commit_add(store, cache, 200, seed=5)
        cache.score(vectors(1, 8), 3)  # builds the graph
        assert cache.index.graph_ready
        store.save_index(cache)
        assert store.saved_index("h") == (1, True)
    with Store(tmp_path) as store:
        loaded = store.load("h")
    assert loaded.index.graph_ready  # loaded, not waiting for a rebuild
    same(loaded, cache)


def test_a_write_past_the_size_limit_is_refused_whole_and_the_store_goes_on(
        tmp_path: Path) -> None:
    with Store(tmp_path, max_bytes=128 * 1024) as store:  # 32 pages, 17 of them the schema
        cache = Cache(CacheConfig("c", None, 64))
        store.create(cache.config)
        commit_add(store, cache, 10, seed=1)
        op = cache.plan_add(vectors(600, 64, 2), ids=[None] * 600, texts=[None] * 600,
                            metadata=[{}] * 600)
        with pytest.raises(StorageFull, match="was not written"):
            store.commit("c", op, cache.header.after(op))
        commit_add(store, cache, 2, seed=3)  # a small write still fits
    with Store(tmp_path) as store:
        loaded = store.load("c")
        same(loaded, cache)
        assert loaded.size == 12 and [v for v, _, _ in store.history("c")] == [0, 1, 2]


def test_a_second_store_on_the_same_directory_is_refused(tmp_path: Path) -> None:
    with Store(tmp_path), pytest.raises(StorageError, match="in use by another process"):
        Store(tmp_path)


@pytest.mark.parametrize("damage", ["header", "page"])
def test_a_damaged_database_is_refused_naming_it_and_left_untouched(
        tmp_path: Path, cache: Cache, damage: str) -> None:
    db = tmp_path / DB_NAME
    data = bytearray(db.read_bytes())
    if damage == "header":
        data[:16] = b"not a database!!"
    else:  # the last page (experiences' b-tree) overwritten with garbage
        page = sqlite3.connect(db).execute("PRAGMA page_size").fetchone()[0]
        data[-page:] = bytes(range(256)) * (page // 256)
    db.write_bytes(bytes(data))
    with pytest.raises(StorageCorrupt) as info:
        Store(tmp_path)
    assert info.value.path == db
    assert db.read_bytes() == bytes(data)


def test_a_database_from_a_newer_build_is_refused(tmp_path: Path) -> None:
    Store(tmp_path).close()
    with sqlite3.connect(tmp_path / DB_NAME) as db:
        db.execute("PRAGMA user_version=99")
    with pytest.raises(StorageCorrupt, match="schema version 99"):
        Store(tmp_path)


def test_detections_and_calibration_scores_round_trip(tmp_path: Path) -> None:
    with Store(tmp_path) as store:
        cache = Cache(CacheConfig("d", "m", 4, k=1))
        store.create(cache.config)
        seen = (Detection(label="a drill", where="on the ground", confidence=0.8),
                Detection(label="a red box"))
        phrases = {d.phrase: row for d, row in zip(seen, vectors(2, 4, 7), strict=True)}
        op = cache.plan_add(vectors(5, 4, 3), ids=[f"x{i}" for i in range(5)],
                            texts=[None] * 5, metadata=[{}] * 5,
                            detections=[seen[: 1 + i % 2] for i in range(5)],
                            detection_vectors=phrases)
        commit(store, cache, op)
        obs, dets = cache.loo_scores(), cache.loo_detection_scores()
        pairs = cache.loo_pair_scores()
        commit(store, cache, cache.plan_calibration(loo_quantile(obs, 0.9),
                                                    CalibrationScores.of(obs, dets, pairs)))
    with Store(tmp_path) as store:
        loaded = store.load("d")
    assert loaded.experiences == cache.experiences  # detections and all
    assert loaded.detection_counts == {"a drill on the ground": 5, "a red box": 2}
    assert loaded.pair_counts == {("a drill on the ground", "a red box"): 2}
    kept, want = loaded.calibration_scores, cache.calibration_scores
    assert kept is not None and want is not None and want.pair is not None
    assert kept.pair is not None and kept.pair.tolist() == want.pair.tolist()
    assert len(kept.pair) == 2  # the two experiences with both detections
    for got, wanted in [(kept.observation, want.observation), (kept.detection, want.detection)]:
        assert got.tolist() == wanted.tolist() and len(got) == 5
    np.testing.assert_array_equal(loaded.nominal_detections().vectors,
                                  cache.nominal_detections().vectors)


def test_a_database_of_an_older_schema_is_refused_naming_the_way_out(tmp_path: Path) -> None:
    Store(tmp_path).close()
    with sqlite3.connect(tmp_path / DB_NAME) as db:
        db.execute("PRAGMA user_version=1")
    with pytest.raises(StorageCorrupt, match="schema version 1; this build reads 3") as info:
        Store(tmp_path)
    assert "new data directory" in str(info.value)
    with sqlite3.connect(tmp_path / DB_NAME) as db:  # left as it was
        assert db.execute("PRAGMA user_version").fetchone()[0] == 1


def test_the_data_is_the_services_alone(tmp_path: Path) -> None:
    """Issue 26, finding 7: the database and index files were readable by every user of
    the machine (0644, in a 0755 directory). Now the data directory is 0700 (an existing
    one is tightened) and every file the store writes is 0600."""
    import os
    import stat

    data = tmp_path / "data"
    data.mkdir()
    data.chmod(0o755)
    with Store(data) as store:
        cache = Cache(CacheConfig("c", None, 4, k=1))
        store.create(cache.config)
        commit_add(store, cache, 3, seed=1)
        store.save_index(cache)
        paths = [data, *data.rglob("*")]
        modes = {str(p.relative_to(tmp_path)): stat.S_IMODE(os.stat(p).st_mode) for p in paths}
    assert any(p.endswith(".faiss") for p in modes) and any(p.endswith("-wal") for p in modes)
    loose = {p: oct(m) for p, m in modes.items()
             if m != (0o700 if (tmp_path / p).is_dir() else 0o600)}
    assert loose == {}
