"""Detection threshold tau for the fast anomaly detector, and its evaluation.

Convention (paper ``eq:anomaly-classifier``): a higher score is more anomalous
and an observation is an anomaly iff ``score > tau`` (strict). Scores are
unitless (whatever the score function returns, see ``scoring``).

Three ways to choose tau:

* ``loo_quantile``: eq. (2) (``eq:emp-quantile``), the empirical alpha-quantile
  of the cache members' leave-one-out scores, as in Sec. IV-A and the
  threshold ablation (appendix ``supp:threshold-analysis``, 75..95-th quantiles).
* ``conformal``: split-conformal on held-out nominal scores (the extension
  Sec. IV-A points to, Angelopoulos & Bates 2022), with a finite-sample
  guarantee on the false positive rate.
* ``tpr_target``: the hardware appendix ("Fast Anomaly Detector Calibration"):
  on a labelled calibration set, the threshold with TPR >= a target and the
  lowest FPR.

Plus ``roc_curve``, ``auroc`` and ``binary_metrics`` to evaluate a score or a
threshold on labelled data. Pure numpy, no I/O.

Ranks such as ceil(alpha N) are computed with a tolerance: alpha N within a
relative 1e-9 above an integer counts as that integer, so that float products
like 0.28 * 25 = 7.000000000000001 give rank 7, not 8.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Literal, get_args

import numpy as np

__all__ = [
    "Calibration",
    "CalibrationError",
    "Method",
    "Rates",
    "auroc",
    "binary_metrics",
    "conformal",
    "empirical_quantile",
    "loo_quantile",
    "roc_curve",
    "tpr_target",
]

Method = Literal["loo-quantile", "conformal", "tpr-target"]

_RANK_RTOL = 1e-9


class CalibrationError(ValueError):
    """A calibration got an input it cannot use; ``field`` names that input.

    Fields: "alpha", "tpr", "scores", "is_anomaly", "threshold",
    "calibration" (the labelled calibration set lacks a class), and "method" /
    "n" for an inconsistent ``Calibration``.
    """

    def __init__(self, message: str, *, field: str) -> None:
        super().__init__(message)
        self.field = field


@dataclass(frozen=True)
class Calibration:
    """A calibrated detection threshold and how it was obtained.

    Attributes:
        method: "loo-quantile" (eq. 2), "conformal" or "tpr-target".
        threshold: tau; anomaly iff score > tau. Same units as the scores.
        alpha: quantile / coverage level in (0, 1); None for "tpr-target".
        n: number of calibration scores used.
        tpr: true positive rate achieved on the calibration set (labelled sets only).
        fpr: false positive rate on the calibration set, i.e. the fraction of its
            nominal scores above tau (for the nominal-only methods: all of them).
        auroc: AUROC of the scores on the calibration set (labelled sets only).
        target_tpr: the requested TPR ("tpr-target" only).
        pairs: the calibration kept pair scores too: a verdict with detections combines
            three p-values (:mod:`services.embedding.detector.detections`).
    """

    method: Method
    threshold: float
    alpha: float | None
    n: int
    tpr: float | None = None
    fpr: float | None = None
    auroc: float | None = None
    target_tpr: float | None = None
    pairs: bool = False

    def __post_init__(self) -> None:
        if self.method not in get_args(Method):
            raise CalibrationError(f"unknown method {self.method!r}", field="method")
        if math.isnan(self.threshold):
            raise CalibrationError("threshold must not be NaN", field="threshold")
        if self.n < 1:
            raise CalibrationError(f"n must be >= 1, got {self.n}", field="n")

    def classify(self, scores: np.ndarray) -> np.ndarray:
        """(m,) bool, True = anomaly: ``scores > threshold`` for (m,) scores."""
        return np.asarray(scores, dtype=np.float64) > self.threshold

    def to_dict(self) -> dict[str, object]:
        """Plain-Python dict of all fields (threshold may be +-inf for infinite scores)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, object]) -> Calibration:
        """Inverse of :meth:`to_dict`."""
        return cls(**data)  # type: ignore[arg-type]


@dataclass(frozen=True)
class Rates:
    """Detector quality at one threshold on a labelled set (anomaly = positive).

    Attributes:
        tpr: TP / #anomalies; None if the set has no anomalies.
        fpr: FP / #nominal; None if the set has no nominal samples.
        accuracy: (TP + TN) / n.
        balanced_accuracy: mean of tpr and 1 - fpr over those that exist.
        n: number of samples.
    """

    tpr: float | None
    fpr: float | None
    accuracy: float
    balanced_accuracy: float
    n: int

    def to_dict(self) -> dict[str, object]:
        return asdict(self)


