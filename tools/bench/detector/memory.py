"""``memory``: peak RSS of a subprocess holding the model and a 100k cache.
"""

from __future__ import annotations

import contextlib
import resource
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from services.embedding.settings import DEFAULT_MODEL
from shared.tables import table

if TYPE_CHECKING:
    pass
from .common import MEMORY_TARGET_MB, Clusters, K, Sizes, pass_or_fail, run_probe


def bench_memory(sizes: Sizes) -> dict[str, Any]:
    """Peak RSS of a fresh process: model + ``memory_cache`` vectors + a few scores."""
    probe = run_probe(["--memory-probe", "--size", str(sizes.memory_cache)])
    peak = probe["peak_rss_mb"] or probe["ru_maxrss_mb"]
    return {**probe, "target_mb": MEMORY_TARGET_MB, "verdict": pass_or_fail(peak, MEMORY_TARGET_MB)}


def memory_probe(size: int, seed: int = 0) -> dict[str, Any]:
    """Runs in the subprocess: RSS (MB) after imports, model, cache build and scoring."""
    import faiss  # noqa: F401  (the imports the service needs, for the baseline)
    import psutil
    import sentence_transformers  # noqa: F401
    import torch  # noqa: F401

    from services.embedding.detector.cache import Cache, CacheConfig
    from services.embedding.models.loading import load_embedder

    process = psutil.Process()

    def rss() -> float:
        return process.memory_info().rss / 2**20

    stages = {"after_imports": rss()}
    embedder = load_embedder(DEFAULT_MODEL)
    embedder.embed(["warm-up"])
    stages["after_model"] = rss()
    cache = Cache(CacheConfig("probe", embedder.name, embedder.dim, K))
    clusters = Clusters(embedder.dim, seed)
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


def render_memory(r: Mapping[str, Any]) -> str:
    rss = r["rss_mb"]
    return table(f"[memory] subprocess, model + {r['cache_size']}-vector cache; "
                  f"target peak <= {r['target_mb']:g} MB: {r['verdict']}",
                  [{"after imports MB": rss["after_imports"], "+ model MB": rss["after_model"],
                    "+ cache MB": rss["after_cache"], "+ scoring MB": rss["after_scoring"],
                    "peak (VmHWM) MB": r["peak_rss_mb"], "ru_maxrss MB": r["ru_maxrss_mb"]}])
