"""Latency statistics used to choose the slow reasoner's bound K (paper appendix)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from services.reasoner.latency import (
    LatencyError,
    LatencyReport,
    min_samples,
    quantile_rank,
    summarize,
    upper_bound_rank,
)


def one_to(n: int) -> list[float]:
    """Samples 1.0, 2.0, ..., n (s), shuffled so that sorting is exercised."""
    values = [float(i) for i in range(1, n + 1)]
    return values[1::2] + values[0::2]


# --- empirical quantile (paper eq. emp-quantile) ---------------------------


def test_quantile_rank_n20_q95_is_19th_smallest() -> None:
    # ceil(0.95 * 20) = 19: x_(19) upper bounds 19 / 20 = 0.95 of the samples.
    assert quantile_rank(20, 0.95) == 19


@pytest.mark.parametrize(
    ("n", "q", "rank"),
    [
        (100, 0.07, 7),  # 0.07 * 100 == 7.000000000000001 in floats: plain ceil gives 8
        (100, 0.29, 29),  # 0.29 * 100 == 28.999999999999996
        (100, 0.57, 57),  # 0.57 * 100 == 56.99999999999999
        (10, 0.9, 9),
        (10, 0.91, 10),  # 9.1 -> 10
        (500, 0.95, 475),
        (3, 0.01, 1),
    ],
)
def test_quantile_rank_survives_float_ceil_trap(n: int, q: float, rank: int) -> None:
    assert quantile_rank(n, q) == rank


def test_k_is_the_19th_of_20_samples() -> None:
    # n = 20 only supports a 0.95-quantile bound at confidence <= 1 - 0.95**20 = 0.64.
    report = summarize(one_to(20), quantile=0.95, confidence=0.5)
    assert report.k_s == 19.0
    assert report.quantiles_s["p50"] == 10.0
    assert report.quantiles_s["p90"] == 18.0
    assert report.quantiles_s["p99"] == 20.0


# --- minimum sample size ----------------------------------------------------


def test_min_samples_95_95_is_59() -> None:
    # 0.95**58 = 0.0510 > 0.05 and 0.95**59 = 0.0485 <= 0.05.
    assert 1 - 0.95**58 < 0.95 <= 1 - 0.95**59
    assert min_samples(0.95, 0.95) == 59


@pytest.mark.parametrize(("q", "c"), [(0.5, 0.5), (0.9, 0.99), (0.99, 0.95), (0.5, 0.3)])
def test_min_samples_is_the_smallest_n_satisfying_the_inequality(q: float, c: float) -> None:
    n = min_samples(q, c)
    assert 1 - q**n >= c
    assert n == 1 or 1 - q ** (n - 1) < c


def test_too_few_samples_refused_with_the_count_needed() -> None:
    with pytest.raises(LatencyError) as info:
        summarize(one_to(58))
    assert info.value.field == "n"
    assert "59" in str(info.value)
    assert summarize(one_to(59)).k_upper_s == 59.0  # n = 59: only the maximum bounds it


# --- order-statistic upper bound ------------------------------------------


def test_upper_bound_rank_worked_example() -> None:
    # n = 10, q = 0.5: P(Binomial(10, 0.5) <= k) = sum_{j<=k} C(10, j) / 1024, with
    # cumulative numerators 1, 11, 56, 176, 386, 638, 848, 968, 1013, 1023, 1024.
    # confidence 0.9 needs P(Bin < r) >= 0.9, i.e. a numerator >= 921.6:
    # 848 (k = 6) is short, 968 (k = 7) suffices -> r - 1 = 7 -> r = 8.
    # confidence 0.95 needs >= 972.8: 968 is short, 1013 (k = 8) -> r = 9.
    assert upper_bound_rank(10, 0.5, 0.9) == 8
    assert upper_bound_rank(10, 0.5, 0.95) == 9
    report = summarize(one_to(10), quantile=0.5, confidence=0.9)
    assert report.k_s == 5.0  # ceil(0.5 * 10) = 5
    assert report.k_upper_s == 8.0


def test_upper_bound_rank_matches_exact_binomial_sum() -> None:
    def cdf(k: int, n: int, p: float) -> float:
        return sum(math.comb(n, j) * p**j * (1 - p) ** (n - j) for j in range(k + 1))

    for n, q, c in [(59, 0.95, 0.95), (100, 0.9, 0.95), (500, 0.95, 0.95), (200, 0.5, 0.99)]:
        r = upper_bound_rank(n, q, c)
        assert cdf(r - 1, n, q) >= c
        assert cdf(r - 2, n, q) < c


def test_upper_bound_is_never_below_k() -> None:
    report = summarize(np.random.default_rng(3).lognormal(1.0, 0.3, 500).tolist())
    assert report.k_s <= report.k_upper_s <= report.max_s


def test_upper_bound_covers_true_quantile_in_about_95_percent_of_trials() -> None:
    # Exponential(1): true 0.9 quantile is -ln(0.1). Distribution-free coverage >= 0.95.
    rng = np.random.default_rng(20240601)
    true_q = -math.log(1 - 0.9)
    trials = 400
    covered = sum(
        summarize(rng.exponential(1.0, 100).tolist(), quantile=0.9, bins=5).k_upper_s >= true_q
        for _ in range(trials)
    )
    assert covered / trials >= 0.92  # expected >= 0.95; loose against sampling noise
    # The empirical quantile alone covers only about half the time.
    naive = sum(
        summarize(rng.exponential(1.0, 100).tolist(), quantile=0.9, bins=5).k_s >= true_q
        for _ in range(trials)
    )
    assert naive / trials < 0.8


# --- histogram, cold samples, failures -----------------------------------


def test_histogram_counts_sum_to_n() -> None:
    latencies = np.random.default_rng(1).gamma(4.0, 0.8, 137).tolist()
    report = summarize(latencies, bins=17)
    assert sum(report.histogram.counts) == report.n == 137
    assert len(report.histogram.edges_s) == 18
    assert report.histogram.edges_s[0] == report.min_s
    assert report.histogram.edges_s[-1] == report.max_s


def test_cold_samples_reported_apart_and_excluded() -> None:
    warm = one_to(60)
    with_cold = summarize(warm, cold=[40.0, 25.0], failed=3)
    without = summarize(warm)
    assert with_cold.cold_s == (40.0, 25.0)
    assert with_cold.n == 60
    assert with_cold.n_failed == 3
    for field in ("mean_s", "std_s", "min_s", "max_s", "k_s", "k_upper_s", "histogram"):
        assert getattr(with_cold, field) == getattr(without, field)
    assert dict(with_cold.quantiles_s) == dict(without.quantiles_s)


def test_basic_moments() -> None:
    report = summarize(one_to(60))
    assert report.mean_s == pytest.approx(30.5)
    assert report.std_s == pytest.approx(math.sqrt((60**2 - 1) / 12))  # population std
    assert (report.min_s, report.max_s) == (1.0, 60.0)


def test_to_dict_is_json_ready() -> None:
    report = summarize(one_to(60), cold=[9.0])
    data = report.to_dict()
    assert json.loads(json.dumps(data)) == data
    assert data["quantiles_s"] == {"p50": 30.0, "p90": 54.0, "p95": 57.0, "p99": 60.0}
    assert data["cold_s"] == [9.0]


def test_report_is_frozen() -> None:
    report = summarize(one_to(60))
    assert isinstance(report, LatencyReport)
    with pytest.raises(AttributeError):
        report.k_s = 1.0  # type: ignore[misc]
    with pytest.raises(TypeError):
        report.quantiles_s["p95"] = 1.0  # type: ignore[index]


# --- refusals ----------------------------------------------------------------


@pytest.mark.parametrize("q", [0.0, 1.0, -0.1, 1.5, float("nan")])
def test_quantile_outside_open_unit_interval_refused(q: float) -> None:
    with pytest.raises(LatencyError) as info:
        summarize(one_to(100), quantile=q)
    assert info.value.field == "quantile"


@pytest.mark.parametrize("c", [0.0, 1.0, 2.0, float("nan")])
def test_confidence_outside_open_unit_interval_refused(c: float) -> None:
    with pytest.raises(LatencyError) as info:
        summarize(one_to(100), confidence=c)
    assert info.value.field == "confidence"
    with pytest.raises(LatencyError):
        min_samples(0.95, c)


@pytest.mark.parametrize("bad", [float("nan"), -0.1, float("inf")])
def test_bad_latencies_refused(bad: float) -> None:
    with pytest.raises(LatencyError) as info:
        summarize([*one_to(100), bad])
    assert info.value.field == "latencies"
    assert isinstance(info.value, ValueError)


def test_bad_cold_and_counts_refused() -> None:
    with pytest.raises(LatencyError) as info:
        summarize(one_to(100), cold=[float("nan")])
    assert info.value.field == "cold"
    with pytest.raises(LatencyError) as info:
        summarize(one_to(100), failed=-1)
    assert info.value.field == "failed"
    with pytest.raises(LatencyError) as info:
        summarize(one_to(100), bins=0)
    assert info.value.field == "bins"
    with pytest.raises(LatencyError) as info:
        summarize([])
    assert info.value.field == "n"


# --- the paper's experiment, in spirit ---------------------------------------


def test_bimodal_sample_like_the_paper_gives_k_near_4_3_s() -> None:
    # N = 500: two modes (~2.6 s, ~3.85 s) and 3 % slow outliers; the paper reports
    # mean 3.1 s, std 0.85 s and K = 4.3 s at the 95 % quantile.
    rng = np.random.default_rng(0)
    latencies = np.concatenate(
        [rng.normal(2.6, 0.3, 300), rng.normal(3.85, 0.3, 185), rng.uniform(5.0, 7.5, 15)]
    )
    report = summarize(latencies.tolist())
    assert report.n == 500
    assert report.mean_s == pytest.approx(3.1, abs=0.15)
    assert report.std_s == pytest.approx(0.85, abs=0.15)
    assert report.k_s == pytest.approx(4.3, abs=0.15)
    assert report.k_s <= report.k_upper_s < 5.5
