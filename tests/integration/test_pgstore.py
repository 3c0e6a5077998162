"""The PostgreSQL store on a real PostgreSQL server (tests/postgres.py): the SQLite store's
round trips, plus what replicas need: one order of versions, following the change log, and
a server that goes away and comes back."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import psycopg
import pytest

from services.embedding.detector.cache import Cache, CacheConfig, CalibrationScores, Delete
from services.embedding.detector.calibration import loo_quantile
from services.embedding.detector.errors import Behind, StorageCorrupt, StorageError
from services.embedding.detector.proposals import Proposal
from services.embedding.storage.pgstore import PostgresStore
from shared.messages import Detection
from tests.unit.test_store import commit, commit_add, same, vectors
from tests.zenoh_peers import wait_until
from tools.stack.postgres import PostgresServer


def build(store: PostgresStore) -> Cache:
    """A cache through every kind of change, detections and pair scores included."""
    cache = Cache(CacheConfig("c", "m", 4, k=1))
    store.create(cache.config)
    seen = (Detection(label="a drill", where="on the ground", confidence=0.8),
            Detection(label="a red box"))
    phrases = {d.phrase: row for d, row in zip(seen, vectors(2, 4, 7), strict=True)}
    commit(store, cache, cache.plan_add(
        vectors(5, 4, 3), ids=[f"x{i}" for i in range(5)], texts=[None] * 5,
        metadata=[{"i": i} for i in range(5)],
        detections=[seen[: 1 + i % 2] for i in range(5)], detection_vectors=phrases))
    commit_add(store, cache, 6, seed=1)
    commit(store, cache, cache.plan_delete("e1-2"))
    obs, dets, pairs = cache.loo_scores(), cache.loo_detection_scores(), cache.loo_pair_scores()
    commit(store, cache, cache.plan_calibration(
        loo_quantile(obs, 0.9), CalibrationScores.of(obs, dets, pairs)))
    commit(store, cache, cache.plan_configure(k=2, score="topk"))
    return cache


def test_a_cache_round_trips_with_everything_it_holds(postgres_url: str, tmp_path: Path) -> None:
    with PostgresStore(postgres_url, tmp_path / "a") as store:
        cache = build(store)
    with PostgresStore(postgres_url, tmp_path / "b") as store:  # another replica, no files
        assert store.names() == ["c"]
        loaded = store.load("c")
        assert [(v, op) for v, op, _ in store.history("c")] == [
            (0, "create"), (1, "add"), (2, "add"), (3, "delete"), (4, "calibrate"),
            (5, "configure")]
    same(loaded, cache)
    assert loaded.header == cache.header
    assert loaded.detection_counts == cache.detection_counts
    assert loaded.pair_counts == cache.pair_counts
    kept, want = loaded.calibration_scores, cache.calibration_scores
    assert kept is not None and want is not None and kept.pair is not None
    assert want.pair is not None and kept.pair.tolist() == want.pair.tolist()
    assert kept.observation.tolist() == want.observation.tolist()
    np.testing.assert_array_equal(loaded.nominal_detections().vectors,
                                  cache.nominal_detections().vectors)


def test_a_replica_caught_up_from_the_change_log_is_the_stored_cache(
        postgres_url: str, tmp_path: Path) -> None:
    with PostgresStore(postgres_url, tmp_path / "a") as writer, \
            PostgresStore(postgres_url, tmp_path / "b") as follower:
        writer.create(CacheConfig("c", "m", 4, k=1))
        copy = follower.load("c")  # version 0
        cache = writer.load("c")
        commit_add(writer, cache, 4, seed=1)
        commit_add(writer, cache, 3, seed=2)
        commit(writer, cache, cache.plan_delete("e2-0"))
        commit(writer, cache, cache.plan_delete("e1-1"))
        commit(writer, cache, cache.plan_calibration(
            loo_quantile(cache.loo_scores(), 0.9)))
        ops, header = follower.changes_since("c", copy.version)
    assert [op.version for op, _ in ops] == [1, 2, 3, 4, 5]
    assert ops[1][0].labels == (5, 6)  # e2-0 is gone
    for op, _ in ops:
        if not (isinstance(op, Delete) and op.label not in copy.experiences):
            copy.apply(op)
    copy.header = header
    same(copy, cache)
    assert copy.header == cache.header


def test_a_write_planned_on_an_old_version_is_refused_and_nothing_is_written(
        postgres_url: str, tmp_path: Path) -> None:
    with PostgresStore(postgres_url, tmp_path / "a") as a, \
            PostgresStore(postgres_url, tmp_path / "b") as b:
        a.create(CacheConfig("c", None, 4, k=1))
        on_a, on_b = a.load("c"), b.load("c")
        commit_add(a, on_a, 2, seed=1)
        with pytest.raises(Behind, match="version 1, this one had 0"):
            commit_add(b, on_b, 2, seed=2)
        with pytest.raises(Behind):  # created meanwhile by the other
            b.create(CacheConfig("c", None, 4, k=1))
        assert on_b.size == 0
        assert b.load("c").size == 2 and [v for v, _, _ in b.history("c")] == [0, 1]


def test_every_write_is_told_to_the_listeners(postgres_url: str, tmp_path: Path) -> None:
    got: list[dict[str, object] | None] = []
    stop = threading.Event()
    with PostgresStore(postgres_url, tmp_path / "a") as a, \
            PostgresStore(postgres_url, tmp_path / "b") as b:
        listening = threading.Thread(target=b.listen, args=(stop, got.append), daemon=True)
        listening.start()
        wait_until(lambda: got == [None], "the listener's first resync", 10)
        a.create(CacheConfig("c", None, 4, k=1))
        cache = a.load("c")
        commit_add(a, cache, 1, seed=1)
        proposal = Proposal(id="p1", text="a scene", detections=(Detection(label="a box"),),
                            task="t", robot="r0", seq=1, request_id="q", model="m",
                            rationale="fine", score=0.5, p_value=None, count=1, first_at=1.0,
                            last_at=1.0)
        a.save_proposal("c", proposal)
        wait_until(lambda: len(got) == 4, "three notices", 10)
        stop.set()
        listening.join(5)
    assert got[1:] == [{"cache": "c", "version": 0, "origin": a.origin},
                       {"cache": "c", "version": 1, "origin": a.origin},
                       {"cache": "c", "proposal": "p1", "origin": a.origin}]
    with PostgresStore(postgres_url, tmp_path / "c") as c:
        assert c.proposal("c", "p1") == proposal and c.proposals("c") == [proposal]


def test_a_notice_that_is_not_a_writes_leaves_the_listener_going(
        postgres_url: str, tmp_path: Path) -> None:
    """Issue 43, finding 7: a NOTIFY payload that was not a JSON object killed every
    replica's listener thread (following fell back to polling, lag 0.9 -> 3.7-5.2 s). Each
    is dropped; the next write's notice still arrives, on the same thread."""
    got: list[dict[str, object] | None] = []
    stop = threading.Event()
    with PostgresStore(postgres_url, tmp_path / "b") as b, \
            psycopg.connect(postgres_url, autocommit=True) as db:
        listening = threading.Thread(target=b.listen, args=(stop, got.append), daemon=True)
        listening.start()
        wait_until(lambda: got == [None], "the listener's first resync", 10)
        for payload in ("not json", "[1, 2]", '"a string"', "null", "{broken",
                        '{"cache": 1}', '{"version": "x"}'):
            db.execute("SELECT pg_notify('aesop_embedding', %s)", (payload,))
        db.execute("SELECT pg_notify('aesop_embedding', %s)",
                   ('{"cache": "c", "version": 3, "origin": "elsewhere"}',))
        wait_until(lambda: len(got) >= 2, "the good notice after the bad ones", 10)
        assert listening.is_alive()
        stop.set()
        listening.join(5)
    assert got == [None, {"cache": "c", "version": 3, "origin": "elsewhere"}]


