"""Micro-batching: concurrent requests coalesced into one call of a batch function.

The batch function runs in a worker thread of ``executor`` (asyncio's default
if none); at most one batch per batcher is in flight, and requests that arrive
meanwhile form the next batch. A request that finds the batcher idle waits
``window_s`` for company first (0: it goes at once).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from typing import Generic, TypeVar

T = TypeVar("T")
R = TypeVar("R")


class MicroBatcher(Generic[T, R]):
    def __init__(
        self,
        fn: Callable[[list[T]], Sequence[R]],
        *,
        max_items: int = 64,
        window_s: float = 0.002,
        on_batch: Callable[[int], None] | None = None,
        executor: Executor | None = None,
    ) -> None:
        self._fn = fn
        self._executor = executor
        self._max_items = max_items
        self._window_s = window_s
        self._on_batch = on_batch
        self._pending: list[tuple[list[T], asyncio.Future[list[R]]]] = []
        self._task: asyncio.Task[None] | None = None

    async def submit(self, items: Sequence[T]) -> list[R]:
        future: asyncio.Future[list[R]] = asyncio.get_running_loop().create_future()
        self._pending.append((list(items), future))
        if self._task is None or self._task.done():
            self._task = asyncio.create_task(self._run())
        return await future

    async def _run(self) -> None:
        while self._pending:
            if self._window_s > 0 and self._count() < self._max_items:
                await asyncio.sleep(self._window_s)
            batch = self._take()
            items = [item for chunk, _ in batch for item in chunk]
            if self._on_batch is not None:
                self._on_batch(len(items))
            try:
                results = await asyncio.get_running_loop().run_in_executor(
                    self._executor, self._fn, items)
            except Exception as exc:  # every waiter of this batch gets the error
                for _, fut in batch:
                    if not fut.done():
                        fut.set_exception(exc)
                continue
            pos = 0
            for chunk, fut in batch:
                if not fut.done():
                    fut.set_result(list(results[pos : pos + len(chunk)]))
                pos += len(chunk)

    def _count(self) -> int:
        return sum(len(chunk) for chunk, _ in self._pending)

    def _take(self) -> list[tuple[list[T], asyncio.Future[list[R]]]]:
        taken: list[tuple[list[T], asyncio.Future[list[R]]]] = []
        total = 0
        while self._pending and (not taken or total + len(self._pending[0][0]) <= self._max_items):
            chunk = self._pending.pop(0)
            taken.append(chunk)
            total += len(chunk[0])
        return taken

    async def close(self) -> None:
        if self._task is not None:
            await asyncio.gather(self._task, return_exceptions=True)
