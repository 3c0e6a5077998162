"""What the parts of ``aesop bench detector`` share: sizes, targets, the run's model and
data (:class:`Bench`), timing and synthetic-vector helpers.
"""

from __future__ import annotations

import json
import logging
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from services.embedding.models.base import Embedder, Wrapping
from services.embedding.settings import DEFAULT_MODEL

if TYPE_CHECKING:
    from services.embedding.service import CacheService
    from tools.scenes import Dataset



log = logging.getLogger(__name__)


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
    quick: bool = False  # the drift part's smaller sets


FULL = Sizes(
    domains={"warehouse": (None, None), "vehicle": (None, None), "vtol": (2000, 500)},
    repeats=3, threshold_seeds=5, latency_n=300, search_sizes=(100_000, 1_000_000),
    exact_queries=50, build_texts=1000, rest_cache=2000, rest_requests=1000,
)


QUICK = Sizes(
    domains={name: (100, 40) for name in QUALITY_DOMAINS},
    # enough nominal scenes with detections that the combined score can flag at alpha 0.95
    # (at least 60: 100 left 58 in the vehicle domain and the part failed)
    kind_domains={name: (150, 40) for name in QUALITY_DOMAINS},
    repeats=1, threshold_seeds=2, latency_n=50, search_sizes=(10_000, 50_000),
    exact_queries=50, build_texts=300, rest_cache=100, rest_requests=200, loo_repeats=1,
    restart_cache=20_000, quick=True,
)


class Bench:
    """What the parts share: the sizes, the seed, one loaded model, and each
    domain's samples and embeddings (every text is embedded once per run)."""

    def __init__(self, sizes: Sizes, seed: int) -> None:
        self.sizes = sizes
        self.seed = seed
        self._datasets: dict[tuple[str, bool], Dataset] = {}
        self._vectors: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]] = {}

    @cached_property
    def embedder(self) -> Embedder:
        from services.embedding.models.loading import load_embedder
        from services.embedding.settings import DEFAULT_MODEL
        from tools.counted import Counted

        log.info("loading %s", DEFAULT_MODEL)
        embedder = Counted(load_embedder(DEFAULT_MODEL))  # texts embedded: the live line's
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
        return self.embedder.embed(texts, batch_size=64)

    def vectors(self, name: str, form: str = "prompt") -> tuple[np.ndarray, np.ndarray]:
        """(nominal, anomaly) unit embeddings of ``dataset(name)``, (n, DIM) float32 each,
        of the full prompts (``form="prompt"``, as in the paper) or the brief form."""
        if (name, form) not in self._vectors:
            ds = self.dataset(name)
            texts = [s.text if form == "prompt" else s.brief for s in ds.nominal + ds.anomalies]
            log.info("embedding %d %s texts (%s)", len(texts), name, form)
            v = self.embedder.embed(texts, batch_size=64)
            self._vectors[name, form] = (v[: len(ds.nominal)], v[len(ds.nominal):])
        return self._vectors[name, form]


def stats(seconds: Sequence[float]) -> dict[str, float]:
    """Median, p99 and mean of durations, in milliseconds."""
    ms = np.asarray(seconds, dtype=np.float64) * 1e3
    return {"n": int(ms.size), "median_ms": float(np.median(ms)),
            "p99_ms": float(np.percentile(ms, 99)), "mean_ms": float(ms.mean())}


def time_each(fn: Callable[[int], object], n: int) -> list[float]:
    """Durations (s) of ``fn(0) .. fn(n-1)``."""
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        out.append(time.perf_counter() - t0)
    return out


def time_calls(fn: Callable[[], Any], repeats: int) -> tuple[list[float], Any]:
    """Durations (s) of ``repeats`` calls of ``fn`` and the last call's result."""
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return times, result


def pass_or_fail(value: float, target: float) -> str:
    return "pass" if value <= target else "FAIL"


