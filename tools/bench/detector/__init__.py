"""``aesop bench detector``: quality, score kinds, drift, latency, search, calibration,
build, memory, REST, restart.

Ten parts, each one function returning a JSON-able dict (``--only PART``):

* ``quality``  accuracy / AUROC vs cache size and vs concept coverage on the
  synthetic domains (paper §V-A, ``fig:synthetic-results``), top-5 scoring,
  tau = 95th LOO quantile (eq. 2); plus the threshold-quantile table of the
  appendix (``supp:threshold-analysis``) on VTOL.
* ``kinds``    per domain (three synthetic, quadrotor), brief form with detections: AUROC,
  balanced accuracy and FPR of the top-k, detection and combined scores, and the
  split-conformal FPR of the combined score against alpha.
* ``drift``    a new captioner's wording on the synthetic domains: zero-shot AUROC / FPR per
  score kind, the curve after 0..80 reviewed scenes accepted, the drift monitor's delay
  and its false alarms on 10,000 frames of the old wording.
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

Progress goes to stderr (:mod:`tools.progress`: the part, n of N, texts embedded; logging),
tables to stdout only when asked; the
returned dict holds no NaN. Timings on the 2-core machines are noisy: every
number is a median or p99 and comparisons are ratios measured in one run
(``meta.load_average`` records how busy the machine was).

``python -m tools.bench.detector --memory-probe`` is the memory part's
subprocess (``__main__.py``); it prints one JSON line. One module per part.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from shared.tables import table
from tools import progress

from .build import bench_build, render_build
from .common import FULL, QUICK, Bench, jsonable
from .drift import bench_drift, render_drift
from .kinds import bench_kinds, render_kinds
from .latency import bench_latency, render_latency
from .memory import bench_memory, render_memory
from .quality import bench_quality, render_quality
from .rest import bench_rest, render_rest
from .restart import bench_restart, render_restart
from .search import bench_loo, bench_search, render_loo, render_search

log = logging.getLogger(__name__)


PARTS = ("quality", "kinds", "drift", "latency", "search", "loo", "build", "memory", "rest",
         "restart")


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
    bench = Bench(sizes, seed)
    out = sys.stdout
    started = time.perf_counter()
    result: dict[str, Any] = {"meta": _meta(quick, seed, parts)}
    runners: dict[str, Callable[[], dict[str, Any]]] = {
        "quality": lambda: bench_quality(bench, plot),
        "kinds": lambda: bench_kinds(bench),
        "drift": lambda: bench_drift(bench),
        "latency": lambda: bench_latency(bench),
        "search": lambda: bench_search(sizes, seed),
        "loo": lambda: bench_loo(sizes, seed),
        "build": lambda: bench_build(bench),
        "memory": lambda: bench_memory(sizes),
        "rest": lambda: bench_rest(bench),
        "restart": lambda: bench_restart(sizes, seed),
    }
    with contextlib.redirect_stdout(sys.stderr):  # stray prints must not reach the JSON
        for n, part in enumerate(parts, 1):
            progress.step(part, n, len(parts))
            t0 = time.perf_counter()
            try:
                result[part] = runners[part]()
            except Exception as exc:  # report the failure, run the other parts
                log.error("bench %s failed:\n%s", part, traceback.format_exc())
                result[part] = {"error": f"{type(exc).__name__}: {exc}"}
            result[part]["wall_s"] = time.perf_counter() - t0
            progress.say(f"bench detector: {part} done in {result[part]['wall_s']:.1f} s")
            if table:
                progress.out(render(part, result[part]), file=out)
    result["meta"]["wall_s"] = time.perf_counter() - started
    result["meta"]["load_average_end"] = list(os.getloadavg())
    if table:
        print(f"total wall time {result['meta']['wall_s']:.1f} s, load average "
              f"{result['meta']['load_average_start'][0]:.1f} -> "
              f"{result['meta']['load_average_end'][0]:.1f}", file=out)
    return jsonable(result)


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


def render(part: str, r: Mapping[str, Any]) -> str:
    """The human-readable tables of one part's result."""
    if "error" in r:
        return table(f"[{part}] FAILED", [{"error": r["error"]}])
    return {"quality": render_quality, "kinds": render_kinds, "drift": render_drift,
            "latency": render_latency, "search": render_search,
            "loo": render_loo, "build": render_build, "memory": render_memory,
            "rest": render_rest, "restart": render_restart}[part](r)
