"""``rest``: scoring over HTTP under 32 concurrent clients, micro-batching on vs off.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from services.embedding.settings import DEFAULT_MODEL
from shared.process import ServiceProcess, free_port
from shared.tables import table

if TYPE_CHECKING:
    pass
from .common import Bench, K, Sizes, stats

log = logging.getLogger(__name__)


def bench_rest(bench: Bench) -> dict[str, Any]:
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
    env = {"AESOP_EMBEDDING_ZENOH_WORKER": "false", "AESOP_LOG_LEVEL": "warning",
           "AESOP_EMBEDDING_TUNING__MICROBATCH": str(microbatch).lower()}
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
    return {"requests_per_s": sizes.rest_requests / wall, "latency": stats(latencies),
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


def render_rest(r: Mapping[str, Any]) -> str:
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
