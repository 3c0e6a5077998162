"""Cache planning/apply (the one mutation path) and the FAISS index wrapper."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from services.embedding.detector.cache import Cache, CacheConfig, CalibrationScores, Detections
from services.embedding.detector.calibration import loo_quantile
from services.embedding.detector.errors import Conflict, InvalidInput, NotFound
from services.embedding.detector.index import VectorIndex
from shared.messages import Detection


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
    # cos to x and y is 1/sqrt(2) each, rounded to 4 decimals: s = -(0.7071 + 0.7071) / 2
    assert r.score == pytest.approx(-0.7071, abs=1e-12)
    assert {n.id for n in r.neighbors} == {"x", "y"}


def test_leave_one_out_never_scores_a_member_against_itself() -> None:
    cache = make(k=1)
    add(cache, [[1, 0, 0], [1, 0.1, 0], [0, 0, 1], [0, 0.1, 1]])
    loo = cache.loo_scores()
    # each point's nearest *other* point: cos between (1,0,0) and (1,.1,0) = 1/sqrt(1.01),
    # 0.99504 (rounded to 4 decimals: 0.995)
    assert loo == pytest.approx([-0.995] * 4, abs=1e-12)
    tau = loo_quantile(loo, 0.5).threshold
    assert tau == pytest.approx(-0.995, abs=1e-12)


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


# -- detections: the cache's nominal detections and the combined verdict ----------------

AXES = {"red box": [1, 0, 0], "drill": [0, 1, 0], "tire": [0.9, 0.1, 0],
        "keyboard": [0, 0, 1]}


def found(*labels: str) -> Detections:
    return Detections(tuple(labels), unit([AXES[x] for x in labels]))


def add_with(cache: Cache, scenes: list[tuple[list[float], tuple[str, ...]]]) -> None:
    n = len(scenes)
    cache.apply(cache.plan_add(
        np.asarray([v for v, _ in scenes], dtype=np.float32), ids=[None] * n,
        texts=[f"t{i}" for i in range(n)], metadata=[{}] * n,
        detections=[tuple(Detection(label=x) for x in labels) for _, labels in scenes],
        detection_vectors={x: unit([AXES[x]])[0] for x in AXES}))


def nominal_cache() -> Cache:
    cache = make(k=1)
    add_with(cache, [([1, 0.1 * i, 0], ("red box", "drill") if i % 2 else ("red box",))
                     for i in range(50)])
    return cache


def test_a_cache_keeps_its_distinct_detections_and_how_many_experiences_hold_each() -> None:
    cache = nominal_cache()
    assert cache.detection_counts == {"red box": 50, "drill": 25}
    assert cache.nominal_detections().labels == ("drill", "red box")
    assert set(cache.detection_vectors) == {"red box", "drill"}  # only the phrases it holds
    cache.apply(cache.plan_delete(cache.experiences[1].id))  # a scene with the drill
    assert cache.detection_counts == {"red box": 49, "drill": 24}


def test_a_plan_without_a_vector_for_a_new_detection_is_refused() -> None:
    cache = make()
    with pytest.raises(Conflict, match="no vector for detection 'a keyboard'"):
        cache.plan_add(np.ones((1, 3), np.float32), ids=[None], texts=[None], metadata=[{}],
                       detections=[(Detection(label="a keyboard"),)])
    assert cache.size == 0


def calibrate_both(cache: Cache, alpha: float = 0.9) -> None:
    obs, dets = cache.loo_scores(), cache.loo_detection_scores()
    cache.apply(cache.plan_calibration(loo_quantile(obs, alpha),
                                       CalibrationScores.of(obs, dets)))


def test_an_odd_detection_among_nominal_ones_is_named_with_its_nearest_and_p_value() -> None:
    cache = nominal_cache()
    calibrate_both(cache)
    near = unit([[1, 0.5, 0]])  # the whole observation is as nominal as can be
    (plain,) = cache.score(near)
    assert plain.is_anomaly is False and plain.p_value is None and plain.matches == ()
    (odd,) = cache.score(near, detections=[found("red box", "keyboard")])
    assert odd.is_anomaly is True
    assert odd.detection_score == pytest.approx(0.0, abs=1e-4)  # keyboard ⟂ everything
    (match,) = odd.matches  # the red box is seen as it is: not named
    assert match.detection == "keyboard" and match.similarity == pytest.approx(0, abs=1e-4)
    assert match.nearest in ("drill", "red box")
    # beyond all 50 calibration scores (-1: every nominal detection seen as it is): below
    # 1/(n+1), by how far it is on the way to the worst score, 1 (here half way: 0.75/51),
    # doubled by Bonferroni
    assert match.p_value == pytest.approx(0.75 / 51) and odd.p_value == pytest.approx(1.5 / 51)
    (seen,) = cache.score(near, detections=[found("red box", "drill")])
    assert seen.is_anomaly is False and seen.p_value == 1.0 and seen.matches == ()


def test_a_near_detection_is_named_but_judged_by_the_calibration() -> None:
    cache = nominal_cache()
    calibrate_both(cache)
    (tire,) = cache.score(unit([[1, 0.5, 0]]), detections=[found("red box", "tire")])
    (match,) = tire.matches
    assert match.nearest == "red box" and match.similarity == pytest.approx(0.9939, abs=1e-4)
    # every nominal detection is held by many scenes: their LOO scores are all -1, so a
    # detection not seen as it is gets the smallest p-value: flagged
    assert tire.is_anomaly is True


def test_without_detection_scores_in_the_calibration_the_verdict_is_the_threshold() -> None:
    cache = nominal_cache()
    cache.apply(cache.plan_calibration(loo_quantile(cache.loo_scores(), 0.9)))  # no scores
    (r,) = cache.score(unit([[1, 0.5, 0]]), detections=[found("red box", "keyboard")])
    assert r.is_anomaly is False and r.p_value is None  # score <= tau, as before
    assert [m.detection for m in r.matches] == ["keyboard"] and r.matches[0].p_value is None


def test_a_text_only_query_is_judged_exactly_as_before() -> None:
    cache = nominal_cache()
    calibrate_both(cache)
    q = unit([[1, 0.5, 0], [0, 0, 1], [1, 3, 0]])
    assert cache.calibration is not None
    for r in cache.score(q):
        assert r.is_anomaly == (r.score > cache.calibration.threshold) and r.p_value is None


# -- pairs: two nominal detections never seen together ----------------------------------

def paired_cache() -> Cache:
    """The red box is seen with the drill and with the keyboard, never the drill with the
    keyboard; every pair by many scenes."""
    cache = make(k=1)
    add_with(cache, [([1, 0.1 * i, 0], (("red box", "drill"), ("red box", "keyboard"),
                                        ("drill",))[i % 3]) for i in range(60)])
    return cache


def calibrate_pairs(cache: Cache, alpha: float = 0.9) -> None:
    obs, dets, pairs = cache.loo_scores(), cache.loo_detection_scores(), cache.loo_pair_scores()
    cache.apply(cache.plan_calibration(replace(loo_quantile(obs, alpha), pairs=True),
                                       CalibrationScores.of(obs, dets, pairs)))


def test_a_cache_counts_the_pairs_its_experiences_hold_and_forgets_deleted_ones() -> None:
    cache = paired_cache()
    assert cache.pair_counts == {("drill", "red box"): 20, ("keyboard", "red box"): 20}
    cache.apply(cache.plan_delete(cache.experiences[0].id))  # red box and drill
    assert cache.pair_counts[("drill", "red box")] == 19
    pairs = cache.nominal_pairs()
    labels = cache.nominal_detections().labels
    assert {(labels[a], labels[b]) for a, b in zip(pairs.first, pairs.second, strict=True)} \
        == {("drill", "red box"), ("keyboard", "red box")}


def test_two_nominal_detections_never_seen_together_are_flagged_and_named() -> None:
    cache = paired_cache()
    near = unit([[1, 0.5, 0]])
    calibrate_both(cache)  # without pairs: every detection is nominal, so is the scene
    (two,) = cache.score(near, detections=[found("drill", "keyboard")])
    assert two.is_anomaly is False and two.pair is None and two.pair_score is None
    calibrate_pairs(cache)
    (odd,) = cache.score(near, detections=[found("drill", "keyboard")])
    assert odd.is_anomaly is True and odd.matches == ()  # each is nominal on its own
    assert odd.pair is not None and odd.pair.detections == ("drill", "keyboard")
    assert odd.pair.nearest in (("drill", "red box"), ("keyboard", "red box"))
    assert odd.pair.similarity == pytest.approx(0.0, abs=1e-4)
    # 40 scenes with a pair, each pair held by many (-1): beyond them all, half way to the
    # worst score (0.75/41), times three
    assert odd.pair.p_value == pytest.approx(0.75 / 41)
    assert odd.p_value == pytest.approx(2.25 / 41)
    (seen,) = cache.score(near, detections=[found("keyboard", "red box")])
    assert seen.is_anomaly is False and seen.pair is None and seen.pair_score == -1.0
    (one,) = cache.score(near, detections=[found("drill")])  # no pair: still three tests
    assert one.is_anomaly is False and one.pair_score is None and one.p_value == 1.0