def test_a_server_that_goes_away_fails_calls_cleanly_and_is_reached_again(
        postgres_server: PostgresServer, postgres_url: str, tmp_path: Path) -> None:
    with PostgresStore(postgres_url, tmp_path / "a") as store:
        store.create(CacheConfig("c", None, 4, k=1))
        cache = store.load("c")
        postgres_server.stop(immediate=True)
        try:
            with pytest.raises(StorageError, match="PostgreSQL: cache 'c' version 1 failed"):
                commit_add(store, cache, 1, seed=1)
            assert cache.size == 0
            with pytest.raises(StorageError):
                store.names()
        finally:
            postgres_server.start()
        commit_add(store, cache, 1, seed=1)
        assert store.load("c").size == 1


def test_a_database_of_another_schema_version_is_refused(postgres_url: str,
                                                        tmp_path: Path) -> None:
    PostgresStore(postgres_url, tmp_path / "a").close()
    with psycopg.connect(postgres_url, autocommit=True) as db:
        db.execute("UPDATE aesop_schema SET version = 99")
    with pytest.raises(StorageCorrupt, match="schema version 99; this build reads 1"):
        PostgresStore(postgres_url, tmp_path / "b")


def test_the_url_and_its_password_stay_out_of_the_stores_repr(postgres_url: str,
                                                              tmp_path: Path) -> None:
    with PostgresStore(postgres_url, tmp_path / "a") as store:
        password = postgres_url.split(":")[2].split("@")[0]
        assert password not in repr(store)
