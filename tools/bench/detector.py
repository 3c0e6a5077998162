"""``aesop bench detector``: quality, score kinds, latency, search, calibration, build,
memory, REST, restart.

Nine parts, each one function returning a JSON-able dict (``--only PART``):

* ``quality``  accuracy / AUROC vs cache size and vs concept coverage on the
  synthetic domains (paper §V-A, ``fig:synthetic-results``), top-5 scoring,
  tau = 95th LOO quantile (eq. 2); plus the threshold-quantile table of the
  appendix (``supp:threshold-analysis``) on VTOL.
* ``kinds``    per domain (three synthetic, quadrotor), brief form with detections: AUROC,
  balanced accuracy and FPR of the top-k, detection and combined scores, and the
  split-conformal FPR of the combined score against alpha.
* ``latency``  one observation end to end through ``CacheService.score_texts``
  against a 20k cache, with the embed-only and search-only parts, per embedding
  backend (torch, ONNX float32, ONNX int8).
* ``search``   exact (flat) vs HNSW search: single-query latency, build time, recall@5.
* ``loo``      leave-one-out calibration at 20k vs FAISS's batched search.
* ``build``    texts/s through ``CacheService.add`` (embedding dominates).
* ``memory``   peak RSS of a subprocess holding the model and a 100k cache.
* ``rest``     scoring over HTTP under 32 concurrent clients, micro-batching on vs off.
* ``restart``  an HNSW cache on the SQLite store: commit, graph build, index save, and a
  restart that loads the saved index vs one that must rebuild it.

Progress goes to stderr (logging), tables to stdout only when asked; the
returned dict holds no NaN. Timings on the 2-core machines are noisy: every
number is a median or p99 and comparisons are ratios measured in one run
(``meta.load_average`` records how busy the machine was).

``python -m tools.bench.detector --memory-probe`` is the memory part's
subprocess; it prints one JSON line.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
import itertools
import json
import logging
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property, partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from services.embedding.embedders import Embedder
from services.embedding.settings import DEFAULT_MODEL
from shared.process import ServiceProcess, free_port
from shared.tables import table

if TYPE_CHECKING:
    from services.embedding.evaluation import EvalScore
    from services.embedding.service import CacheService
    from tools.scenes import Dataset

log = logging.getLogger(__name__)

PARTS = ("quality", "kinds", "latency", "search", "loo", "build", "memory", "rest", "restart")
DIM = 384  # all-MiniLM-L6-v2
K = 5  # top-5 scoring, as in the paper
ALPHA = 0.95  # tau = 95th LOO quantile (eq. 2)
HOLDOUT = 0.2  # nominal share held out for testing; the cache comes from the other 80%
QUALITY_DOMAINS = ("warehouse", "vehicle", "vtol")
CACHE_FRACTIONS = (0.01, 0.05, 0.10, 0.25, 0.50, 0.80)  # of all nominal samples
COVERAGE_FRACTIONS = (0.10, 0.25, 0.50, 0.75, 1.00)  # of the nominal concepts
QUANTILES = (0.75, 0.85, 0.90, 0.95)
PAPER_MPNET_VTOL = {0.75: 0.83, 0.85: 0.89, 0.90: 0.91, 0.95: 0.93}  # tab:quantiles-results
LATENCY_TARGET_MS = {"median": 15.0, "p99": 30.0}
# the embedding backends the latency part compares, with the threads of each inference
# (issue 12: p50 <= 5 ms, p99 <= 10 ms); torch stays at one (its pool spins: see
# EmbeddingSettings.torch_threads), ONNX Runtime's is told not to spin
BACKENDS = ((DEFAULT_MODEL, 1), ("onnx:" + DEFAULT_MODEL, 1), ("onnx:" + DEFAULT_MODEL, 2),
            ("onnx-int8:" + DEFAULT_MODEL, 1), ("onnx-int8:" + DEFAULT_MODEL, 2))
BACKEND_TARGET_MS = {"median": 5.0, "p99": 10.0}
LOO_TARGET_S = 2.0
MEMORY_TARGET_MB = 1024.0
EF_SEARCH_SWEEP = (64, 128, 256, 512)  # HNSW efSearch values measured on each graph
HNSW_BUILD_BUDGET_S = 300.0  # lower M for a larger size if the projected build exceeds it
CLUSTERS = 2000  # Gaussian cluster centres of the synthetic vectors


@dataclass(frozen=True)
class Sizes:
    """How much work each part does (full run vs ``--quick``)."""

    domains: Mapping[str, tuple[int | None, int | None]]  # (nominal, anomaly); None: default
    repeats: int  # random splits per point of the quality curves
    threshold_seeds: int
    latency_n: int
    search_sizes: tuple[int, ...]
    exact_queries: int  # single exact queries timed per size
    build_texts: int
    rest_cache: int
    rest_requests: int
    latency_cache: int = 20_000
    search_queries: int = 200
    loo_size: int = 20_000
    loo_repeats: int = 3
    memory_cache: int = 100_000
    # the kinds part's domains (nominal, anomaly); None: the domain's own default (VTOL:
    # 4000 / 1000; the quality part trims it to 2000 / 500 to embed full prompts)
    kind_domains: Mapping[str, tuple[int | None, int | None]] = field(default_factory=dict)
    rest_concurrency: int = 32
    restart_cache: int = 200_000


FULL = Sizes(
    domains={"warehouse": (None, None), "vehicle": (None, None), "vtol": (2000, 500)},
    repeats=3, threshold_seeds=5, latency_n=300, search_sizes=(100_000, 1_000_000),
    exact_queries=50, build_texts=1000, rest_cache=2000, rest_requests=1000,
)
QUICK = Sizes(
    domains={name: (100, 40) for name in QUALITY_DOMAINS},
    kind_domains={name: (100, 40) for name in QUALITY_DOMAINS},
    repeats=1, threshold_seeds=2, latency_n=50, search_sizes=(10_000, 50_000),
    exact_queries=50, build_texts=300, rest_cache=100, rest_requests=200, loo_repeats=1,
    restart_cache=20_000,
)


# -- entry point ---------------------------------------------------------------


def run_detector_bench(
    *, quick: bool, only: list[str] | None, plot: Path | None, seed: int, table: bool
) -> dict[str, Any]:
    """Run the selected parts; return one JSON-able dict with a key per part (and ``meta``).

    Tables go to stdout when ``table``; everything else goes to stderr, so with
    ``table=False`` stdout stays clean for the caller's JSON. A part that fails
    is reported as ``{"error": ...}`` and the others still run.
    """
    parts = _select(only)
    sizes = QUICK if quick else FULL
    bench = _Bench(sizes, seed)
    out = sys.stdout
    started = time.perf_counter()
    result: dict[str, Any] = {"meta": _meta(quick, seed, parts)}
    runners: dict[str, Callable[[], dict[str, Any]]] = {
        "quality": lambda: bench_quality(bench, plot),
        "kinds": lambda: bench_kinds(bench),
        "latency": lambda: bench_latency(bench),
        "search": lambda: bench_search(sizes, seed),
        "loo": lambda: bench_loo(sizes, seed),
        "build": lambda: bench_build(bench),
        "memory": lambda: bench_memory(sizes),
        "rest": lambda: bench_rest(bench),
        "restart": lambda: bench_restart(sizes, seed),
    }
    with contextlib.redirect_stdout(sys.stderr):  # stray prints must not reach the JSON
        for part in parts:
            log.info("bench %s ...", part)
            t0 = time.perf_counter()
            try:
                result[part] = runners[part]()
            except Exception as exc:  # report the failure, run the other parts
                log.error("bench %s failed:\n%s", part, traceback.format_exc())
                result[part] = {"error": f"{type(exc).__name__}: {exc}"}
            result[part]["wall_s"] = time.perf_counter() - t0
            log.info("bench %s done in %.1f s", part, result[part]["wall_s"])
            if table:
                print(render(part, result[part]), file=out, flush=True)
    result["meta"]["wall_s"] = time.perf_counter() - started
    result["meta"]["load_average_end"] = list(os.getloadavg())
    if table:
        print(f"total wall time {result['meta']['wall_s']:.1f} s, load average "
              f"{result['meta']['load_average_start'][0]:.1f} -> "
              f"{result['meta']['load_average_end'][0]:.1f}", file=out)
    return _jsonable(result)


def _select(only: Sequence[str] | None) -> list[str]:
    if not only:
        return list(PARTS)
    unknown = sorted(set(only) - set(PARTS))
    if unknown:  # a usage error, answered like argparse does: message, exit status 2
        print(f"aesop: --only: unknown part(s) {', '.join(unknown)}; "
              f"choose from {', '.join(PARTS)}", file=sys.stderr)
        raise SystemExit(2)
    return [p for p in PARTS if p in only]


def _meta(quick: bool, seed: int, parts: list[str]) -> dict[str, Any]:
    import faiss

    return {
        "quick": quick, "seed": seed, "parts": parts, "cpus": os.cpu_count(),
        "faiss": faiss.__version__, "load_average_start": list(os.getloadavg()),
    }


class _Bench:
    """What the parts share: the sizes, the seed, one loaded model, and each
    domain's samples and embeddings (every text is embedded once per run)."""

    def __init__(self, sizes: Sizes, seed: int) -> None:
        self.sizes = sizes
        self.seed = seed
        self._datasets: dict[tuple[str, bool], Dataset] = {}
        self._vectors: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]] = {}

    @cached_property
    def embedder(self) -> Embedder:
        from services.embedding.loading import load_embedder
        from services.embedding.settings import DEFAULT_MODEL

        log.info("loading %s", DEFAULT_MODEL)
        embedder = load_embedder(DEFAULT_MODEL)
        embedder.embed(["warm-up"])
        return embedder

    def dataset(self, name: str, *, kinds: bool = False) -> Dataset:
        """Domain ``name`` at the quality part's sizes, or the kinds part's."""
        if (name, kinds) not in self._datasets:
            from tools.scenes import generate

            sizes = self.sizes.kind_domains if kinds else self.sizes.domains
            n_nominal, n_anomaly = sizes.get(name, (None, None))
            self._datasets[name, kinds] = generate(name, seed=self.seed, n_nominal=n_nominal,
                                                   n_anomaly=n_anomaly)
        return self._datasets[name, kinds]

    def nominal_vectors(self, name: str, n: int, form: str = "prompt") -> np.ndarray:
        """The first ``n`` nominal embeddings: from ``vectors`` if already embedded, else
        only those ``n`` texts are embedded."""
        if (name, form) in self._vectors:
            return self._vectors[name, form][0][:n]
        texts = [s.text if form == "prompt" else s.brief
                 for s in self.dataset(name).nominal[:n]]
        log.info("embedding %d %s texts", len(texts), name)
        return self.embedder.embed(texts, batch_size=64, show_progress_bar=True)

    def vectors(self, name: str, form: str = "prompt") -> tuple[np.ndarray, np.ndarray]:
        """(nominal, anomaly) unit embeddings of ``dataset(name)``, (n, DIM) float32 each,
        of the full prompts (``form="prompt"``, as in the paper) or the brief form."""
        if (name, form) not in self._vectors:
            ds = self.dataset(name)
            texts = [s.text if form == "prompt" else s.brief for s in ds.nominal + ds.anomalies]
            log.info("embedding %d %s texts (%s)", len(texts), name, form)
            v = self.embedder.embed(texts, batch_size=64, show_progress_bar=True)
            self._vectors[name, form] = (v[: len(ds.nominal)], v[len(ds.nominal):])
        return self._vectors[name, form]


