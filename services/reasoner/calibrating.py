"""Measure a backend's answer latency to choose K (hardware appendix, "Choosing K").

The paper queried GPT-3.5 500 times with its prompt and set K at the 95th
percentile. This runs N queries one after another (warm-up queries first,
reported apart as cold starts) and summarises them with ``latency.summarize``.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass

from .backends import BackendError, ChatBackend
from .latency import LatencyReport, summarize


@dataclass(frozen=True)
class CalibrationPlan:
    n: int
    warmup: int = 3
    quantile: float = 0.95
    confidence: float = 0.95
    timeout_s: float = 30.0  # a query slower than this counts as failed


async def measure(backend: ChatBackend, messages: list[dict[str, str]], plan: CalibrationPlan,
                  progress: Callable[[int, int], None] | None = None) -> LatencyReport:
    """Time ``warmup + n`` queries; failures and timeouts are counted, not timed."""
    total = plan.warmup + plan.n
    cold: list[float] = []
    warm: list[float] = []
    failed = 0
    for i in range(total):
        start = time.perf_counter()
        try:
            await asyncio.wait_for(backend.complete(messages), plan.timeout_s)
        except (BackendError, TimeoutError):
            failed += i >= plan.warmup
        else:
            (cold if i < plan.warmup else warm).append(time.perf_counter() - start)
        if progress is not None:
            progress(i + 1, total)
    return summarize(warm, quantile=plan.quantile, confidence=plan.confidence, cold=cold,
                     failed=failed)
