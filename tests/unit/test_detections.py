"""Per-detection scores and the combined conformal p-value (issue 12, part 1's math)."""

from __future__ import annotations

import numpy as np

from services.embedding.detector.detections import (
    NominalDetections,
    combined_p,
    distinct,
    embedded_form,
    loo_pair_scores,
    loo_scores,
    p_values,
    pairs_of,
    similarities,
    worst,
    worst_pair,
)


def unit(*rows: list[float]) -> np.ndarray:
    x = np.array(rows, dtype=np.float64)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


NOMINAL = NominalDetections(("a drill", "a tire", "a ball"),
                            unit([1, 0, 0], [0, 1, 0], [0, 0, 1]), np.array([3, 2, 1]))


def test_distinct_detections_count_observations_not_repeats() -> None:
    labels, counts = distinct([["a drill", "a tire", "a drill"], ["a drill"], []])
    assert labels == ["a drill", "a tire"] and counts.tolist() == [2, 1]


def test_the_worst_detection_names_itself_and_its_nearest_nominal() -> None:
    got = worst(NOMINAL, unit([1, 0, 0], [0.6, 0.8, 0]))  # a drill, and something tire-like
    assert got is not None
    assert (got.detection, got.nearest) == (1, 1)
    assert np.isclose(got.similarity, 0.8) and np.isclose(got.score, -0.8)
    assert worst(NOMINAL, np.zeros((0, 3))) is None


def test_leave_one_out_drops_only_what_no_other_observation_holds() -> None:
    # observation 0 holds the drill (3 holders) and the ball (it alone)
    scores = loo_scores(NOMINAL, [[0, 2], [1], []], NOMINAL.vectors)
    assert np.isclose(scores[0], 0.0)  # the ball, without itself, is orthogonal to the rest
    assert np.isclose(scores[1], -1.0)  # the tire has another holder: it matches itself
    assert np.isnan(scores[2])


def test_p_values_are_conformal_ranks() -> None:
    cal = np.array([0.1, 0.2, 0.3, np.nan])  # NaN: a calibration item without detections
    p = p_values(cal, np.array([0.05, 0.2, 0.25, 0.3, np.nan]))
    assert np.allclose(p[:4], [4 / 4, 3 / 4, 2 / 4, 2 / 4]) and np.isnan(p[4])


def test_beyond_every_calibration_score_p_values_still_rank_and_flag_the_same() -> None:
    """A new wording puts every score beyond the calibration set: the conformal p-value is
    1/(n+1) for all and cannot rank. Here it goes on falling with the score, within
    [1/(2(n+1)), 1/(n+1)), so any threshold at or above 1/(n+1) flags the same."""
    cal = np.array([-1.0, -0.9, -0.8])
    scores = np.array([-0.8, -0.7, -0.4, 0.1, 1.0, 1.5])
    p = p_values(cal, scores)
    assert p[0] == 2 / 4  # at the largest calibration score: conformal as ever
    tail = p[1:]
    assert np.all(np.diff(tail[:4]) < 0)  # ranks by the score
    assert np.all(tail < 1 / 4) and np.all(tail >= 1 / 8)
    assert tail[3] == tail[4] == 1 / 8  # the bound, 1: the worst a cosine score gets
    assert np.allclose(tail[0], (1 - 0.1 / 1.8 / 2) / 4)
    assert np.array_equal(p < 0.3, p_values(cal, np.minimum(scores, -0.7)) < 0.3)
    unbounded = p_values(np.array([1.0, 2.0, 3.0]), np.array([4.0, 10.0, 100.0]), bound=None)
    assert np.all(np.diff(unbounded) < 0) and np.all(unbounded >= 1 / 8)


def test_a_phrase_is_embedded_without_its_article_or_count() -> None:
    assert embedded_form("a red box") == "red box"
    assert embedded_form("Two  red boxes on the ground") == "red boxes on the ground"
    assert embedded_form("the one carton") == "carton"
    assert embedded_form("the") == "the"  # nothing left: the phrase as it is
    assert embedded_form("anvil") == "anvil"


def test_bonferroni_over_two_and_text_only_unchanged() -> None:
    p_obs = np.array([0.5, 0.02, 0.3])
    p_det = np.array([0.01, 0.6, np.nan])
    assert np.allclose(combined_p(p_obs, p_det), [0.02, 0.04, 0.3])


