"""``build``: texts/s through ``CacheService.add`` (embedding dominates).
"""

from __future__ import annotations

import asyncio
import logging
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from services.embedding.settings import DEFAULT_MODEL
from shared.tables import table

if TYPE_CHECKING:
    pass
from .common import Bench, K, open_service

log = logging.getLogger(__name__)


def bench_build(bench: Bench) -> dict[str, Any]:
    """Texts/s through ``CacheService.add`` (embedding, WAL append with fsync, index add)."""
    return asyncio.run(_build(bench))


async def _build(bench: Bench) -> dict[str, Any]:
    from services.embedding.schemas import Item
    from tools.scenes import generate

    n = bench.sizes.build_texts
    texts = [s.brief for s in generate("vtol", seed=bench.seed + 1, n_nominal=n,
                                       n_anomaly=0).nominal]
    embedder = bench.embedder
    with tempfile.TemporaryDirectory(prefix="aesop-bench-") as tmp:
        service = await open_service(embedder, Path(tmp), fsync=True)
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


def render_build(r: Mapping[str, Any]) -> str:
    return table(f"[build] CacheService.add of {r['texts']} brief VTOL observations, batch "
                  f"{r['embed_batch_size']}",
                  [{"seconds": r["seconds"], "texts/s": r["texts_per_s"],
                    "vectors/s (no embedding)": r["vectors_per_s"],
                    "embedding share": f"{r['embedding_share']:.1%}"}])
