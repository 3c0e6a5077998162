"""Handle every message of a subscription concurrently, with a bound, and stop cleanly.

The loop every service's Zenoh worker runs: subscribe ``key_expr``, start
``handler(received)`` as a task per message (at most ``max_in_flight`` at once;
the subscription's drop-oldest queue absorbs bursts), log a handler that
fails, count a message that does not decode (``on_undecodable``, e.g. into the
service's metrics; the bus logs it, rate-limited), and on ``stop()`` close the
subscription and wait for the handlers.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Coroutine
from typing import Any, Generic

from .bus import Bus, M, Received, Subscription

log = logging.getLogger(__name__)


class MessagePump(Generic[M]):
    def __init__(self, bus: Bus, key_expr: str, model: type[M],
                 handler: Callable[[Received[M]], Coroutine[Any, Any, None]], *,
                 max_in_flight: int = 64, maxsize: int = 256,
                 on_undecodable: Callable[[], None] | None = None) -> None:
        self.bus, self.key_expr, self.model, self.handler = bus, key_expr, model, handler
        self.maxsize, self.on_undecodable = maxsize, on_undecodable
        self._slots = asyncio.Semaphore(max_in_flight)
        self._tasks: set[asyncio.Task[None]] = set()
        self._subscription: Subscription[M] | None = None

    async def run(self) -> None:
        self._subscription = self.bus.subscribe(self.key_expr, self.model, maxsize=self.maxsize,
                                                on_error=self.on_undecodable)
        async for received in self._subscription:
            await self._slots.acquire()
            task = asyncio.create_task(self.handler(received))
            self._tasks.add(task)
            task.add_done_callback(self._done)

    def _done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        self._slots.release()
        if not task.cancelled() and task.exception() is not None:
            log.error("handling a message on %s failed", self.key_expr,
                      exc_info=task.exception())

    async def stop(self) -> None:
        if self._subscription is not None:
            self._subscription.close()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