# -- helpers ---------------------------------------------------------------------


def _stats(seconds: Sequence[float]) -> dict[str, float]:
    """Median, p99 and mean of durations, in milliseconds."""
    ms = np.asarray(seconds, dtype=np.float64) * 1e3
    return {"n": int(ms.size), "median_ms": float(np.median(ms)),
            "p99_ms": float(np.percentile(ms, 99)), "mean_ms": float(ms.mean())}


def _time_each(fn: Callable[[int], object], n: int) -> list[float]:
    """Durations (s) of ``fn(0) .. fn(n-1)``."""
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        out.append(time.perf_counter() - t0)
    return out


def _time_calls(fn: Callable[[], Any], repeats: int) -> tuple[list[float], Any]:
    """Durations (s) of ``repeats`` calls of ``fn`` and the last call's result."""
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return times, result


def _verdict(value: float, target: float) -> str:
    return "pass" if value <= target else "FAIL"


class _Clusters:
    """Unit vectors around ``CLUSTERS`` random centres.

    Each point is centre + noise with a decaying spectrum (variance of dimension
    i proportional to 1/i, effective dimension ~25, like sentence embeddings),
    noise norm ~``spread``; then normalised. Same-cluster cosine is ~0.7.
    Queries drawn with another generator come from the same distribution but
    are not members.
    """

    def __init__(self, dim: int, seed: int, *, spread: float = 0.7) -> None:
        rng = np.random.default_rng([seed, 7])
        self.centres = _unit(rng.standard_normal((CLUSTERS, dim), dtype=np.float32))
        scale = 1.0 / np.sqrt(np.arange(1, dim + 1, dtype=np.float64))
        self.scale = (scale * spread / np.linalg.norm(scale)).astype(np.float32)

    def sample(self, n: int, rng: np.random.Generator, *, chunk: int = 100_000) -> np.ndarray:
        out = np.empty((n, self.centres.shape[1]), dtype=np.float32)
        for start in range(0, n, chunk):
            m = min(chunk, n - start)
            noise = rng.standard_normal((m, out.shape[1]), dtype=np.float32) * self.scale
            out[start:start + m] = _unit(self.centres[rng.integers(CLUSTERS, size=m)] + noise)
        return out


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _jsonable(value: Any) -> Any:
    """numpy scalars -> Python, non-finite floats -> None, tuples -> lists, keys -> str."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.integer | np.bool_):
        return value.item()
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    return value


# -- 1. quality --------------------------------------------------------------------


def bench_quality(bench: _Bench, plot: Path | None) -> dict[str, Any]:
    """Accuracy and AUROC vs cache size and vs concept coverage, and the quantile table."""
    domains = {name: _quality_domain(bench, name) for name in QUALITY_DOMAINS}
    result = {
        "model": bench.embedder.name, "k": K, "alpha": ALPHA, "repeats": bench.sizes.repeats,
        "test_set": "held-out 20% of nominal + all anomalies",
        "domains": domains,
        "thresholds": _thresholdtable(bench),
        "text_forms": _text_forms(bench),
    }
    if plot is not None:
        plot_quality(domains, plot)
        result["plot"] = str(plot)
    return result


def _quality_domain(bench: _Bench, name: str) -> dict[str, Any]:
    from tools.scenes import concept_subset

    ds = bench.dataset(name)
    nominal, anomalies = bench.vectors(name)
    domain = ds.domain
    n = len(nominal)
    by_size: dict[float, list[dict[str, Any]]] = {f: [] for f in CACHE_FRACTIONS}
    by_coverage: dict[float, list[dict[str, Any]]] = {f: [] for f in COVERAGE_FRACTIONS}
    for r in range(bench.sizes.repeats):
        rng = np.random.default_rng([bench.seed, r, QUALITY_DOMAINS.index(name)])
        held, pool = _split(n, rng)
        test_x = np.concatenate([nominal[held], anomalies])
        test_y = np.r_[np.zeros(len(held), bool), np.ones(len(anomalies), bool)]
        for f in CACHE_FRACTIONS:
            size = min(len(pool), max(K + 1, round(f * n)))
            members = rng.choice(pool, size, replace=False)
            by_size[f].append(_detect(nominal[members], test_x, test_y))
        for f in COVERAGE_FRACTIONS:
            subset = set(concept_subset(domain, f, seed=bench.seed * 1000 + r))
            covered = [i for i in pool if set(ds.nominal[i].concepts) <= subset]
            seen = {c for i in covered for c in ds.nominal[i].concepts}
            point: dict[str, Any] = (_detect(nominal[covered], test_x, test_y)
                                     if len(covered) > K else {"cache_size": len(covered)})
            point["concepts_covered"] = len(seen) / len(domain.nominal_concepts)
            by_coverage[f].append(point)
    return {
        "n_nominal": n, "n_anomaly": len(anomalies), "n_test": len(test_y),
        "n_concepts": len(domain.nominal_concepts),
        "cache_size": [{"fraction": f, **_mean_std(by_size[f])} for f in CACHE_FRACTIONS],
        "coverage": [{"fraction": f, **_mean_std(by_coverage[f])} for f in COVERAGE_FRACTIONS],
    }


def _split(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(held-out, pool) index arrays: HOLDOUT of ``n`` for testing, the rest for caches."""
    perm = rng.permutation(n)
    cut = round(HOLDOUT * n)
    return perm[:cut], perm[cut:]


