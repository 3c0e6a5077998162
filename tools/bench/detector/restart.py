"""``restart``: an HNSW cache on the SQLite store: commit, graph build, index save, and a
restart that loads the saved index vs one that must rebuild it.
"""

from __future__ import annotations

import gc
import shutil
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.tables import table

if TYPE_CHECKING:
    pass
from .common import K, Sizes


def bench_restart(sizes: Sizes, seed: int) -> dict[str, Any]:
    """An HNSW cache of ``restart_cache`` 384-d vectors on the store (fsync on): the time to
    commit it, build its graph, save its index, and open it again with the index file
    (loaded, graph included) and without it (built from the stored vectors)."""
    from services.embedding.detector.cache import Cache, CacheConfig
    from services.embedding.storage.indexfiles import INDEX_DIR
    from services.embedding.storage.store import Store

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


def render_restart(r: Mapping[str, Any]) -> str:
    rows = [{"step": label, "s": r[key]} for label, key in (
        ("commit (SQLite, fsync)", "commit_s"), ("HNSW graph build", "graph_build_s"),
        ("index save", "index_save_s"), ("restart, index file current", "restart_with_index_s"),
        ("restart, no index file (rebuild)", "restart_without_index_s"))]
    return table(f"[restart] HNSW cache of {r['n']:,} x {r['dim']} on the store "
                 f"({r['database_mb']:.0f} MB database); the saved index makes a restart "
                 f"{r['ratio']:.1f}x faster", rows)
