"""``search``: exact (flat) vs HNSW search (single-query latency, build time, recall@5);
``loo``: leave-one-out calibration at 20k vs FAISS's batched search.
"""

from __future__ import annotations

import gc
import logging
import math
import time
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.tables import table

if TYPE_CHECKING:
    pass
from .common import (
    CLUSTERS,
    DIM,
    EF_SEARCH_SWEEP,
    HNSW_BUILD_BUDGET_S,
    LOO_TARGET_S,
    Clusters,
    K,
    Sizes,
    cache_of,
    pass_or_fail,
    stats,
    time_calls,
    time_each,
)

log = logging.getLogger(__name__)


def bench_search(sizes: Sizes, seed: int) -> dict[str, Any]:
    """Exact vs HNSW single-query search at each size, with build times and recall@5."""
    clusters = Clusters(DIM, seed)
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


def _search_at(n: int, m: int, projected: float | None, clusters: Clusters,
               queries: np.ndarray, sizes: Sizes, seed: int) -> dict[str, Any]:
    import faiss

    from services.embedding.detector.index import VectorIndex

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
    exact = stats(time_each(lambda i: index.search_exact(queries[i:i + 1], K), n_exact))
    approx = stats(time_each(lambda i: index.search(queries[i:i + 1], K), len(queries)))
    index.query_threads = 1  # what the service uses: one OpenMP thread per small search
    exact_1 = stats(time_each(lambda i: index.search_exact(queries[i:i + 1], K), n_exact))
    approx_1 = stats(time_each(lambda i: index.search(queries[i:i + 1], K), len(queries)))
    labels = stats(time_each(lambda i: index.labels(), 20))
    _, truth = index.search_exact(queries, K)
    recall = _recall(index, queries, truth)
    ef_default, sweep = index.ef_search, []
    for ef in EF_SEARCH_SWEEP:  # recall against single-query time (one thread), same graph
        index.set_ef_search(ef)
        timed = stats(time_each(lambda i: index.search(queries[i:i + 1], K), len(queries)))
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


def bench_loo(sizes: Sizes, seed: int) -> dict[str, Any]:
    """``Cache.loo_scores`` at 20k vs FAISS's own batched ``search(x, k+1)`` on the same data."""
    from services.embedding.detector.scoring import loo_topk_scores

    n = sizes.loo_size
    x = Clusters(DIM, seed).sample(n, np.random.default_rng([seed, 4]))
    cache = cache_of(x)
    index = cache.index
    members = np.ascontiguousarray(index.vectors())
    loo_times, loo = time_calls(lambda: cache.loo_scores(K), sizes.loo_repeats)
    faiss_times, (sims, labels) = time_calls(lambda: index.search_exact(members, K + 1),
                                              sizes.loo_repeats)
    loo_s, faiss_s = float(np.median(loo_times)), float(np.median(faiss_times))
    same = np.abs(loo_topk_scores(sims, labels, index.labels(), K) - loo).max()
    return {
        "n": n, "dim": DIM, "k": K, "repeats": sizes.loo_repeats,
        "loo_scores_s": loo_s, "faiss_search_s": faiss_s,
        "ratio_faiss_over_loo": faiss_s / loo_s,
        "max_abs_diff": float(same),  # the two give the same LOO scores
        "target_s": LOO_TARGET_S, "verdict": pass_or_fail(loo_s, LOO_TARGET_S),
    }


def render_search(r: Mapping[str, Any]) -> str:
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


def render_loo(r: Mapping[str, Any]) -> str:
    return table(
        f"[loo] leave-one-out at {r['n']} x {r['dim']}, k={r['k']}, median of {r['repeats']}; "
        f"target <= {r['target_s']:g} s: {r['verdict']}",
        [{"Cache.loo_scores s": r["loo_scores_s"], "faiss search(x, k+1) s": r["faiss_search_s"],
          "faiss / loo": r["ratio_faiss_over_loo"], "max |diff|": r["max_abs_diff"]}])