# ---------------------------------------------------------------- validation


def _ceil_rank(x: float) -> int:
    """ceil(x), forgiving float error: x within a relative 1e-9 above an integer rounds down."""
    return math.ceil(x - _RANK_RTOL * max(1.0, abs(x)))


def _level(value: float, field: str, *, allow_one: bool) -> float:
    """A level in (0, 1), or (0, 1] with ``allow_one``."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise CalibrationError(f"{field} must be a number, got {value!r}", field=field)
    v = float(value)
    upper = "1]" if allow_one else "1)"
    if not (0.0 < v < 1.0 or (allow_one and v == 1.0)):
        raise CalibrationError(f"{field} must be in (0, {upper}, got {value!r}", field=field)
    return v


def _scores(scores: np.ndarray, *, finite: bool) -> np.ndarray:
    """(N,) float64, N >= 1, no NaN (and no +-inf with ``finite``)."""
    s = np.asarray(scores, dtype=np.float64)
    if s.ndim != 1 or s.size == 0:
        raise CalibrationError(
            f"scores must be a non-empty 1-D array, got shape {s.shape}", field="scores"
        )
    if finite and not np.all(np.isfinite(s)):
        raise CalibrationError("scores must be finite", field="scores")
    if np.any(np.isnan(s)):
        raise CalibrationError("scores must not contain NaN", field="scores")
    return s


def _labels(is_anomaly: np.ndarray, n: int) -> np.ndarray:
    """(n,) bool anomaly labels, from bools or 0/1 integers."""
    y = np.asarray(is_anomaly)
    if y.shape != (n,):
        raise CalibrationError(
            f"is_anomaly must have shape ({n},) like scores, got {y.shape}", field="is_anomaly"
        )
    if y.dtype != np.bool_:
        if not np.issubdtype(y.dtype, np.integer) or np.any((y != 0) & (y != 1)):
            raise CalibrationError("is_anomaly must be bool (or 0/1)", field="is_anomaly")
        y = y.astype(bool)
    return y


def _both_classes(y: np.ndarray, field: str) -> tuple[int, int]:
    """(#anomalies, #nominal), both >= 1."""
    n_a = int(y.sum())
    n_nom = int(y.size - n_a)
    if n_a == 0 or n_nom == 0:
        raise CalibrationError(
            f"need at least one anomaly and one nominal sample, got {n_a} and {n_nom}",
            field=field,
        )
    return n_a, n_nom


def _kth_smallest(s: np.ndarray, j: int) -> float:
    """The j-th smallest (1-based) of s."""
    return float(np.partition(s, j - 1)[j - 1])


# ---------------------------------------------------------------- nominal-only


def empirical_quantile(scores: np.ndarray, alpha: float) -> float:
    """Eq. (2): tau = inf{q : |{i : s_i <= q}| / N >= alpha}.

    That is the ceil(alpha N)-th smallest score (rank with the float tolerance
    of the module docstring). At least a fraction alpha of the scores are
    <= tau, so at most 1 - alpha of them would be flagged.

    Args:
        scores: (N,) scores, N >= 1, no NaN (+-inf allowed).
        alpha: quantile level in (0, 1), e.g. 0.95.

    Returns:
        tau, one of the scores.

    Raises:
        CalibrationError: ``field="alpha"`` outside (0, 1); ``field="scores"``
            for an empty, non-1-D or NaN-containing array.
    """
    a = _level(alpha, "alpha", allow_one=False)
    s = _scores(scores, finite=False)
    n = s.size
    j = min(max(1, _ceil_rank(a * n)), n)
    return _kth_smallest(s, j)


def loo_quantile(loo_scores: np.ndarray, alpha: float) -> Calibration:
    """Eq. (2) on the cache members' leave-one-out scores s(e_i; D_e \\ {e_i}).

    Args:
        loo_scores: (N,) leave-one-out scores of the N cache members
            (``scoring.loo_topk_scores`` or ``MahalanobisModel.loo_scores``).
        alpha: quantile level in (0, 1); the paper uses 0.95.

    Returns:
        Calibration(method="loo-quantile", n=N, fpr = in-sample fraction > tau).
    """
    s = _scores(loo_scores, finite=False)
    tau = empirical_quantile(s, alpha)
    return Calibration(
        method="loo-quantile",
        threshold=tau,
        alpha=float(alpha),
        n=int(s.size),
        fpr=float(np.mean(s > tau)),
    )


def _min_conformal_n(alpha: float) -> int:
    """Smallest n with ceil((n+1) alpha) <= n, i.e. n >= alpha / (1 - alpha)."""
    n = max(1, math.floor(alpha / (1.0 - alpha)) - 1)
    while _ceil_rank((n + 1) * alpha) > n:
        n += 1
    return n


def conformal(cal_scores: np.ndarray, alpha: float) -> Calibration:
    """Split-conformal threshold from held-out nominal calibration scores.

    tau = the ceil((n+1) alpha)-th smallest of the n calibration scores. The
    scores must come from nominal samples NOT in the cache (or leave-one-out
    scores of cache members, which are exchangeable only approximately).

    Guarantee: if a nominal test score and the n calibration scores are
    exchangeable, P(score_test <= tau) >= alpha, i.e. the false positive rate is
    at most 1 - alpha, marginally over the calibration draw. Without ties it is
    also below alpha + 1/(n+1). alpha is the coverage level as in eq. (2) (e.g.
    0.95), not the miscoverage.

    Args:
        cal_scores: (n,) nominal calibration scores, no NaN.
        alpha: coverage level in (0, 1), at most n/(n+1).

    Returns:
        Calibration(method="conformal", n=n, fpr = in-sample fraction > tau).

    Raises:
        CalibrationError: ``field="alpha"`` if alpha is outside (0, 1) or
            ceil((n+1) alpha) > n (tau would be +inf: the miscoverage 1 - alpha
            must be at least 1/(n+1)); ``field="scores"`` as in
            :func:`empirical_quantile`.
    """
    a = _level(alpha, "alpha", allow_one=False)
    s = _scores(cal_scores, finite=False)
    n = s.size
    j = max(1, _ceil_rank((n + 1) * a))
    if j > n:
        raise CalibrationError(
            f"conformal alpha={a} with n={n} calibration scores would give tau=+inf: "
            f"the miscoverage 1-alpha must be at least 1/(n+1)={1.0 / (n + 1):.4g} "
            f"(alpha <= n/(n+1)={n / (n + 1):.4g}); alpha={a} needs at least "
            f"{_min_conformal_n(a)} calibration scores",
            field="alpha",
        )
    tau = _kth_smallest(s, j)
    return Calibration(
        method="conformal", threshold=tau, alpha=a, n=int(n), fpr=float(np.mean(s > tau))
    )


# ---------------------------------------------------------------- labelled


def tpr_target(scores: np.ndarray, is_anomaly: np.ndarray, tpr: float) -> Calibration:
    """Threshold with TPR >= ``tpr`` on a labelled calibration set and the lowest FPR.

    The hardware appendix calibrates this way (TPR >= 0.9). FPR does not
    increase with tau, so the answer is the LARGEST tau with
    #{anomalies with score > tau} >= m, m = ceil(tpr n_a) (float-tolerant). With
    a_m the m-th largest anomaly score, any tau >= a_m flags fewer than m
    anomalies, and every tau in [next score below a_m, a_m) flags the same
    samples; tau is the largest calibration score (any label) strictly below a_m,
    or nextafter(a_m, -inf) if there is none.

    Args:
        scores: (n,) finite calibration scores.
        is_anomaly: (n,) bool (or 0/1) labels, at least one of each class.
        tpr: target true positive rate in (0, 1].

    Returns:
        Calibration(method="tpr-target", alpha=None, with the achieved tpr and fpr
        on the calibration set, its auroc, and target_tpr).

    Raises:
        CalibrationError: ``field="tpr"`` outside (0, 1]; ``field="calibration"``
            without both classes; ``field="scores"`` / ``"is_anomaly"`` for bad arrays.
    """
    target = _level(tpr, "tpr", allow_one=True)
    s = _scores(scores, finite=True)
    y = _labels(is_anomaly, s.size)
    n_a, _ = _both_classes(y, "calibration")
    m = min(max(1, _ceil_rank(target * n_a)), n_a)
    a_m = float(np.sort(s[y])[n_a - m])
    below = s[s < a_m]
    tau = float(below.max()) if below.size else float(np.nextafter(a_m, -np.inf))
    metrics = binary_metrics(s, y, tau)
    return Calibration(
        method="tpr-target",
        threshold=tau,
        alpha=None,
        n=int(s.size),
        tpr=metrics.tpr,
        fpr=metrics.fpr,
        auroc=auroc(s, y),
        target_tpr=target,
    )


def roc_curve(
    scores: np.ndarray, is_anomaly: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ROC curve of the detector ``score > threshold`` over all thresholds.

    With v_1 > ... > v_K the distinct scores, the thresholds are
    [+inf, v_2, ..., v_K, -inf]: point i is (FPR, TPR) of ``scores > thresholds[i]``,
    so (0, 0) comes first, (1, 1) last, and each step admits one more distinct
    score (ties move diagonally).

    Args:
        scores: (n,) finite scores.
        is_anomaly: (n,) bool (or 0/1) labels, at least one of each class.

    Returns:
        fpr (K+1,), tpr (K+1,) non-decreasing in [0, 1], thresholds (K+1,) descending.

    Raises:
        CalibrationError: ``field="is_anomaly"`` without both classes or for bad
            labels; ``field="scores"`` for bad scores.
    """
    s = _scores(scores, finite=True)
    y = _labels(is_anomaly, s.size)
    n_a, n_nom = _both_classes(y, "is_anomaly")
    order = np.argsort(-s, kind="stable")
    s_desc, y_desc = s[order], y[order]
    ends = np.append(np.flatnonzero(np.diff(s_desc) != 0), s.size - 1)
    tps = np.cumsum(y_desc)[ends]
    fps = ends + 1 - tps
    fpr = np.concatenate([[0.0], fps / n_nom])
    tpr = np.concatenate([[0.0], tps / n_a])
    thresholds = np.concatenate([[np.inf], s_desc[ends[1:]], [-np.inf]])
    return fpr, tpr, thresholds


def auroc(scores: np.ndarray, is_anomaly: np.ndarray) -> float:
    """Area under the ROC curve via the Mann-Whitney rank-sum statistic.

    AUROC = (R_a - n_a (n_a + 1) / 2) / (n_a n_nom), R_a the sum of the
    anomalies' ranks among all scores (1-based, ties get their average rank).
    Equals P(anomaly score > nominal score) + P(equal) / 2, and the trapezoid
    area under :func:`roc_curve`. 0.5 when all scores are equal.

    Args:
        scores: (n,) finite scores.
        is_anomaly: (n,) bool (or 0/1) labels, at least one of each class.

    Returns:
        AUROC in [0, 1].
    """
    s = _scores(scores, finite=True)
    y = _labels(is_anomaly, s.size)
    n_a, n_nom = _both_classes(y, "is_anomaly")
    _, inverse, counts = np.unique(s, return_inverse=True, return_counts=True)
    upper = np.cumsum(counts)
    avg_rank = upper - (counts - 1) / 2.0
    rank_sum = float(avg_rank[inverse][y].sum())
    return (rank_sum - n_a * (n_a + 1) / 2.0) / (n_a * n_nom)


def binary_metrics(scores: np.ndarray, is_anomaly: np.ndarray, threshold: float) -> Rates:
    """TPR, FPR and accuracies of ``scores > threshold`` against labels.

    A class that is absent gives None for its rate (tpr without anomalies, fpr
    without nominal samples); balanced accuracy is then the other term alone.

    Args:
        scores: (n,) finite scores, n >= 1.
        is_anomaly: (n,) bool (or 0/1) labels.
        threshold: tau, not NaN (+-inf allowed).

    Raises:
        CalibrationError: ``field="threshold"`` for NaN; ``"scores"`` /
            ``"is_anomaly"`` for bad arrays.
    """
    t = float(threshold)
    if math.isnan(t):
        raise CalibrationError("threshold must not be NaN", field="threshold")
    s = _scores(scores, finite=True)
    y = _labels(is_anomaly, s.size)
    pred = s > t
    n_a = int(y.sum())
    n_nom = int(s.size - n_a)
    tp = int(np.sum(pred & y))
    fp = int(np.sum(pred & ~y))
    tpr = tp / n_a if n_a else None
    fpr = fp / n_nom if n_nom else None
    terms = [r for r in (tpr, None if fpr is None else 1.0 - fpr) if r is not None]
    return Rates(
        tpr=tpr,
        fpr=fpr,
        accuracy=(tp + n_nom - fp) / s.size,
        balanced_accuracy=sum(terms) / len(terms),
        n=int(s.size),
    )
