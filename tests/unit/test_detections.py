"""Per-detection scores and the combined conformal p-value (issue 12, part 1's math)."""

from __future__ import annotations

import numpy as np

from services.embedding.detections import (
    NominalDetections,
    combined_p,
    distinct,
    loo_scores,
    p_values,
    worst,
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
    p = p_values(cal, np.array([0.05, 0.2, 0.25, 0.9, np.nan]))
    assert np.allclose(p[:4], [4 / 4, 3 / 4, 2 / 4, 1 / 4]) and np.isnan(p[4])


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