def _detect(cache_x: np.ndarray, test_x: np.ndarray, test_y: np.ndarray,
            alphas: Sequence[float] = (ALPHA,)) -> dict[str, Any]:
    """Detector built on ``cache_x`` with tau from eq. (2), evaluated on the test set."""
    from services.embedding.calibration import auroc, binary_metrics, loo_quantile
    from services.embedding.evaluation import EvalConfig, build_cache

    cache = build_cache(cache_x, EvalConfig(k=K), None)
    loo = cache.loo_scores(K)
    scores = np.array([r.score for r in cache.score(test_x, K, neighbors=0)])
    out: dict[str, Any] = {"cache_size": len(cache_x), "auroc": auroc(scores, test_y)}
    for alpha in alphas:
        m = binary_metrics(scores, test_y, loo_quantile(loo, alpha).threshold)
        suffix = "" if len(alphas) == 1 else f"@{alpha:g}"
        out |= {f"accuracy{suffix}": m.accuracy, f"balanced_accuracy{suffix}":
                m.balanced_accuracy, f"tpr{suffix}": m.tpr, f"fpr{suffix}": m.fpr}
    return out


def _mean_std(points: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean of every numeric field over repeats, plus ``<field>_std`` for the metrics."""
    out: dict[str, Any] = {}
    for key in dict.fromkeys(k for p in points for k in p):
        values = [p[key] for p in points if p.get(key) is not None]
        out[key] = float(np.mean(values)) if values else None
        if key in ("accuracy", "auroc", "balanced_accuracy") and values:
            out[f"{key}_std"] = float(np.std(values))
    return out


def _text_forms(bench: _Bench) -> list[dict[str, Any]]:
    """Full prompt vs brief form (no preamble), cache = 80% of nominal, one split each."""
    rows = []
    for name in QUALITY_DOMAINS:
        held, pool = _split(len(bench.dataset(name).nominal),
                            np.random.default_rng([bench.seed, 77]))
        for form in ("prompt", "brief"):
            nominal, anomalies = bench.vectors(name, form)
            test_x = np.concatenate([nominal[held], anomalies])
            test_y = np.r_[np.zeros(len(held), bool), np.ones(len(anomalies), bool)]
            rows.append({"domain": name, "form": form,
                         **_detect(nominal[pool], test_x, test_y)})
    return rows


def _thresholdtable(bench: _Bench) -> dict[str, Any]:
    """VTOL, cache = random 80% of nominal: accuracy at the 75..95th LOO quantiles."""
    nominal, anomalies = bench.vectors("vtol")
    runs = []
    for s in range(bench.sizes.threshold_seeds):
        held, pool = _split(len(nominal), np.random.default_rng([bench.seed, s, 99]))
        test_x = np.concatenate([nominal[held], anomalies])
        test_y = np.r_[np.zeros(len(held), bool), np.ones(len(anomalies), bool)]
        runs.append(_detect(nominal[pool], test_x, test_y, QUANTILES))
    rows = []
    for q in QUANTILES:
        acc = [r[f"accuracy@{q:g}"] for r in runs]
        bal = [r[f"balanced_accuracy@{q:g}"] for r in runs]
        rows.append({"quantile": q, "accuracy": float(np.mean(acc)),
                     "accuracy_std": float(np.std(acc)), "balanced_accuracy": float(np.mean(bal)),
                     "paper_mpnet": PAPER_MPNET_VTOL[q]})
    return {"domain": "vtol", "cache_fraction": 1 - HOLDOUT, "seeds": len(runs),
            "auroc": float(np.mean([r["auroc"] for r in runs])), "rows": rows}


def plot_quality(domains: Mapping[str, Mapping[str, Any]], path: Path) -> None:
    """2 x 3 figure like ``fig:synthetic-results``: vs cache size (top), vs coverage (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    fig, axes = plt.subplots(2, len(domains), figsize=(4.2 * len(domains), 7), squeeze=False)
    for col, (name, d) in enumerate(domains.items()):
        for row, (key, xlabel) in enumerate((("cache_size", "experiences in cache (log)"),
                                             ("coverage", "nominal concept coverage (%)"))):
            ax = axes[row][col]
            points = [p for p in d[key] if p.get("accuracy") is not None]
            x = [p["cache_size"] if row == 0 else 100 * p["fraction"] for p in points]
            for metric, label, style in (("accuracy", "accuracy", "o-"), ("auroc", "AUROC", "s--"),
                                         ("balanced_accuracy", "balanced accuracy", "^-.")):
                y = np.array([p[metric] for p in points])
                err = np.array([p.get(f"{metric}_std", 0.0) for p in points])
                ax.plot(x, y, style, label=label)
                ax.fill_between(x, y - err, y + err, alpha=0.2)
            ax.axhline(d["n_anomaly"] / d["n_test"], color="grey", lw=0.8, ls=":",
                       label="all-anomaly accuracy")
            if row == 0:
                ax.set_xscale("log")
                ax.xaxis.set_major_formatter(ScalarFormatter())
                ax.xaxis.set_minor_formatter(NullFormatter())
            ax.set_ylim(0.0, 1.02)
            ax.set_xlabel(xlabel)
            ax.grid(True, alpha=0.3)
            ax.set_title(f"{name} ({d['n_nominal']} nominal, {d['n_anomaly']} anomalies)",
                         fontsize=10)
            if col == 0:
                ax.set_ylabel("accuracy / AUROC")
                ax.legend(loc="lower right")
    fig.suptitle(f"Fast anomaly detector, all-MiniLM-L6-v2, top-{K}, "
                 f"tau = {ALPHA:.0%} LOO quantile")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    log.info("wrote %s", path)


# -- score kinds and the conformal FPR (issue 12) ----------------------------------------

# label: (score kind, pairs as a third component)
KINDS: dict[str, tuple[EvalScore, bool]] = {
    "topk": ("topk", False), "detections": ("detections", False),
    "combined": ("combined", False), "combined+pairs": ("combined", True)}
CONFORMAL_KINDS = ("combined", "combined+pairs")
KIND_DOMAINS = ("warehouse", "vehicle", "vtol", "quadrotor")
CONFORMAL_ALPHAS = (0.8, 0.9, 0.95, 0.99)


def bench_kinds(bench: _Bench) -> dict[str, Any]:
    """Per domain, the brief form (what a robot publishes) with its detections, split as
    ``aesop detector domains`` splits it (80% of nominal the cache, the rest and every
    anomaly the test): AUROC, balanced accuracy and FPR of each score kind, loo-quantile
    at alpha 0.95, k 5; then ``combined`` (with and without pairs) calibrated
    split-conformal (the cache's nominal set halved: cache and calibration) at each alpha:
    its FPR on the held-out nominal test samples against the ``1 - alpha`` it promises."""
    from services.embedding.errors import InvalidInput
    from services.embedding.evaluation import EvalConfig, evaluate

    memo = _Memo(bench.embedder)
    domains = {}
    for name in KIND_DOMAINS:
        nominal, test = (_labelled(x)
                         for x in bench.dataset(name, kinds=True).split_for_eval(bench.seed))
        kinds = {label: evaluate(memo, nominal, test, config=EvalConfig(
            k=K, alpha=ALPHA, method="loo-quantile", score=score, pairs=pairs))
            for label, (score, pairs) in KINDS.items()}
        half = len(nominal) // 2
        conformal = []
        for label, alpha in itertools.product(CONFORMAL_KINDS, CONFORMAL_ALPHAS):
            score, pairs = KINDS[label]
            try:
                got = evaluate(memo, nominal[:half], test, nominal[half:], EvalConfig(
                    k=K, alpha=alpha, method="conformal", score=score, pairs=pairs))
            except InvalidInput as exc:  # too few calibration samples to ever flag
                conformal.append({"kind": label, "alpha": alpha, "fpr": None,
                                  "promised": 1 - alpha, "note": exc.message})
                continue
            conformal.append({"kind": label, "alpha": alpha, "fpr": got["fpr"],
                              "promised": 1 - alpha, "tpr": got["tpr"],
                              "n_calibration": got["n_calibration"]})
        domains[name] = {"n_nominal": len(nominal), "n_test": len(test),
                         "kinds": {k: {m: v[m] for m in ("auroc", "balanced_accuracy", "fpr")}
                                   for k, v in kinds.items()},
                         "conformal": conformal}
    return {"model": memo.name, "k": K, "alpha": ALPHA, "domains": domains,
            "quantiles": _kind_quantiles(bench, memo)}


def _kind_quantiles(bench: _Bench, memo: Embedder) -> dict[str, Any]:
    """The paper's VTOL quantile table for the combined kinds: cache = a random 80% of the
    nominal samples (brief form, with detections), loo-quantile at alpha = each quantile,
    accuracy on the rest and every anomaly, averaged over ``threshold_seeds`` splits
    (the same splits as the top-k table of the quality part)."""
    from services.embedding.evaluation import EvalConfig, evaluate

    ds = bench.dataset("vtol", kinds=True)
    nominal, anomalies = _labelled(ds.nominal), _labelled(ds.anomalies)
    runs: dict[tuple[str, float], list[dict[str, Any]]] = {}
    for s in range(bench.sizes.threshold_seeds):
        held, pool = _split(len(nominal), np.random.default_rng([bench.seed, s, 99]))
        test = [nominal[i] for i in held] + anomalies
        for label, q in itertools.product(CONFORMAL_KINDS, QUANTILES):
            score, pairs = KINDS[label]
            runs.setdefault((label, q), []).append(evaluate(
                memo, [nominal[i] for i in pool], test,
                config=EvalConfig(k=K, alpha=q, method="loo-quantile", score=score,
                                  pairs=pairs)))
    rows = [{"kind": label, "quantile": q,
             "accuracy": float(np.mean([r["accuracy"] for r in got])),
             "accuracy_std": float(np.std([r["accuracy"] for r in got])),
             "balanced_accuracy": float(np.mean([r["balanced_accuracy"] for r in got])),
             "paper_mpnet": PAPER_MPNET_VTOL[q]}
            for (label, q), got in runs.items()]
    return {"domain": "vtol", "cache_fraction": 1 - HOLDOUT,
            "seeds": bench.sizes.threshold_seeds, "rows": rows}


def _labelled(samples: Sequence[Any]) -> list[Any]:
    from services.embedding.cache import Labelled

    return [Labelled(s.brief, s.label == "anomaly", tuple(s.concepts)) for s in samples]


class _Memo(Embedder):
    """An embedder that embeds each text once (the kinds part evaluates one domain's
    texts seven times)."""

    def __init__(self, inner: Embedder) -> None:
        self.inner = inner
        self.seen: dict[str, np.ndarray] = {}

    @property
    def name(self) -> str:
        return self.inner.name

    @property
    def dim(self) -> int:
        return self.inner.dim

    def embed(self, texts: Sequence[str], **_: Any) -> np.ndarray:
        new = [t for t in dict.fromkeys(texts) if t not in self.seen]
        if new:
            self.seen.update(zip(new, self.inner.embed(new, batch_size=64), strict=True))
        return np.stack([self.seen[t] for t in texts]) if texts else \
            np.zeros((0, self.dim), dtype=np.float32)


# -- 2. latency ------------------------------------------------------------------------


def bench_latency(bench: _Bench) -> dict[str, Any]:
    """One observation end to end, measured in a fresh process (``--latency-probe``) per
    backend: torch, then the ONNX exports (float32, int8) of the same model.

    The probe's main thread never runs torch or FAISS, as in ``aesop serve``: libgomp
    keeps an OpenMP team per thread that has used it, and a second live team (this
    process's, after the quality part) slows the service's compute thread about 2x."""
    sizes = bench.sizes
    runs = [_probe(["--latency-probe", "--n", str(sizes.latency_n), "--size",
                    str(sizes.latency_cache), "--seed", str(bench.seed), "--model", model,
                    "--threads", str(threads)])
            for model, threads in BACKENDS]
    return runs[0] | {"backends": runs}


def latency_probe(n: int, size: int, seed: int, model: str = DEFAULT_MODEL, threads: int = 1
                  ) -> dict[str, Any]:
    return asyncio.run(_latency(n, size, seed, model, threads))


async def _latency(n: int, size: int, seed: int, model: str = DEFAULT_MODEL,
                   threads: int = 1) -> dict[str, Any]:
    """The observation as a robot publishes it (the brief form) is the measure; the
    paper's full prompt is timed too, to show what its fixed preamble costs."""
    from concurrent.futures import ThreadPoolExecutor

    from services.embedding.entries import on_fresh_thread
    from services.embedding.loading import load_embedder
    from tools.scenes import generate

    embedder = await on_fresh_thread(partial(load_embedder, model, threads=threads))
    ds = generate("vtol", seed=seed, n_nominal=max(n, 200), n_anomaly=n)
    samples = (ds.anomalies + ds.nominal)[:n]
    texts = {"brief": [s.brief for s in samples], "prompt": [s.text for s in samples]}
    cache_x = _Clusters(DIM, seed).sample(size, np.random.default_rng([seed, 1]))
    end_to_end = {}
    with tempfile.TemporaryDirectory(prefix="aesop-bench-") as tmp:
        for microbatch in (True, False):  # the second service reopens the first one's cache
            service = await _service(embedder, Path(tmp), microbatch=microbatch)
            try:
                if "latency" not in service.names():
                    await _fill(service, "latency", cache_x)
                    await service.calibrate("latency", "loo-quantile")
                for form in ("brief", "prompt") if microbatch else ("brief",):
                    batch = texts[form]
                    for text in batch[:10]:  # warm-up
                        await service.scorer.score_texts("latency", [text])
                    end_to_end[form, microbatch] = _stats(
                        [await _score_one(service, batch[i]) for i in range(len(batch))])
            finally:
                await service.close()
    entry_cache = _cache_of(cache_x)
    def timings() -> tuple[dict[str, dict[str, float]], dict[str, float]]:
        vectors = embedder.embed(texts["brief"])
        def embed_one(form: str, i: int) -> object:
            return embedder.embed([texts[form][i]])

        embed = {form: _stats(_time_each(partial(embed_one, form), len(samples)))
                 for form in texts}
        search = _stats(_time_each(lambda i: entry_cache.score(vectors[i:i + 1], K),
                                   len(samples)))
        return embed, search

    with ThreadPoolExecutor(1) as compute:  # one OpenMP thread, as in the service
        embed, search = compute.submit(timings).result()
    e2e = end_to_end["brief", True]
    chars = {form: np.mean([len(t) for t in batch]) for form, batch in texts.items()}
    return {
        "model": embedder.name, "threads": threads, "cache_size": size, "dim": DIM,
        "n": len(samples),
        "text": f"VTOL observation, brief form (mean {chars['brief']:.0f} chars; "
                f"the full prompt has {chars['prompt']:.0f})",
        "end_to_end": e2e, "end_to_end_no_microbatch": end_to_end["brief", False],
        "end_to_end_prompt": end_to_end["prompt", True],
        "embed_only": embed["brief"], "embed_only_prompt": embed["prompt"],
        "search_only": search, "target_ms": LATENCY_TARGET_MS,
        "median_verdict": _verdict(e2e["median_ms"], LATENCY_TARGET_MS["median"]),
        "p99_verdict": _verdict(e2e["p99_ms"], LATENCY_TARGET_MS["p99"]),
    }


async def _service(embedder: Embedder, data_dir: Path, *, microbatch: bool = True,
                   fsync: bool = False) -> CacheService:
    """A started ``CacheService`` on ``data_dir`` that shares the already-loaded model."""
    from services.embedding.loading import EmbedderPool
    from services.embedding.service import CacheService
    from services.embedding.settings import EmbeddingSettings

    settings = EmbeddingSettings(data_dir=data_dir, microbatch=microbatch, fsync=fsync,
                                 zenoh_worker=False)
    service = CacheService(settings, embedders=EmbedderPool(loader=lambda _: embedder))
    await service.start()
    return service


async def _fill(service: CacheService, name: str, vectors: np.ndarray) -> None:
    """Create cache ``name`` pinned to the default model and add ``vectors`` as experiences."""
    from services.embedding.entries import Item
    from services.embedding.settings import DEFAULT_MODEL

    await service.create(name, model=DEFAULT_MODEL, k=K)
    for start in range(0, len(vectors), 5000):
        chunk = vectors[start:start + 5000]
        await service.add(name, [Item(vector=v) for v in chunk.tolist()])


async def _score_one(service: CacheService, text: str) -> float:
    t0 = time.perf_counter()
    batch = await service.scorer.score_texts("latency", [text])
    assert batch.threshold is not None
    _ = batch.results[0].score > batch.threshold  # the verdict
    return time.perf_counter() - t0


def _cache_of(vectors: np.ndarray) -> Any:
    from services.embedding.evaluation import EvalConfig, build_cache

    return build_cache(vectors, EvalConfig(k=K), None)


# -- 3. search -------------------------------------------------------------------------


def bench_search(sizes: Sizes, seed: int) -> dict[str, Any]:
    """Exact vs HNSW single-query search at each size, with build times and recall@5."""
    clusters = _Clusters(DIM, seed)
    queries = clusters.sample(sizes.search_queries, np.random.default_rng([seed, 2]))
    rows: list[dict[str, Any]] = []
    for n in sizes.search_sizes:
        m, projected = _hnsw_m(n, rows[-1] if rows else None)
        rows.append(_search_at(n, m, projected, clusters, queries, sizes, seed))
        gc.collect()
    return {"dim": DIM, "k": K, "queries": sizes.search_queries, "clusters": CLUSTERS,
            "hnsw_build_budget_s": HNSW_BUILD_BUDGET_S, "sizes": rows}


def _hnsw_m(n: int, previous: Mapping[str, Any] | None) -> tuple[int, float | None]:
    """HNSW M for size ``n``: 32, halved (down to 8) while the build time projected
    from the previous size (n log n, roughly linear in M) exceeds the budget."""
    if previous is None:
        return 32, None
    n0, t0, m0 = previous["n"], previous["hnsw_build_s"], previous["hnsw_m"]
    projected = t0 * (n / n0) * math.log(n) / math.log(n0)
    m = m0
    while m > 8 and projected * m / m0 > HNSW_BUILD_BUDGET_S:
        m //= 2
    return m, projected * m / m0


def _search_at(n: int, m: int, projected: float | None, clusters: _Clusters,
               queries: np.ndarray, sizes: Sizes, seed: int) -> dict[str, Any]:
    import faiss

    from services.embedding.index import VectorIndex

    log.info("search: %d vectors, HNSW M=%d%s", n, m,
             f" (projected build {projected:.0f} s)" if projected else "")
    x = clusters.sample(n, np.random.default_rng([seed, 3, n]))
    index = VectorIndex(DIM, "hnsw", hnsw_m=m, query_threads=None)  # FAISS's default first
    t0 = time.perf_counter()
    index.add(x, np.arange(n, dtype=np.int64))  # the exact index: IndexFlatIP storage
    flat_build = time.perf_counter() - t0
    del x
    t0 = time.perf_counter()
    index.search(queries[:1], K)  # the graph is built lazily, on the first search
    hnsw_build = time.perf_counter() - t0
    log.info("search: flat build %.2f s, HNSW build %.1f s", flat_build, hnsw_build)
    for q in queries[:5]:  # warm-up
        index.search_exact(q[None], K)
        index.search(q[None], K)
    n_exact = min(sizes.exact_queries if n >= 500_000 else len(queries), len(queries))
    exact = _stats(_time_each(lambda i: index.search_exact(queries[i:i + 1], K), n_exact))
    approx = _stats(_time_each(lambda i: index.search(queries[i:i + 1], K), len(queries)))
    index.query_threads = 1  # what the service uses: one OpenMP thread per small search
    exact_1 = _stats(_time_each(lambda i: index.search_exact(queries[i:i + 1], K), n_exact))
    approx_1 = _stats(_time_each(lambda i: index.search(queries[i:i + 1], K), len(queries)))
    labels = _stats(_time_each(lambda i: index.labels(), 20))
    _, truth = index.search_exact(queries, K)
    recall = _recall(index, queries, truth)
    ef_default, sweep = index.ef_search, []
    for ef in EF_SEARCH_SWEEP:  # recall against single-query time (one thread), same graph
        index.set_ef_search(ef)
        timed = _stats(_time_each(lambda i: index.search(queries[i:i + 1], K), len(queries)))
        sweep.append({"ef_search": ef, "recall_at_5": _recall(index, queries, truth),
                      "median_ms": timed["median_ms"], "p99_ms": timed["p99_ms"]})
    return {
        "n": n, "faiss_threads": faiss.omp_get_max_threads(), "exact": exact, "hnsw": approx,
        "speedup_exact_over_hnsw": exact["median_ms"] / approx["median_ms"],
        "exact_1_thread": exact_1, "hnsw_1_thread": approx_1,
        "speedup_exact_over_hnsw_1_thread": exact_1["median_ms"] / approx_1["median_ms"],
        "recall_at_5": float(recall),
        "flat_build_s": flat_build, "hnsw_build_s": hnsw_build,
        "hnsw_m": m, "hnsw_ef_construction": faiss.IndexHNSWFlat(8, m).hnsw.efConstruction,
        "hnsw_ef_search": ef_default, "hnsw_projected_build_s": projected,
        "labels_copy_ms": labels["median_ms"],  # paid by every HNSW search (index.labels())
        "ef_search_sweep": sweep,
    }


def _recall(index: Any, queries: np.ndarray, truth: np.ndarray) -> float:
    """recall@K of the index's (HNSW) search against the exact neighbours ``truth``."""
    _, found = index.search(queries, K)
    return float(np.mean([len(set(t) & set(f)) / K for t, f in zip(truth, found, strict=True)]))


# -- 4. leave-one-out ------------------------------------------------------------------


def bench_loo(sizes: Sizes, seed: int) -> dict[str, Any]:
    """``Cache.loo_scores`` at 20k vs FAISS's own batched ``search(x, k+1)`` on the same data."""
    from services.embedding.scoring import loo_topk_scores

    n = sizes.loo_size
    x = _Clusters(DIM, seed).sample(n, np.random.default_rng([seed, 4]))
    cache = _cache_of(x)
    index = cache.index
    members = np.ascontiguousarray(index.vectors())
    loo_times, loo = _time_calls(lambda: cache.loo_scores(K), sizes.loo_repeats)
    faiss_times, (sims, labels) = _time_calls(lambda: index.search_exact(members, K + 1),
                                              sizes.loo_repeats)
    loo_s, faiss_s = float(np.median(loo_times)), float(np.median(faiss_times))
    same = np.abs(loo_topk_scores(sims, labels, index.labels(), K) - loo).max()
    return {
        "n": n, "dim": DIM, "k": K, "repeats": sizes.loo_repeats,
        "loo_scores_s": loo_s, "faiss_search_s": faiss_s,
        "ratio_faiss_over_loo": faiss_s / loo_s,
        "max_abs_diff": float(same),  # the two give the same LOO scores
        "target_s": LOO_TARGET_S, "verdict": _verdict(loo_s, LOO_TARGET_S),
    }


# -- 5. build --------------------------------------------------------------------------


def bench_build(bench: _Bench) -> dict[str, Any]:
    """Texts/s through ``CacheService.add`` (embedding, WAL append with fsync, index add)."""
    return asyncio.run(_build(bench))


async def _build(bench: _Bench) -> dict[str, Any]:
    from services.embedding.entries import Item
    from services.embedding.settings import DEFAULT_MODEL
    from tools.scenes import generate

    n = bench.sizes.build_texts
    texts = [s.brief for s in generate("vtol", seed=bench.seed + 1, n_nominal=n,
                                       n_anomaly=0).nominal]
    embedder = bench.embedder
    with tempfile.TemporaryDirectory(prefix="aesop-bench-") as tmp:
        service = await _service(embedder, Path(tmp), fsync=True)
        try:
            await service.create("build", model=DEFAULT_MODEL, k=K)
            log.info("build: adding %d texts", n)
            t0 = time.perf_counter()
            await service.add("build", [Item(text=t) for t in texts])
            text_s = time.perf_counter() - t0
            vectors = np.array(service.entry("build").cache.index.vectors()).tolist()
            t0 = time.perf_counter()
            await service.add("build", [Item(vector=v) for v in vectors])
            vector_s = time.perf_counter() - t0
        finally:
            await service.close()
    return {
        "texts": n, "embed_batch_size": 64, "seconds": text_s, "texts_per_s": n / text_s,
        "vectors_per_s": n / vector_s,  # the same add without embedding, for the breakdown
        "embedding_share": 1 - vector_s / text_s,
    }


# -- 6. memory -------------------------------------------------------------------------


def _probe(args: list[str]) -> dict[str, Any]:
    """Run ``python -m tools.bench.detector <args>`` and read its one JSON line."""
    cmd = [sys.executable, "-m", "tools.bench.detector", *args]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900,
                          check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"{args[0]} exited {proc.returncode}: {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def bench_memory(sizes: Sizes) -> dict[str, Any]:
    """Peak RSS of a fresh process: model + ``memory_cache`` vectors + a few scores."""
    probe = _probe(["--memory-probe", "--size", str(sizes.memory_cache)])
    peak = probe["peak_rss_mb"] or probe["ru_maxrss_mb"]
    return {**probe, "target_mb": MEMORY_TARGET_MB, "verdict": _verdict(peak, MEMORY_TARGET_MB)}


def memory_probe(size: int, seed: int = 0) -> dict[str, Any]:
    """Runs in the subprocess: RSS (MB) after imports, model, cache build and scoring."""
    import faiss  # noqa: F401  (the imports the service needs, for the baseline)
    import psutil
    import sentence_transformers  # noqa: F401
    import torch  # noqa: F401

    from services.embedding.cache import Cache, CacheConfig
    from services.embedding.loading import load_embedder
    from services.embedding.settings import DEFAULT_MODEL

    process = psutil.Process()

    def rss() -> float:
        return process.memory_info().rss / 2**20

    stages = {"after_imports": rss()}
    embedder = load_embedder(DEFAULT_MODEL)
    embedder.embed(["warm-up"])
    stages["after_model"] = rss()
    cache = Cache(CacheConfig("probe", embedder.name, embedder.dim, K))
    clusters = _Clusters(embedder.dim, seed)
    rng = np.random.default_rng([seed, 5])
    for start in range(0, size, 10_000):  # as a service receives it: requests of <= 10k
        m = min(10_000, size - start)
        ids = [str(i) for i in range(start, start + m)]
        cache.apply(cache.plan_add(clusters.sample(m, rng), ids=ids, texts=[None] * m,
                                   metadata=[{}] * m))
    stages["after_cache"] = rss()
    from tools.scenes import generate

    texts = [s.text for s in generate("vtol", seed=seed, n_nominal=8, n_anomaly=8).samples]
    cache.score(embedder.embed(texts), K)
    stages["after_scoring"] = rss()
    maxrss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KB on Linux
    return {"cache_size": cache.size, "dim": embedder.dim, "rss_mb": stages,
            "baseline_rss_mb": stages["after_imports"], "peak_rss_mb": _vm_hwm_mb(),
            "ru_maxrss_mb": maxrss_kb / 1024}


def _vm_hwm_mb() -> float | None:
    """Peak RSS of this process image (``VmHWM``), in MB.

    Unlike ``ru_maxrss`` it does not inherit the parent's peak: Linux carries
    the high-water mark of the pre-exec address space (the parent's, after a
    vfork) into the child's ``ru_maxrss``, so a probe started by a 4 GB parent
    reports 4 GB there.
    """
    with contextlib.suppress(OSError), open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return None


# -- 7. REST -----------------------------------------------------------------------------


def bench_rest(bench: _Bench) -> dict[str, Any]:
    """Concurrent single-text score requests against real servers: the default model
    (ONNX float32) with micro-batching on and off, then the torch backend (on)."""
    sizes = bench.sizes
    ds = bench.dataset("vtol")
    cache_x = bench.nominal_vectors("vtol", sizes.rest_cache, "brief")
    texts = [s.brief for s in ds.nominal[sizes.rest_cache:] + ds.anomalies]
    runs = {}
    for label, microbatch, model in (("microbatch", True, None),  # one after the other
                                     ("no_microbatch", False, None),
                                     ("torch", True, DEFAULT_MODEL)):
        with tempfile.TemporaryDirectory(prefix="aesop-bench-") as tmp, \
                _server(Path(tmp), microbatch=microbatch) as base:
            runs[label] = asyncio.run(_rest_run(base, cache_x, texts, sizes, model))
        log.info("rest %s: %.1f req/s, p50 %.0f ms", label, runs[label]["requests_per_s"],
                 runs[label]["latency"]["median_ms"])
    on, off, torch = runs["microbatch"], runs["no_microbatch"], runs["torch"]
    return {
        "cache_size": len(cache_x), "requests": sizes.rest_requests,
        "concurrency": sizes.rest_concurrency, **runs,
        "throughput_ratio": on["requests_per_s"] / off["requests_per_s"],
        "p50_ratio": on["latency"]["median_ms"] / off["latency"]["median_ms"],
        "p99_ratio": on["latency"]["p99_ms"] / off["latency"]["p99_ms"],
        "onnx_over_torch": on["requests_per_s"] / torch["requests_per_s"],
    }


@contextlib.contextmanager
def _server(data_dir: Path, *, microbatch: bool) -> Iterator[str]:
    """``aesop serve embedding`` on a free loopback port; stopped on exit, whatever happens."""
    port = free_port()
    env = {"AESOP_EMBEDDING_ZENOH_WORKER": "false",
           "AESOP_EMBEDDING_MICROBATCH": str(microbatch).lower(), "AESOP_LOG_LEVEL": "warning"}
    with ServiceProcess(["serve", "embedding", "--port", str(port), "--data-dir",
                         str(data_dir / "data")], port=port, env=env,
                        log_path=data_dir / "server.log", unset=["AESOP_ADMIN_TOKEN"]) as proc:
        yield proc.url


async def _rest_run(base: str, cache_x: np.ndarray, texts: Sequence[str], sizes: Sizes,
                    model: str | None = None) -> dict[str, Any]:
    import httpx

    limits = httpx.Limits(max_connections=sizes.rest_concurrency,
                          max_keepalive_connections=sizes.rest_concurrency)
    async with httpx.AsyncClient(base_url=base, timeout=120, limits=limits) as client:
        info = await _rest_setup(client, cache_x, model)
        await _rest_load(client, texts, sizes.rest_concurrency, sizes.rest_concurrency)  # warm-up
        t0 = time.perf_counter()
        latencies, errors = await _rest_load(client, texts, sizes.rest_requests,
                                             sizes.rest_concurrency)
        wall = time.perf_counter() - t0
        metrics = (await client.get("/metrics")).text
    return {"requests_per_s": sizes.rest_requests / wall, "latency": _stats(latencies),
            "errors": errors, "wall_s": wall, "mean_batch": _mean_batch(metrics),
            "model": info["model"]}


async def _rest_setup(client: Any, cache_x: np.ndarray, model: str | None) -> dict[str, Any]:
    """PUT the cache (the server loads the model; None: the service's default), POST the
    vectors, calibrate tau; the cache's info."""
    body = {"k": K} | ({"model": model} if model else {})
    r = await client.put("/v1/caches/bench", json=body)
    r.raise_for_status()
    for start in range(0, len(cache_x), 500):
        chunk = cache_x[start:start + 500]
        ids = [f"n{i}" for i in range(start, start + len(chunk))]
        r = await client.post("/v1/caches/bench/experiences",
                              json={"vectors": chunk.tolist(), "ids": ids})
        r.raise_for_status()
    r = await client.post("/v1/caches/bench/calibrate", json={"method": "loo-quantile"})
    r.raise_for_status()
    return (await client.get("/v1/caches/bench")).json()


async def _rest_load(client: Any, texts: Sequence[str], n: int, concurrency: int
                     ) -> tuple[list[float], int]:
    """``n`` single-text score requests from ``concurrency`` clients; (latencies s, errors)."""
    latencies: list[float] = []
    errors = 0
    counter = iter(range(n))

    async def worker() -> None:
        nonlocal errors
        for i in counter:
            t0 = time.perf_counter()
            r = await client.post("/v1/caches/bench/score",
                                  json={"texts": [texts[i % len(texts)]]})
            latencies.append(time.perf_counter() - t0)
            errors += r.status_code != 200

    await asyncio.gather(*(worker() for _ in range(concurrency)))
    return latencies, errors


def _mean_batch(metrics: str) -> float | None:
    """Mean texts per micro-batched embedding call, from the Prometheus text."""
    values = {}
    for line in metrics.splitlines():
        for key in ("aesop_embedding_batch_size_sum", "aesop_embedding_batch_size_count"):
            if line.startswith(key + " "):
                values[key] = float(line.split()[1])
    count = values.get("aesop_embedding_batch_size_count")
    return values["aesop_embedding_batch_size_sum"] / count if count else None


# -- tables -----------------------------------------------------------------------------


def bench_restart(sizes: Sizes, seed: int) -> dict[str, Any]:
    """An HNSW cache of ``restart_cache`` 384-d vectors on the store (fsync on): the time to
    commit it, build its graph, save its index, and open it again with the index file
    (loaded, graph included) and without it (built from the stored vectors)."""
    from services.embedding.cache import Cache, CacheConfig
    from services.embedding.store import INDEX_DIR, Store

    n, dim, batch = sizes.restart_cache, 384, 50_000
    x = np.random.default_rng(seed).standard_normal((n, dim)).astype(np.float32)
    query = x[:1] / np.linalg.norm(x[:1])
    out: dict[str, Any] = {"n": n, "dim": dim}
    with tempfile.TemporaryDirectory(prefix="aesop-restart-") as tmp:
        root = Path(tmp)
        with Store(root) as store:
            cache = Cache(CacheConfig("restart", None, dim, index="hnsw"))
            store.create(cache.config)
            t0 = time.perf_counter()
            for start in range(0, n, batch):
                m = min(batch, n - start)
                op = cache.plan_add(x[start:start + m], ids=[None] * m, texts=[None] * m,
                                    metadata=[{}] * m)
                store.commit(cache.name, op, cache.header.after(op))
                cache.apply(op)
            out["commit_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            cache.score(query, K)  # the first search builds the graph
            out["graph_build_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            store.save_index(cache)
            out["index_save_s"] = time.perf_counter() - t0
        del cache
        gc.collect()
        with Store(root) as store:
            t0 = time.perf_counter()
            loaded = store.load("restart")
            loaded.score(query, K)
            out["restart_with_index_s"] = time.perf_counter() - t0
            out["graph_loaded"] = loaded.index.graph_ready
        del loaded
        gc.collect()
        shutil.rmtree(root / INDEX_DIR)
        with Store(root) as store:
            t0 = time.perf_counter()
            store.load("restart").score(query, K)
            out["restart_without_index_s"] = time.perf_counter() - t0
        out["database_mb"] = sum(f.stat().st_size for f in root.glob("embedding.sqlite3*")) / 1e6
    out["ratio"] = out["restart_without_index_s"] / out["restart_with_index_s"]
    return out


def render(part: str, r: Mapping[str, Any]) -> str:
    """The human-readable tables of one part's result."""
    if "error" in r:
        return table(f"[{part}] FAILED", [{"error": r["error"]}])
    return {"quality": _render_quality, "kinds": _render_kinds,
            "latency": _render_latency, "search": _render_search,
            "loo": _render_loo, "build": _render_build, "memory": _render_memory,
            "rest": _render_rest, "restart": _render_restart}[part](r)


def _render_quality(r: Mapping[str, Any]) -> str:
    out = []
    for name, d in r["domains"].items():
        head = (f"[quality] {name}: {d['n_nominal']} nominal, {d['n_anomaly']} anomalies, "
                f"test {d['n_test']}; mean (std) over {r['repeats']} splits")
        for key, label in (("cache_size", "cache fraction"), ("coverage", "concept coverage")):
            rows = [{label: f"{p['fraction']:.0%}", "cache size": round(p["cache_size"]),
                     **({"concepts": f"{p['concepts_covered']:.0%}"} if key == "coverage"
                        else {}),
                     "accuracy": _pm(p, "accuracy"), "balanced": _pm(p, "balanced_accuracy"),
                     "AUROC": _pm(p, "auroc"), "TPR": p.get("tpr"), "FPR": p.get("fpr")}
                    for p in d[key]]
            out.append(table(f"{head} -- vs {label}", rows))
    t = r["thresholds"]
    rows = [{"LOO quantile": f"{row['quantile']:.0%}",
             "accuracy": f"{row['accuracy']:.3f} ({row['accuracy_std']:.3f})",
             "balanced": row["balanced_accuracy"], "paper MPNet": row["paper_mpnet"]}
            for row in t["rows"]]
    out.append(table(f"[quality] threshold quantiles, VTOL, cache = random 80% of nominal, "
                      f"{t['seeds']} seeds, MiniLM (AUROC {t['auroc']:.3f}) vs paper MPNet", rows))
    rows = [{"domain": f["domain"], "text embedded": f["form"], "AUROC": f["auroc"],
             "accuracy": f["accuracy"], "balanced": f["balanced_accuracy"], "TPR": f["tpr"],
             "FPR": f["fpr"]} for f in r["text_forms"]]
    out.append(table("[quality] full prompt vs brief observation (no preamble), cache = 80% "
                      "of nominal, tau = 95% LOO quantile", rows))
    if "plot" in r:
        out.append(f"figure: {r['plot']}\n")
    return "\n".join(out)


def _pm(point: Mapping[str, Any], key: str) -> str:
    if point.get(key) is None:
        return "-"
    return f"{point[key]:.3f}" + (f" ({point[key + '_std']:.3f})" if key + "_std" in point else "")


def _render_kinds(r: Mapping[str, Any]) -> str:
    rows = [{"domain": name, "cache / test": f"{d['n_nominal']} / {d['n_test']}",
             **{f"AUROC {k}": d["kinds"][k]["auroc"] for k in KINDS},
             **{f"bal.acc {k}": d["kinds"][k]["balanced_accuracy"] for k in KINDS},
             **{f"FPR {k}": d["kinds"][k]["fpr"] for k in CONFORMAL_KINDS}}
            for name, d in r["domains"].items()]
    out = table(f"[kinds] score kinds, brief form with detections, {r['model']}, k {r['k']}, "
                f"loo-quantile alpha {r['alpha']} (target AUROC >= 0.95)", rows)
    def fpr(c: Mapping[str, Any]) -> str:
        if c["fpr"] is None:
            return "n too small"
        return f"{c['fpr']:.3f} {'ok' if c['fpr'] <= c['promised'] + 0.01 else 'OVER'}"

    rows = [{"domain": name, "kind": kind,
             **{f"FPR @ {c['alpha']:g} (<= {c['promised']:.2f})": fpr(c)
                for c in d["conformal"] if c["kind"] == kind}}
            for name, d in r["domains"].items() for kind in CONFORMAL_KINDS]
    out += "\n" + table("[kinds] split conformal: held-out nominal FPR vs 1 - alpha "
                        "(target: at most 1 - alpha + 1%)", rows)
    q = r["quantiles"]
    rows = [{"kind": row["kind"], "quantile": row["quantile"],
             "accuracy": f"{row['accuracy']:.3f} ± {row['accuracy_std']:.3f}",
             "balanced acc": row["balanced_accuracy"], "paper MPNet": row["paper_mpnet"],
             "target": "met" if row["accuracy"] >= row["paper_mpnet"] else "missed"}
            for row in q["rows"]]
    return out + "\n" + table(
        f"[kinds] threshold quantiles, VTOL brief form with detections, cache = random "
        f"{q['cache_fraction']:.0%} of nominal, {q['seeds']} splits (target: at or above "
        "the paper's MPNet)", rows)


def _render_latency(r: Mapping[str, Any]) -> str:
    rows = [{"path": label, "n": s["n"], "median ms": s["median_ms"], "p99 ms": s["p99_ms"]}
            for label, s in (("end to end (score_texts, microbatch on)", r["end_to_end"]),
                             ("end to end (microbatch off)", r["end_to_end_no_microbatch"]),
                             ("end to end, full paper prompt", r["end_to_end_prompt"]),
                             ("embed only", r["embed_only"]),
                             ("embed only, full paper prompt", r["embed_only_prompt"]),
                             ("search + top-5 score only", r["search_only"]))]
    t = r["target_ms"]
    out = table(f"[latency] one observation vs a {r['cache_size']}-entry cache; {r['text']}; "
                f"target median <= {t['median']:g} ms: {r['median_verdict']}, "
                f"p99 <= {t['p99']:g} ms: {r['p99_verdict']}", rows)
    if "backends" not in r:
        return out
    torch_ms = r["end_to_end"]["median_ms"]
    b = BACKEND_TARGET_MS
    rows = [{"backend": x["model"], "threads": x["threads"],
             "e2e median ms": x["end_to_end"]["median_ms"],
             "e2e p99 ms": x["end_to_end"]["p99_ms"],
             "embed median ms": x["embed_only"]["median_ms"],
             "vs torch": f"{torch_ms / x['end_to_end']['median_ms']:.2f}x",
             "target": f"{_verdict(x['end_to_end']['median_ms'], b['median'])} / "
                       f"{_verdict(x['end_to_end']['p99_ms'], b['p99'])}"}
            for x in r["backends"]]
    return out + "\n" + table(
        f"[latency] by backend and threads per inference (target median <= {b['median']:g} "
        f"ms / p99 <= {b['p99']:g} ms)", rows)


def _render_search(r: Mapping[str, Any]) -> str:
    rows = []
    for s in r["sizes"]:
        for suffix, threads in (("", s["faiss_threads"]), ("_1_thread", 1)):
            exact, hnsw = s["exact" + suffix], s["hnsw" + suffix]
            rows.append({"n": s["n"], "threads": threads, "exact med ms": exact["median_ms"],
                         "exact p99 ms": exact["p99_ms"], "hnsw med ms": hnsw["median_ms"],
                         "hnsw p99 ms": hnsw["p99_ms"],
                         "exact/hnsw": s["speedup_exact_over_hnsw" + suffix]})
    builds = [{"n": s["n"], "recall@5": s["recall_at_5"], "flat build s": s["flat_build_s"],
               "hnsw build s": s["hnsw_build_s"], "projected s": s["hnsw_projected_build_s"],
               "M": s["hnsw_m"], "efConstruction": s["hnsw_ef_construction"],
               "efSearch": s["hnsw_ef_search"], "labels() ms": s["labels_copy_ms"]}
              for s in r["sizes"]]
    title = (f"[search] k={r['k']}, clustered unit vectors dim {r['dim']} "
             f"({r['clusters']} centres)")
    sweep = [{"n": s["n"], "M": s["hnsw_m"], "efSearch": row["ef_search"],
              "recall@5": row["recall_at_5"], "med ms": row["median_ms"],
              "p99 ms": row["p99_ms"], "recall >= 0.95": "yes" if row["recall_at_5"] >= 0.95
              else "no"} for s in r["sizes"] for row in s.get("ef_search_sweep", ())]
    return (table(f"{title}: single-query latency (FAISS OpenMP threads)", rows) + "\n"
            + table(f"{title}: builds and HNSW recall@5 over {r['queries']} queries", builds)
            + "\n" + table(f"{title}: HNSW efSearch against recall@5 and single-query time "
                           "(1 thread)", sweep))


def _render_loo(r: Mapping[str, Any]) -> str:
    return table(
        f"[loo] leave-one-out at {r['n']} x {r['dim']}, k={r['k']}, median of {r['repeats']}; "
        f"target <= {r['target_s']:g} s: {r['verdict']}",
        [{"Cache.loo_scores s": r["loo_scores_s"], "faiss search(x, k+1) s": r["faiss_search_s"],
          "faiss / loo": r["ratio_faiss_over_loo"], "max |diff|": r["max_abs_diff"]}])


def _render_build(r: Mapping[str, Any]) -> str:
    return table(f"[build] CacheService.add of {r['texts']} brief VTOL observations, batch "
                  f"{r['embed_batch_size']}",
                  [{"seconds": r["seconds"], "texts/s": r["texts_per_s"],
                    "vectors/s (no embedding)": r["vectors_per_s"],
                    "embedding share": f"{r['embedding_share']:.1%}"}])


def _render_memory(r: Mapping[str, Any]) -> str:
    rss = r["rss_mb"]
    return table(f"[memory] subprocess, model + {r['cache_size']}-vector cache; "
                  f"target peak <= {r['target_mb']:g} MB: {r['verdict']}",
                  [{"after imports MB": rss["after_imports"], "+ model MB": rss["after_model"],
                    "+ cache MB": rss["after_cache"], "+ scoring MB": rss["after_scoring"],
                    "peak (VmHWM) MB": r["peak_rss_mb"], "ru_maxrss MB": r["ru_maxrss_mb"]}])


def _render_restart(r: Mapping[str, Any]) -> str:
    rows = [{"step": label, "s": r[key]} for label, key in (
        ("commit (SQLite, fsync)", "commit_s"), ("HNSW graph build", "graph_build_s"),
        ("index save", "index_save_s"), ("restart, index file current", "restart_with_index_s"),
        ("restart, no index file (rebuild)", "restart_without_index_s"))]
    return table(f"[restart] HNSW cache of {r['n']:,} x {r['dim']} on the store "
                 f"({r['database_mb']:.0f} MB database); the saved index makes a restart "
                 f"{r['ratio']:.1f}x faster", rows)


def _render_rest(r: Mapping[str, Any]) -> str:
    rows = [{"server": label, "model": run["model"], "req/s": run["requests_per_s"],
             "p50 ms": run["latency"]["median_ms"], "p99 ms": run["latency"]["p99_ms"],
             "errors": run["errors"], "mean batch": run["mean_batch"]}
            for label in ("microbatch", "no_microbatch", "torch") for run in (r[label],)]
    rows.append({"server": "ratio on/off", "model": None, "req/s": r["throughput_ratio"],
                 "p50 ms": r["p50_ratio"], "p99 ms": r["p99_ratio"], "errors": None,
                 "mean batch": None})
    rows.append({"server": "ratio default/torch (both on)", "model": None,
                 "req/s": r["onnx_over_torch"], "p50 ms": None, "p99 ms": None,
                 "errors": None, "mean batch": None})
    return table(f"[rest] POST /score, one text each, {r['requests']} requests from "
                  f"{r['concurrency']} concurrent clients, cache {r['cache_size']}", rows)


# -- the memory probe's command line ----------------------------------------------------


def _main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="helpers of `aesop bench detector`")
    probe = parser.add_mutually_exclusive_group(required=True)
    probe.add_argument("--memory-probe", action="store_true")
    probe.add_argument("--latency-probe", action="store_true")
    parser.add_argument("--size", type=int, default=100_000)
    parser.add_argument("--n", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--model", default=DEFAULT_MODEL)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    with contextlib.redirect_stdout(sys.stderr):
        if args.memory_probe:
            result = memory_probe(args.size, args.seed)
        else:
            result = latency_probe(args.n, args.size, args.seed, args.model, args.threads)
    print(json.dumps(_jsonable(result), allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(_main())
