"""Latency statistics of the slow reasoner, and the choice of its bound K.

The MPC (paper eq. modification-mpc) keeps the recovery plans jointly feasible
for K time steps, K being an upper bound on the slow reasoner's latency. The
paper (appendix "Choosing K - Analysis of LLM Query Latencies") queries
GPT-3.5-turbo N = 500 times, finds a bimodal distribution (mean 3.1 s, std
0.85 s) and sets K = 4.3 s, the 95 % empirical quantile of the response times.

:func:`summarize` turns measured latencies into a :class:`LatencyReport` that
holds the same recommendation (``k_s``, the empirical quantile with the
paper's convention, eq. emp-quantile: the smallest sample that upper bounds
at least ``quantile * n`` samples) and, next to it, a distribution-free upper
confidence bound on the *true* quantile (``k_upper_s``): an order statistic
chosen with the binomial distribution, valid for any continuous latency
distribution and i.i.d. samples.

Everything here is pure: no I/O, no clock; the timed queries live in
:mod:`.calibrating` (``POST /v1/latency/calibrate``).

Errors: every refusal is a :class:`LatencyError` (a ``ValueError``) whose
``field`` names what was wrong: ``"quantile"``, ``"confidence"``, ``"bins"``,
``"failed"``, ``"latencies"``, ``"cold"``, ``"histogram"`` or ``"n"`` (too few
samples).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
import numpy.typing as npt

__all__ = [
    "REPORTED_QUANTILES",
    "Histogram",
    "LatencyError",
    "LatencyReport",
    "min_samples",
    "quantile_rank",
    "summarize",
    "upper_bound_rank",
]

# Relative tolerance when turning ``quantile * n`` into an integer rank, so that
# 0.07 * 100 == 7.000000000000001 gives rank 7 and not 8.
_RANK_RTOL = 1e-9

REPORTED_QUANTILES: Mapping[str, float] = MappingProxyType(
    {"p50": 0.50, "p90": 0.90, "p95": 0.95, "p99": 0.99}
)
"""The quantile levels listed in :attr:`LatencyReport.quantiles_s`."""


class LatencyError(ValueError):
    """Refused input to the latency statistics; ``field`` names the culprit."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field


@dataclass(frozen=True)
class Histogram:
    """Counts of latencies in ``len(counts)`` equal bins.

    ``edges_s`` (s) has ``len(counts) + 1`` increasing entries; bin ``i`` is
    ``[edges_s[i], edges_s[i + 1])``, the last one closed on the right.
    """

    edges_s: tuple[float, ...]
    counts: tuple[int, ...]

    def __post_init__(self) -> None:
        if len(self.edges_s) != len(self.counts) + 1:
            raise LatencyError("histogram", "need exactly one more edge than counts")


@dataclass(frozen=True)
class LatencyReport:
    """Summary of the slow reasoner's measured latencies (all times in s).

    ``n`` successful warm samples enter every statistic; ``cold_s`` (the
    warm-up / cold-start samples) and ``n_failed`` (queries with no latency,
    e.g. errors or timeouts) are reported apart and enter none. ``std_s`` is
    the population standard deviation (ddof = 0) of the ``n`` samples.

    ``k_s`` is the empirical ``quantile`` (paper's convention, as the paper's
    K = 4.3 s); ``k_upper_s`` is an order statistic that upper bounds the true
    ``quantile`` with probability at least ``confidence`` (distribution-free).
    """

    n: int
    n_failed: int
    cold_s: tuple[float, ...]
    mean_s: float
    std_s: float
    min_s: float
    max_s: float
    quantiles_s: Mapping[str, float]
    histogram: Histogram
    quantile: float
    k_s: float
    k_upper_s: float
    confidence: float

    def to_dict(self) -> dict[str, object]:
        """Plain JSON-ready dict (lists instead of tuples, dicts instead of mappings)."""
        return {
            "n": self.n,
            "n_failed": self.n_failed,
            "cold_s": list(self.cold_s),
            "mean_s": self.mean_s,
            "std_s": self.std_s,
            "min_s": self.min_s,
            "max_s": self.max_s,
            "quantiles_s": dict(self.quantiles_s),
            "histogram": {
                "edges_s": list(self.histogram.edges_s),
                "counts": list(self.histogram.counts),
            },
            "quantile": self.quantile,
            "k_s": self.k_s,
            "k_upper_s": self.k_upper_s,
            "confidence": self.confidence,
        }


def _check_level(value: float, field: str) -> float:
    value = float(value)
    if not 0.0 < value < 1.0:  # also refuses NaN
        raise LatencyError(field, f"must lie in the open interval (0, 1), got {value!r}")
    return value


def quantile_rank(n: int, quantile: float) -> int:
    """1-based rank of the empirical ``quantile`` among ``n`` sorted samples.

    Paper eq. emp-quantile: the smallest sample ``x_(k)`` with ``k / n >=
    quantile``, i.e. ``k = ceil(quantile * n)``, computed with a relative
    tolerance so that float noise (``0.07 * 100 = 7.000000000000001``) does not
    push the rank up by one. Example: n = 20, quantile = 0.95 -> 19.
    """
    quantile = _check_level(quantile, "quantile")
    if n < 1:
        raise LatencyError("n", f"need at least one sample, got {n}")
    exact = quantile * n
    return min(n, max(1, math.ceil(exact - _RANK_RTOL * max(1.0, exact))))


def _tail_exceeds(n: int, quantile: float, confidence: float) -> bool:
    """True when even the largest sample cannot bound the quantile: q**n > 1 - c."""
    return quantile**n > 1.0 - confidence


