"""Threshold calibration (eq. 2, split-conformal, TPR target) and ROC / metrics."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest

from services.embedding.detector.calibration import (
    Calibration,
    CalibrationError,
    auroc,
    binary_metrics,
    conformal,
    empirical_quantile,
    loo_quantile,
    roc_curve,
    tpr_target,
)

FIVE = np.array([0.5, 0.1, 0.4, 0.2, 0.3])  # sorted: 0.1 0.2 0.3 0.4 0.5

# A small labelled set, 5 nominal + 5 anomalies.
NOMINAL = [0.1, 0.2, 0.3, 0.55, 0.7]
ANOMALY = [0.4, 0.6, 0.8, 0.9, 0.95]
SCORES = np.array(NOMINAL + ANOMALY)
LABELS = np.array([False] * 5 + [True] * 5)


# ---------------------------------------------------------------- eq. (2)


@pytest.mark.parametrize(
    ("alpha", "expected"),
    [
        (0.5, 0.3),  # ceil(0.5*5 = 2.5) = 3rd smallest
        (0.6, 0.3),  # ceil(3.0) = 3: exactly 3/5 = 0.6 of scores are <= 0.3
        (0.61, 0.4),  # ceil(3.05) = 4
        (0.2, 0.1),  # ceil(1.0) = 1
        (0.01, 0.1),  # ceil(0.05) = 1
        (0.99, 0.5),  # ceil(4.95) = 5
    ],
)
def test_empirical_quantile_hand_computed(alpha: float, expected: float) -> None:
    assert empirical_quantile(FIVE, alpha) == expected


def test_empirical_quantile_float_ceil_trap() -> None:
    scores = np.random.default_rng(0).permutation(np.arange(1.0, 26.0))  # 1..25
    # 0.28 * 25 is 7 exactly, but in floating point it is 7.000000000000001,
    # and a naive ceil would take the 8th smallest.
    assert 0.28 * 25 > 7 and math.ceil(0.28 * 25) == 8
    assert empirical_quantile(scores, 0.28) == 7.0
    # The brief's example: alpha=0.95, N=20 -> the 19th smallest.
    assert empirical_quantile(np.arange(1.0, 21.0), 0.95) == 19.0


def test_empirical_quantile_is_the_infimum_of_eq2() -> None:
    # Check against eq. (2) literally, in exact integer arithmetic:
    # tau = min{q in scores : 100 * #{s <= q} >= a100 * N} for alpha = a100/100.
    rng = np.random.default_rng(3)
    for n in (1, 2, 7, 20, 25, 33):
        s = np.round(rng.normal(size=n), 1)  # rounded: ties on purpose
        for a100 in range(1, 100):
            alpha = a100 / 100
            q = min(v for v in s if 100 * np.sum(s <= v) >= a100 * n)
            assert empirical_quantile(s, alpha) == q, (n, alpha)


def test_loo_quantile_calibration() -> None:
    cal = loo_quantile(FIVE, 0.6)
    assert cal.method == "loo-quantile"
    assert cal.threshold == 0.3
    assert cal.alpha == 0.6 and cal.n == 5
    assert cal.fpr == pytest.approx(2 / 5)  # 0.4 and 0.5 are > 0.3
    assert cal.tpr is None and cal.auroc is None and cal.target_tpr is None
    np.testing.assert_array_equal(cal.classify(np.array([0.3, 0.31])), [False, True])


# ---------------------------------------------------------------- conformal


def test_conformal_hand_computed_index() -> None:
    scores = np.random.default_rng(1).permutation(np.arange(1.0, 20.0))  # n = 19: 1..19
    # ceil((19+1) * 0.95) = 19 -> the 19th smallest = the largest
    assert conformal(scores, 0.95).threshold == 19.0
    # ceil(20 * 0.9) = 18 ; ceil(20 * 0.5) = 10 ; ceil(20 * 0.52) = ceil(10.4) = 11
    assert conformal(scores, 0.9).threshold == 18.0
    assert conformal(scores, 0.5).threshold == 10.0
    assert conformal(scores, 0.52).threshold == 11.0
    cal = conformal(scores, 0.9)
    assert (cal.method, cal.alpha, cal.n) == ("conformal", 0.9, 19)
    assert cal.fpr == pytest.approx(1 / 19)  # only 19 > 18


def test_conformal_float_ceil_trap() -> None:
    scores = np.arange(1.0, 25.0)  # n = 24; (24+1) * 0.28 = 7.000000000000001 in floats
    assert conformal(scores, 0.28).threshold == 7.0


def test_conformal_refuses_when_threshold_would_be_infinite() -> None:
    # n=18, alpha=0.95: ceil(19 * 0.95) = ceil(18.05) = 19 > 18.
    with pytest.raises(CalibrationError) as err:
        conformal(np.arange(1.0, 19.0), 0.95)
    assert err.value.field == "alpha"
    msg = str(err.value)
    assert "1/(n+1)" in msg
    assert "at least 19 calibration scores" in msg  # 0.95/(1-0.95) = 19
    # alpha=0.9 needs 9: ceil(10 * 0.9) = 9 <= 9, but ceil(9 * 0.9) = 9 > 8.
    assert conformal(np.arange(1.0, 10.0), 0.9).threshold == 9.0
    with pytest.raises(CalibrationError, match="at least 9 calibration scores"):
        conformal(np.arange(1.0, 9.0), 0.9)


def test_conformal_coverage_on_fresh_nominal_samples() -> None:
    # Exchangeable nominal scores: the average coverage P(s_test <= tau) over
    # calibration draws is >= alpha (and < alpha + 1/(n+1) without ties).
    # Here ceil(20 * 0.9) = 18, so the exact expected coverage is 18/20 = 0.9.
    rng = np.random.default_rng(4)
    n, alpha, trials, n_test = 19, 0.9, 2000, 50
    cal = rng.standard_gamma(2.0, size=(trials, n))
    test = rng.standard_gamma(2.0, size=(trials, n_test))
    taus = np.array([conformal(row, alpha).threshold for row in cal])
    coverage = float(np.mean(test <= taus[:, None]))
    assert alpha - 0.01 <= coverage <= alpha + 1 / (n + 1) + 0.01


# ---------------------------------------------------------------- TPR target


@pytest.mark.parametrize(
    ("target", "tau", "tpr", "fpr"),
    [
        # m = ceil(0.9 * 5 = 4.5) = 5 -> a_5 = 0.4; largest score below it 0.3;
        # anomalies > 0.3: all 5 ; nominal > 0.3: 0.55, 0.7
        (0.9, 0.3, 1.0, 2 / 5),
        # m = ceil(4.0) = 4 -> a_4 = 0.6; below it 0.55; TP 4 (0.6..0.95), FP 1 (0.7)
        (0.8, 0.55, 4 / 5, 1 / 5),
        # m = ceil(3.0) = 3 -> a_3 = 0.8; below it 0.7; TP 3, FP 0
        (0.6, 0.7, 3 / 5, 0.0),
        # m = ceil(0.5) = 1 -> a_1 = 0.95; below it 0.9; TP 1
        (0.1, 0.9, 1 / 5, 0.0),
    ],
)
def test_tpr_target_hand_computed(target: float, tau: float, tpr: float, fpr: float) -> None:
    cal = tpr_target(SCORES, LABELS, target)
    assert cal.method == "tpr-target"
    assert cal.threshold == tau
    assert cal.tpr == pytest.approx(tpr)
    assert cal.fpr == pytest.approx(fpr)
    assert cal.target_tpr == target and cal.alpha is None and cal.n == 10
    assert cal.auroc == pytest.approx(0.88)


def test_tpr_target_is_the_largest_threshold_meeting_the_target() -> None:
    cal = tpr_target(SCORES, LABELS, 0.8)
    # any larger candidate threshold misses the target
    for t in SCORES[cal.threshold < SCORES]:
        tpr = binary_metrics(SCORES, LABELS, t).tpr
        assert tpr is not None and tpr < 0.8


def test_tpr_target_float_ceil_trap() -> None:
    anomalies = np.arange(1.0, 26.0)  # 25 anomalies, 1..25
    nominal = np.array([0.5, 18.5, 100.0])
    scores = np.concatenate([anomalies, nominal])
    labels = np.array([True] * 25 + [False] * 3)
    # m = ceil(0.28 * 25) = 7 (not 8) -> a_7 = 19; largest score below: 18.5
    cal = tpr_target(scores, labels, 0.28)
    assert cal.threshold == 18.5
    assert cal.tpr == pytest.approx(7 / 25)
    assert cal.fpr == pytest.approx(1 / 3)  # 100 > 18.5


def test_tpr_target_nothing_below_uses_nextafter() -> None:
    # m = 2 -> a_2 = 0.1 is the smallest score overall
    cal = tpr_target(np.array([0.1, 0.9, 0.5]), np.array([True, True, False]), 1.0)
    assert cal.threshold == np.nextafter(0.1, -np.inf)
    assert cal.tpr == 1.0 and cal.fpr == 1.0


def test_tpr_target_ties_at_a_m() -> None:
    # anomalies 0.5, 0.5, 0.9 ; nominal 0.5, 0.2. tpr=1 -> m=3 -> a_3 = 0.5;
    # largest score strictly below 0.5 is 0.2; the tied nominal 0.5 is flagged too.
    scores = np.array([0.5, 0.5, 0.9, 0.5, 0.2])
    labels = np.array([True, True, True, False, False])
    cal = tpr_target(scores, labels, 1.0)
    assert cal.threshold == 0.2
    assert (cal.tpr, cal.fpr) == (1.0, 0.5)


# ---------------------------------------------------------------- ROC / AUROC


def test_auroc_hand_computed() -> None:
    # pairs (anomaly > nominal): 0.4 beats 3, 0.6 beats 4, 0.8/0.9/0.95 beat 5 -> 22/25
    assert auroc(SCORES, LABELS) == pytest.approx(0.88)


def test_auroc_with_ties() -> None:
    # nominal 0.1, 0.5 ; anomaly 0.5, 0.9. Pairs: 0.5>0.1 (1), 0.5=0.5 (1/2),
    # 0.9 beats both (2) -> 3.5/4. Ranks: 0.1->1, 0.5,0.5->2.5, 0.9->4;
    # R_a = 2.5 + 4 = 6.5, U = 6.5 - 2*3/2 = 3.5.
    scores = np.array([0.1, 0.5, 0.5, 0.9])
    labels = np.array([False, False, True, True])
    assert auroc(scores, labels) == pytest.approx(0.875)
    assert auroc(np.full(6, 0.3), np.array([0, 1, 0, 1, 1, 0])) == 0.5
    assert auroc(np.array([0.0, 1.0]), np.array([False, True])) == 1.0
    assert auroc(np.array([1.0, 0.0]), np.array([False, True])) == 0.0


def test_roc_curve_hand_computed() -> None:
    scores = np.array([0.1, 0.5, 0.5, 0.9])
    labels = np.array([False, False, True, True])
    fpr, tpr, thr = roc_curve(scores, labels)
    # distinct scores 0.9 > 0.5 > 0.1 -> thresholds [inf, 0.5, 0.1, -inf]
    np.testing.assert_array_equal(thr, [np.inf, 0.5, 0.1, -np.inf])
    np.testing.assert_allclose(fpr, [0.0, 0.0, 0.5, 1.0])  # score > t
    np.testing.assert_allclose(tpr, [0.0, 0.5, 1.0, 1.0])
    # trapezoid area: 0.5 * (0.5+1)/2 + 0.5 * 1 = 0.875
    assert np.trapezoid(tpr, fpr) == pytest.approx(0.875)


def test_roc_curve_points_match_binary_metrics_and_auroc_matches_area() -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        n = int(rng.integers(2, 40))
        labels = rng.random(n) < 0.4
        labels[:2] = [True, False]
        scores = np.round(rng.normal(size=n) + labels, 1)  # ties on purpose
        fpr, tpr, thr = roc_curve(scores, labels)
        assert (fpr[0], tpr[0], fpr[-1], tpr[-1]) == (0.0, 0.0, 1.0, 1.0)
        assert thr[0] == np.inf and np.all(np.diff(thr) < 0)
        for f, t, th in zip(fpr, tpr, thr, strict=True):
            m = binary_metrics(scores, labels, th)
            assert (m.fpr, m.tpr) == pytest.approx((f, t))
        assert auroc(scores, labels) == pytest.approx(np.trapezoid(tpr, fpr), abs=1e-12)
        # and the definition P(a > n) + P(a = n)/2, by brute force over pairs
        a, b = scores[labels][:, None], scores[~labels][None, :]
        assert auroc(scores, labels) == pytest.approx(np.mean((a > b) + 0.5 * (a == b)))


# ---------------------------------------------------------------- metrics


def test_binary_metrics_hand_computed() -> None:
    # tau = 0.55: TP 4 (0.6, 0.8, 0.9, 0.95), FN 1 (0.4), FP 1 (0.7), TN 4
    m = binary_metrics(SCORES, LABELS, 0.55)
    assert (m.tpr, m.fpr, m.n) == (0.8, 0.2, 10)
    assert m.accuracy == pytest.approx(8 / 10)
    assert m.balanced_accuracy == pytest.approx((0.8 + 0.8) / 2)
    # strict: a score equal to tau is nominal
    assert binary_metrics(np.array([0.55]), np.array([True]), 0.55).tpr == 0.0


def test_binary_metrics_single_class() -> None:
    only_nominal = binary_metrics(np.array([0.1, 0.6]), np.array([False, False]), 0.5)
    assert only_nominal.tpr is None and only_nominal.fpr == 0.5
    assert only_nominal.accuracy == 0.5 and only_nominal.balanced_accuracy == 0.5
    only_anomaly = binary_metrics(np.array([0.1, 0.6]), np.array([1, 1]), 0.5)
    assert only_anomaly.fpr is None and only_anomaly.tpr == 0.5
    assert only_anomaly.balanced_accuracy == 0.5
    assert only_anomaly.to_dict()["fpr"] is None


# ---------------------------------------------------------------- Calibration / errors


def test_calibration_round_trip_and_validation() -> None:
    cal = tpr_target(SCORES, LABELS, 0.9)
    d = cal.to_dict()
    assert d["method"] == "tpr-target" and d["threshold"] == 0.3 and d["alpha"] is None
    assert Calibration.from_dict(d) == cal
    with pytest.raises(CalibrationError) as err:
        Calibration(method="bogus", threshold=0.0, alpha=None, n=1)  # type: ignore[arg-type]
    assert err.value.field == "method"


@pytest.mark.parametrize("alpha", [0.0, 1.0, -0.1, 1.5, math.nan, True, "0.9"])
def test_bad_alpha(alpha: object) -> None:
    for fn in (empirical_quantile, loo_quantile, conformal):
        with pytest.raises(CalibrationError) as err:
            fn(FIVE, alpha)  # type: ignore[arg-type]
        assert err.value.field == "alpha"


@pytest.mark.parametrize("scores", [np.array([]), np.array([0.1, math.nan]), np.ones((2, 2))])
def test_bad_scores(scores: np.ndarray) -> None:
    for fn in (empirical_quantile, loo_quantile, conformal):
        with pytest.raises(CalibrationError) as err:
            fn(scores, 0.5)
        assert err.value.field == "scores"


def test_infinite_scores_allowed_for_quantiles_not_for_labelled() -> None:
    assert empirical_quantile(np.array([1.0, np.inf, 2.0]), 0.5) == 2.0
    with pytest.raises(CalibrationError) as err:
        auroc(np.array([1.0, np.inf]), np.array([False, True]))
    assert err.value.field == "scores"


def test_bad_labelled_inputs() -> None:
    cases = [
        (lambda: tpr_target(SCORES, LABELS, 0.0), "tpr"),
        (lambda: tpr_target(SCORES, LABELS, 1.01), "tpr"),
        (lambda: tpr_target(SCORES, LABELS, math.nan), "tpr"),
        (lambda: tpr_target(SCORES, np.zeros(10, dtype=bool), 0.9), "calibration"),
        (lambda: tpr_target(SCORES, np.ones(10, dtype=bool), 0.9), "calibration"),
        (lambda: tpr_target(SCORES, LABELS[:9], 0.9), "is_anomaly"),
        (lambda: tpr_target(SCORES, np.full(10, 2), 0.9), "is_anomaly"),
        (lambda: auroc(SCORES, np.zeros(10, dtype=bool)), "is_anomaly"),
        (lambda: roc_curve(SCORES, np.ones(10, dtype=bool)), "is_anomaly"),
        (lambda: binary_metrics(SCORES, LABELS, math.nan), "threshold"),
        (lambda: binary_metrics(np.array([]), np.array([], dtype=bool), 0.5), "scores"),
    ]
    for make, field in cases:
        with pytest.raises(CalibrationError) as err:
            make()
        assert err.value.field == field
    assert tpr_target(SCORES, LABELS, 1.0).tpr == 1.0  # tpr=1 is allowed


def test_quantile_exact_rank_matches_fraction_arithmetic() -> None:
    # The rank tolerance never changes a rank that exact arithmetic gets right.
    s = np.arange(1.0, 201.0)
    for a100 in range(1, 100):
        for n in (7, 20, 25, 100, 200):
            want = math.ceil(Fraction(a100, 100) * n)
            assert empirical_quantile(s[:n], a100 / 100) == float(want), (a100, n)
