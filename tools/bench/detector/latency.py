"""``latency``: one observation end to end against a 20k cache, per embedding backend.

Through ``Scorer.score_texts``, with the embed-only and search-only parts, per embedding
backend (torch, ONNX float32, ONNX int8).
"""

from __future__ import annotations

import asyncio
import tempfile
from collections.abc import Mapping
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from services.embedding.settings import DEFAULT_MODEL
from shared.tables import table

if TYPE_CHECKING:
    pass
from .common import (
    BACKEND_TARGET_MS,
    BACKENDS,
    DIM,
    LATENCY_TARGET_MS,
    Bench,
    Clusters,
    K,
    cache_of,
    fill,
    open_service,
    pass_or_fail,
    run_probe,
    score_one,
    stats,
    time_each,
)


def bench_latency(bench: Bench) -> dict[str, Any]:
    """One observation end to end, measured in a fresh process (``--latency-probe``) per
    backend: torch, then the ONNX exports (float32, int8) of the same model.

    The probe's main thread never runs torch or FAISS, as in ``aesop serve``: libgomp
    keeps an OpenMP team per thread that has used it, and a second live team (this
    process's, after the quality part) slows the service's compute thread about 2x."""
    sizes = bench.sizes
    runs = [run_probe(["--latency-probe", "--n", str(sizes.latency_n), "--size",
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

    from services.embedding.models.loading import load_embedder
    from shared.threads import on_fresh_thread
    from tools.scenes import generate

    embedder = await on_fresh_thread(partial(load_embedder, model, threads=threads))
    ds = generate("vtol", seed=seed, n_nominal=max(n, 200), n_anomaly=n)
    samples = (ds.anomalies + ds.nominal)[:n]
    texts = {"brief": [s.brief for s in samples], "prompt": [s.text for s in samples]}
    cache_x = Clusters(DIM, seed).sample(size, np.random.default_rng([seed, 1]))
    end_to_end = {}
    with tempfile.TemporaryDirectory(prefix="aesop-bench-") as tmp:
        for microbatch in (True, False):  # the second service reopens the first one's cache
            service = await open_service(embedder, Path(tmp), microbatch=microbatch)
            try:
                if "latency" not in service.names():
                    await fill(service, "latency", cache_x)
                    await service.calibrate("latency", "loo-quantile")
                for form in ("brief", "prompt") if microbatch else ("brief",):
                    batch = texts[form]
                    for text in batch[:10]:  # warm-up
                        await service.scorer.score_texts("latency", [text])
                    end_to_end[form, microbatch] = stats(
                        [await score_one(service, batch[i]) for i in range(len(batch))])
            finally:
                await service.close()
    entry_cache = cache_of(cache_x)
    def timings() -> tuple[dict[str, dict[str, float]], dict[str, float]]:
        vectors = embedder.embed(texts["brief"])
        def embed_one(form: str, i: int) -> object:
            return embedder.embed([texts[form][i]])

        embed = {form: stats(time_each(partial(embed_one, form), len(samples)))
                 for form in texts}
        search = stats(time_each(lambda i: entry_cache.score(vectors[i:i + 1], K),
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
        "median_verdict": pass_or_fail(e2e["median_ms"], LATENCY_TARGET_MS["median"]),
        "p99_verdict": pass_or_fail(e2e["p99_ms"], LATENCY_TARGET_MS["p99"]),
    }


def render_latency(r: Mapping[str, Any]) -> str:
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
             "target": f"{pass_or_fail(x['end_to_end']['median_ms'], b['median'])} / "
                       f"{pass_or_fail(x['end_to_end']['p99_ms'], b['p99'])}"}
            for x in r["backends"]]
    return out + "\n" + table(
        f"[latency] by backend and threads per inference (target median <= {b['median']:g} "
        f"ms / p99 <= {b['p99']:g} ms)", rows)
