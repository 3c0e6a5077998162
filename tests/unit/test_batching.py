"""The micro-batcher: concurrent submissions share calls and get their own results back."""

from __future__ import annotations

import asyncio

import pytest

from services.embedding.batching import MicroBatcher


async def test_concurrent_submissions_share_one_call_and_keep_order() -> None:
    calls: list[list[int]] = []

    def double(items: list[int]) -> list[int]:
        calls.append(items)
        return [2 * i for i in items]

    batcher = MicroBatcher(double, max_items=100, window_s=0.05)
    results = await asyncio.gather(*(batcher.submit([i, i + 100]) for i in range(10)))
    assert results == [[2 * i, 2 * (i + 100)] for i in range(10)]
    assert sum(len(c) for c in calls) == 20 and len(calls) < 10
    await batcher.close()


async def test_batches_respect_max_items() -> None:
    sizes: list[int] = []
    batcher = MicroBatcher(lambda xs: xs, max_items=4, window_s=0.01, on_batch=sizes.append)
    out = await asyncio.gather(*(batcher.submit([i]) for i in range(10)))
    assert out == [[i] for i in range(10)] and max(sizes) <= 4 and sum(sizes) == 10


async def test_an_error_reaches_every_waiter_of_its_batch_and_the_next_batch_works() -> None:
    def fail_on_negative(items: list[int]) -> list[int]:
        if any(i < 0 for i in items):
            raise ValueError("negative")
        return items

    batcher = MicroBatcher(fail_on_negative, window_s=0.05)
    results = await asyncio.gather(batcher.submit([1]), batcher.submit([-1]),
                                   return_exceptions=True)
    assert all(isinstance(r, ValueError) for r in results)
    assert await batcher.submit([3]) == [3]
    with pytest.raises(ValueError):
        await batcher.submit([-2])