def test_the_combined_false_positive_rate_stays_under_one_minus_alpha() -> None:
    """Nominal scores exchangeable with the calibration ones: the combined p is a
    valid p-value, whatever the dependence of its two components."""
    rng = np.random.default_rng(0)
    n_cal, n_test, alpha = 2000, 20000, 0.95
    whole = rng.normal(size=n_cal + n_test)
    det = 0.7 * whole + 0.3 * rng.normal(size=n_cal + n_test)  # dependent components
    p = combined_p(p_values(whole[:n_cal], whole[n_cal:]), p_values(det[:n_cal], det[n_cal:]))
    assert np.mean(p < 1 - alpha) <= 1 - alpha


# four nominal objects: a person, a forklift, a shelf, a pallet; a person and a forklift
# are never seen together, a person is seen with a shelf (twice) and a pallet (once)
SCENES = [[0, 2], [2, 0, 0], [0, 3], [1, 2], [1, 3], [2, 3]]
FOUR = NominalDetections(("a person", "a forklift", "a shelf", "a pallet"),
                         unit([1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]),
                         np.array([3, 2, 4, 3]))


def test_pairs_are_distinct_and_counted_by_observation() -> None:
    pairs = pairs_of(SCENES)
    got = {(int(a), int(b)): int(c)
           for a, b, c in zip(pairs.first, pairs.second, pairs.counts, strict=True)}
    assert got == {(0, 2): 2, (0, 3): 1, (1, 2): 1, (1, 3): 1, (2, 3): 1}
    assert pairs_of([[1], []]).first.size == 0


def test_two_nominal_objects_never_seen_together_make_the_worst_pair() -> None:
    pairs = pairs_of(SCENES)
    sims = similarities(FOUR, FOUR.vectors[[2, 0, 1]])  # a shelf, a person, a forklift
    got = worst_pair(pairs, sims)
    assert got is not None
    assert got.detections == (1, 2)  # the person and the forklift
    assert np.isclose(got.similarity, 0.0) and np.isclose(got.score, 0.0)
    # either order of a nominal pair matches it
    seen = worst_pair(pairs, similarities(FOUR, FOUR.vectors[[2, 0]]))
    assert seen is not None and np.isclose(seen.score, -1.0)
    assert (int(pairs.first[seen.nearest]), int(pairs.second[seen.nearest])) == (0, 2)
    assert worst_pair(pairs, sims[:1]) is None  # one detection has no pair


def test_a_pair_like_a_nominal_one_is_as_similar_as_its_least_similar_member() -> None:
    pairs = pairs_of([[0, 2]])
    # something person-like (0.9) beside something shelf-like (0.6)
    sims = similarities(FOUR, unit([0.9, 0, np.sqrt(1 - 0.81), 0],
                                   [0, 0, 0.6, 0.8]))
    got = worst_pair(pairs, sims)
    assert got is not None and np.isclose(got.similarity, 0.6)


def test_pair_leave_one_out_drops_the_pairs_only_that_observation_holds() -> None:
    pairs = pairs_of(SCENES)
    scores = loo_pair_scores(FOUR, pairs, SCENES + [[3]])
    # the person and the shelf: two scenes hold them, so each matches the pair itself
    assert np.isclose(scores[0], -1.0) and np.isclose(scores[1], -1.0)
    # the person and the pallet: only scene 2; without it the nearest pair shares one member
    assert np.isclose(scores[2], 0.0)
    assert np.isnan(scores[6])  # one detection: no pair


def test_bonferroni_over_three_counts_three_tests_even_without_a_pair() -> None:
    p_obs = np.array([0.5, 0.02, 0.3, 0.4])
    p_det = np.array([0.01, 0.6, np.nan, 0.5])
    p_pair = np.array([0.9, 0.5, np.nan, np.nan])  # the fourth: one detection, no pair
    assert np.allclose(combined_p(p_obs, p_det, p_pair), [0.03, 0.06, 0.3, 1.0])
    p_pair = np.array([0.001, 0.5, np.nan, np.nan])
    assert np.allclose(combined_p(p_obs, p_det, p_pair), [0.003, 0.06, 0.3, 1.0])


def test_three_components_keep_the_false_positive_rate_under_one_minus_alpha() -> None:
    rng = np.random.default_rng(1)
    n_cal, n_test, alpha = 2000, 20000, 0.95
    whole = rng.normal(size=n_cal + n_test)
    det = 0.5 * whole + 0.5 * rng.normal(size=n_cal + n_test)
    pair = rng.normal(size=n_cal + n_test)
    single = rng.random(n_cal + n_test) < 0.3  # observations with one detection: no pair
    pair[single] = np.nan
    p = combined_p(p_values(whole[:n_cal], whole[n_cal:]), p_values(det[:n_cal], det[n_cal:]),
                   p_values(pair[:n_cal], pair[n_cal:]))
    assert np.mean(p < 1 - alpha) <= 1 - alpha
