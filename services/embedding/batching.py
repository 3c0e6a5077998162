"""The compute thread and its lanes, and the micro-batcher of concurrent requests.

``ComputeThread`` is one long-lived thread that runs what is submitted to it,
the most urgent lane first (the bus's verdicts before REST scoring and admin
work), first come first served within a lane; a call cancelled before it starts
never runs.

``MicroBatcher`` coalesces concurrent requests into one call of a batch function,
run on ``executor`` (asyncio's default if none); at most one batch per batcher is
in flight, and requests that arrive meanwhile form the next batch. A request that
finds the batcher idle waits ``window_s`` for company first (0: it goes at once).
A request whose caller has gone (its future cancelled) is left out of the batch.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, Future
from typing import Any, Generic, TypeVar

T = TypeVar("T")
R = TypeVar("R")


URGENT, NORMAL = 0, 1  # ComputeThread lanes: the bus's verdicts; everything else


class ComputeThread:
    """One thread for model inference and index searches (see ``service.py`` for why
    one); ``lane(URGENT)`` and ``lane(NORMAL)`` are executors that submit to it."""

    def __init__(self, name: str = "aesop-compute") -> None:
        self._queue: list[tuple[int, int, Future[Any], Callable[[], Any]]] = []
        self._ready = threading.Condition()
        self._order = itertools.count()
        self._closed = False
        self._thread = threading.Thread(target=self._serve, name=name, daemon=True)
        self._thread.start()

    def lane(self, priority: int) -> Executor:
        return _Lane(self, priority)

    def submit(self, priority: int, fn: Callable[[], R]) -> Future[R]:
        future: Future[R] = Future()
        with self._ready:
            if self._closed:
                raise RuntimeError("the compute thread is shut down")
            heapq.heappush(self._queue, (priority, next(self._order), future, fn))
            self._ready.notify()
        return future

    def _serve(self) -> None:
        while True:
            with self._ready:
                while not self._queue and not self._closed:
                    self._ready.wait()
                if not self._queue:
                    return
                _, _, future, fn = heapq.heappop(self._queue)
            if not future.set_running_or_notify_cancel():
                continue  # cancelled while it waited: its caller has gone
            try:
                future.set_result(fn())
            except BaseException as exc:  # handed to the caller, never lost here
                future.set_exception(exc)

    def shutdown(self, wait: bool = True) -> None:
        """Run what is queued, then stop."""
        with self._ready:
            self._closed = True
            self._ready.notify()
        if wait:
            self._thread.join()


class _Lane(Executor):
    def __init__(self, thread: ComputeThread, priority: int) -> None:
        self._thread, self._priority = thread, priority

    def submit(self, fn: Callable[..., R], /, *args: Any, **kwargs: Any) -> Future[R]:
        return self._thread.submit(self._priority, lambda: fn(*args, **kwargs))


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
            if not batch:
                continue
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
            if chunk[1].done():  # cancelled: nobody waits for it
                continue
            taken.append(chunk)
            total += len(chunk[0])
        return taken

    async def close(self) -> None:
        if self._task is not None:
            await asyncio.gather(self._task, return_exceptions=True)