def min_samples(quantile: float, confidence: float) -> int:
    """Smallest n for which :func:`upper_bound_rank` exists.

    The largest of n samples is below the true ``quantile`` with probability
    ``quantile**n``, so it is an upper bound with confidence ``1 - quantile**n``;
    the bound exists iff ``1 - quantile**n >= confidence``. Example:
    ``min_samples(0.95, 0.95) == 59`` (0.95**58 = 0.0510 > 0.05 >= 0.95**59 = 0.0485).
    """
    quantile = _check_level(quantile, "quantile")
    confidence = _check_level(confidence, "confidence")
    n = max(1, math.ceil(math.log1p(-confidence) / math.log(quantile)))
    # The closed form can be off by one in floating point: settle on the test itself.
    while n > 1 and not _tail_exceeds(n - 1, quantile, confidence):
        n -= 1
    while _tail_exceeds(n, quantile, confidence):
        n += 1
    return n


def _log_binom_pmf(k: int, n: int, p: float) -> float:
    """log P(Binomial(n, p) = k) for 0 < p < 1, stable for large n."""
    log_choose = math.lgamma(n + 1) - math.lgamma(k + 1) - math.lgamma(n - k + 1)
    return log_choose + k * math.log(p) + (n - k) * math.log1p(-p)


def upper_bound_rank(n: int, quantile: float, confidence: float) -> int:
    """1-based rank r of the order statistic bounding the true ``quantile``.

    For i.i.d. samples of a continuous distribution with ``quantile``-quantile
    xi, the number of samples below xi is Binomial(n, quantile), so
    ``P(x_(r) >= xi) = P(Binomial(n, quantile) < r)``. r is the smallest rank
    with ``P(Binomial(n, quantile) < r) >= confidence``, found by summing the
    upper tail ``P(Binomial >= r)`` from r = n downwards (small terms first) until
    it would exceed ``1 - confidence``. Raises ``LatencyError("n")`` when
    ``n < min_samples(quantile, confidence)``.

    Example: n = 10, quantile = 0.5, confidence = 0.9 -> r = 8.
    """
    quantile = _check_level(quantile, "quantile")
    confidence = _check_level(confidence, "confidence")
    needed = min_samples(quantile, confidence)
    if n < needed:
        raise LatencyError(
            "n",
            f"{n} samples cannot bound the {quantile:g} quantile at confidence "
            f"{confidence:g}; need at least {needed}",
        )
    alpha = 1.0 - confidence
    tail = quantile**n  # P(Binomial = n), the same expression as min_samples
    r = n
    while r > 1:
        candidate = tail + math.exp(_log_binom_pmf(r - 1, n, quantile))
        if candidate > alpha:
            break
        tail = candidate
        r -= 1
    return r


def _as_latencies(values: Sequence[float], field: str) -> npt.NDArray[np.float64]:
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise LatencyError(field, f"not a sequence of numbers: {exc}") from exc
    if array.ndim != 1:
        raise LatencyError(field, f"must be one-dimensional, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise LatencyError(field, "contains NaN or infinite values")
    if np.any(array < 0.0):
        raise LatencyError(field, "contains negative latencies")
    return array


def summarize(
    latencies_s: Sequence[float],
    *,
    quantile: float = 0.95,
    confidence: float = 0.95,
    cold: Sequence[float] = (),
    failed: int = 0,
    bins: int = 30,
) -> LatencyReport:
    """Summarize warm latencies (s) and recommend K.

    ``latencies_s``: the successful warm query latencies (s), one per query.
    ``cold``: warm-up / cold-start latencies (s), reported but not used.
    ``failed``: how many queries returned no latency. They are only counted:
    if they were timeouts, the true quantile may lie above ``k_s``.
    ``quantile``, ``confidence``: levels in (0, 1) for ``k_s`` and ``k_upper_s``.
    ``bins``: number of histogram bins (>= 1).

    Refuses (``LatencyError``) fewer than ``min_samples(quantile, confidence)``
    latencies (``field="n"``), NaN / infinite / negative values
    (``"latencies"``, ``"cold"``), levels outside (0, 1), ``bins < 1`` and
    ``failed < 0``.
    """
    quantile = _check_level(quantile, "quantile")
    confidence = _check_level(confidence, "confidence")
    if isinstance(bins, bool) or int(bins) != bins or bins < 1:
        raise LatencyError("bins", f"must be a positive integer, got {bins!r}")
    if isinstance(failed, bool) or int(failed) != failed or failed < 0:
        raise LatencyError("failed", f"must be a non-negative integer, got {failed!r}")
    samples = np.sort(_as_latencies(latencies_s, "latencies"))
    cold_s = _as_latencies(cold, "cold")
    n = int(samples.size)
    r_upper = upper_bound_rank(n, quantile, confidence)  # refuses a too small n

    counts, edges = np.histogram(samples, bins=int(bins))
    quantiles_s = {
        name: float(samples[quantile_rank(n, level) - 1])
        for name, level in REPORTED_QUANTILES.items()
    }
    return LatencyReport(
        n=n,
        n_failed=int(failed),
        cold_s=tuple(float(x) for x in cold_s),
        mean_s=float(samples.mean()),
        std_s=float(samples.std()),
        min_s=float(samples[0]),
        max_s=float(samples[-1]),
        quantiles_s=MappingProxyType(quantiles_s),
        histogram=Histogram(
            edges_s=tuple(float(e) for e in edges),
            counts=tuple(int(c) for c in counts),
        ),
        quantile=quantile,
        k_s=float(samples[quantile_rank(n, quantile) - 1]),
        k_upper_s=float(samples[r_upper - 1]),
        confidence=confidence,
    )
