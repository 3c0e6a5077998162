"""Cache planning/apply (the one mutation path) and the FAISS index wrapper."""

from __future__ import annotations

import numpy as np
import pytest

from services.embedding.cache import Cache, CacheConfig
from services.embedding.calibration import loo_quantile
from services.embedding.errors import Conflict, InvalidInput, NotFound
from services.embedding.index import VectorIndex


def unit(rows: list[list[float]]) -> np.ndarray:
    x = np.asarray(rows, dtype=np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def make(k: int = 1, score: str = "topk") -> Cache:
    return Cache(CacheConfig("c", "m", 3, k, score))  # type: ignore[arg-type]


def add(cache: Cache, rows: list[list[float]], ids: list[str] | None = None) -> None:
    n = len(rows)
    cache.apply(cache.plan_add(np.asarray(rows, dtype=np.float32), ids=ids or [None] * n,
                               texts=[f"t{i}" for i in range(n)], metadata=[{}] * n))


def test_topk_score_is_negated_mean_similarity_of_nearest() -> None:
    cache = make(k=2)
    add(cache, [[1, 0, 0], [0, 1, 0], [0, 0, 1]], ids=["x", "y", "z"])
    q = unit([[1, 1, 0]])
    (r,) = cache.score(q, k=2, neighbors=2)
    # cos to x and y is 1/sqrt(2) each: s = -(0.7071 + 0.7071) / 2
    assert r.score == pytest.approx(-1 / np.sqrt(2), abs=1e-6)
    assert {n.id for n in r.neighbors} == {"x", "y"}


def test_leave_one_out_never_scores_a_member_against_itself() -> None:
    cache = make(k=1)
    add(cache, [[1, 0, 0], [1, 0.1, 0], [0, 0, 1], [0, 0.1, 1]])
    loo = cache.loo_scores()
    # each point's nearest *other* point: cos between (1,0,0) and (1,.1,0) = 1/sqrt(1.01)
    assert loo == pytest.approx([-1 / np.sqrt(1.01)] * 4, abs=1e-6)
    tau = loo_quantile(loo, 0.5).threshold
    assert tau == pytest.approx(-1 / np.sqrt(1.01), abs=1e-6)


def test_planning_validates_without_changing_anything() -> None:
    cache = make()
    add(cache, [[1, 0, 0]], ids=["a"])
    before = (cache.version, cache.size, dict(cache.labels_by_id))
    bad = [
        (lambda: cache.plan_add(np.ones((1, 4), np.float32), ids=[None], texts=[None],
                                metadata=[{}]), Conflict, "vectors"),
        (lambda: cache.plan_add(np.array([[np.nan, 0, 0]], np.float32), ids=[None],
                                texts=[None], metadata=[{}]), InvalidInput, "vectors[0]"),
        (lambda: cache.plan_add(np.zeros((1, 3), np.float32), ids=[None], texts=[None],
                                metadata=[{}]), InvalidInput, "vectors[0]"),
        (lambda: cache.plan_add(np.ones((1, 3), np.float32), ids=["a"], texts=[None],
                                metadata=[{}]), Conflict, "items[0].id"),
        (lambda: cache.plan_delete("nope"), NotFound, "id"),
        (lambda: cache.score(unit([[1, 0, 0]]), k=2), Conflict, "k"),
        (lambda: cache.loo_scores(k=1), Conflict, "k"),
    ]
    for call, exc, field in bad:
        with pytest.raises(exc) as info:
            call()
        assert info.value.field == field
    assert (cache.version, cache.size, dict(cache.labels_by_id)) == before


def test_versions_and_staleness() -> None:
    cache = make()
    add(cache, [[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    v = cache.version
    cache.apply(cache.plan_calibration(loo_quantile(cache.loo_scores(), 0.9)))
    assert cache.version == v + 1 and not cache.stale and cache.threshold is not None
    add(cache, [[1, 1, 1]])
    assert cache.version == v + 2 and cache.stale
    assert cache.plan_configure(k=1, score="topk") is None  # nothing to change
    cache.apply(cache.plan_configure(k=2, score="topk"))  # type: ignore[arg-type]
    assert cache.config.k == 2 and cache.version == v + 3


def test_mahalanobis_cache_scores_far_points_higher() -> None:
    rng = np.random.default_rng(0)
    cache = Cache(CacheConfig("m", None, 3, 1, "mahalanobis"))
    pts = rng.normal([1, 0, 0], 0.05, size=(50, 3))
    add(cache, pts.tolist())
    near, far = cache.score(unit([[1, 0.01, 0], [0, 0, 1]]))
    assert far.score > near.score
    assert cache.loo_scores().shape == (50,)


def test_hnsw_index_matches_exact_search_and_survives_deletes() -> None:
    rng = np.random.default_rng(1)
    x = rng.standard_normal((2000, 16)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    labels = np.arange(2000, dtype=np.int64) * 7
    flat, hnsw = VectorIndex(16, "flat"), VectorIndex(16, "hnsw", ef_search=128)
    for index in (flat, hnsw):
        index.add(x, labels)
        index.remove(labels[:100])
    q = x[100:200]
    _, exact = flat.search(q, 5)
    _, approx = hnsw.search(q, 5)
    recall = np.mean([len(set(a) & set(e)) / 5 for a, e in zip(approx, exact, strict=True)])
    assert recall > 0.9
    assert not np.isin(approx, labels[:100]).any()  # deleted vectors are gone


def test_self_search_agrees_with_faiss() -> None:
    rng = np.random.default_rng(2)
    x = rng.standard_normal((300, 8)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    index = VectorIndex(8)
    index.add(x, np.arange(300, dtype=np.int64) + 1000)
    sims, labels = index.self_search(4, block=64)
    f_sims, f_labels = index.search_exact(x, 4)
    np.testing.assert_allclose(sims, f_sims, atol=1e-5)
    assert (labels[:, 0] == np.arange(300) + 1000).all()