class Clusters:
    """Unit vectors around ``CLUSTERS`` random centres.

    Each point is centre + noise with a decaying spectrum (variance of dimension
    i proportional to 1/i, effective dimension ~25, like sentence embeddings),
    noise norm ~``spread``; then normalised. Same-cluster cosine is ~0.7.
    Queries drawn with another generator come from the same distribution but
    are not members.
    """

    def __init__(self, dim: int, seed: int, *, spread: float = 0.7) -> None:
        rng = np.random.default_rng([seed, 7])
        self.centres = unit_rows(rng.standard_normal((CLUSTERS, dim), dtype=np.float32))
        scale = 1.0 / np.sqrt(np.arange(1, dim + 1, dtype=np.float64))
        self.scale = (scale * spread / np.linalg.norm(scale)).astype(np.float32)

    def sample(self, n: int, rng: np.random.Generator, *, chunk: int = 100_000) -> np.ndarray:
        out = np.empty((n, self.centres.shape[1]), dtype=np.float32)
        for start in range(0, n, chunk):
            m = min(chunk, n - start)
            noise = rng.standard_normal((m, out.shape[1]), dtype=np.float32) * self.scale
            out[start:start + m] = unit_rows(self.centres[rng.integers(CLUSTERS, size=m)] + noise)
        return out


def unit_rows(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def jsonable(value: Any) -> Any:
    """numpy scalars -> Python, non-finite floats -> None, tuples -> lists, keys -> str."""
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [jsonable(v) for v in value]
    if isinstance(value, np.integer | np.bool_):
        return value.item()
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    return value


def labelled(samples: Sequence[Any]) -> list[Any]:
    from services.embedding.detector.cache import Labelled

    return [Labelled(s.brief, s.label == "anomaly", tuple(s.detections)) for s in samples]


class Memo(Wrapping):
    """An embedder that embeds each text once (the kinds part evaluates one domain's
    texts seven times)."""

    def __init__(self, inner: Embedder) -> None:
        super().__init__(inner)
        self.seen: dict[str, np.ndarray] = {}

    def embed(self, texts: Sequence[str], **_: Any) -> np.ndarray:
        new = [t for t in dict.fromkeys(texts) if t not in self.seen]
        if new:
            self.seen.update(zip(new, self.inner.embed(new, batch_size=64), strict=True))
        return np.stack([self.seen[t] for t in texts]) if texts else \
            np.zeros((0, self.dim), dtype=np.float32)


async def open_service(embedder: Embedder, data_dir: Path, *, microbatch: bool = True,
                   fsync: bool = False) -> CacheService:
    """A started ``CacheService`` on ``data_dir`` that shares the already-loaded model."""
    from services.embedding.models.loading import EmbedderPool
    from services.embedding.service import CacheService
    from services.embedding.settings import EmbeddingSettings, EmbeddingTuning

    settings = EmbeddingSettings(data_dir=data_dir, tuning=EmbeddingTuning(microbatch=microbatch),
                                 fsync=fsync, zenoh_worker=False)
    service = CacheService(settings, embedders=EmbedderPool(loader=lambda _: embedder))
    await service.start()
    return service


async def fill(service: CacheService, name: str, vectors: np.ndarray) -> None:
    """Create cache ``name`` pinned to the default model and add ``vectors`` as experiences."""
    from services.embedding.schemas import Item
    from services.embedding.settings import DEFAULT_MODEL

    await service.create(name, model=DEFAULT_MODEL, k=K)
    for start in range(0, len(vectors), 5000):
        chunk = vectors[start:start + 5000]
        await service.add(name, [Item(vector=v) for v in chunk.tolist()])


async def score_one(service: CacheService, text: str) -> float:
    t0 = time.perf_counter()
    batch = await service.scorer.score_texts("latency", [text])
    assert batch.threshold is not None
    _ = batch.results[0].score > batch.threshold  # the verdict
    return time.perf_counter() - t0


def cache_of(vectors: np.ndarray) -> Any:
    from services.embedding.detector.evaluation import EvalConfig, build_cache

    return build_cache(vectors, EvalConfig(k=K), None)


def run_probe(args: list[str]) -> dict[str, Any]:
    """Run ``python -m tools.bench.detector <args>`` and read its one JSON line."""
    cmd = [sys.executable, "-m", "tools.bench.detector", *args]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900,
                          check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"{args[0]} exited {proc.returncode}: {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])
