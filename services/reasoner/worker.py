"""Zenoh worker: reasoner requests in, decisions out, each by its deadline.

Subscribes ``aesop/*/reasoner/request`` and answers every ``ReasonerRequest``
with a ``ReasonerDecision`` on ``aesop/{robot}/reasoner/decision``. The
deadline counts from the moment the request reached this process.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

from shared import topics
from shared.bus import Bus
from shared.messages import ReasonerRequest

from .deciding import Decider
from .settings import ReasonerSettings

log = logging.getLogger(__name__)


class ReasonerWorker:
    def __init__(self, decider: Decider, bus: Bus, *, metrics: Any = None,
                 owns_bus: bool = False, max_in_flight: int = 64) -> None:
        self.decider = decider
        self.bus = bus
        self.metrics = metrics
        self.owns_bus = owns_bus
        self._slots = asyncio.Semaphore(max_in_flight)
        self._tasks: set[asyncio.Task[None]] = set()
        self._subscription: Any = None

    @classmethod
    def factory(cls, settings: ReasonerSettings) -> Callable[[Decider, Any], ReasonerWorker]:
        def make(decider: Decider, metrics: Any) -> ReasonerWorker:
            return cls(decider, Bus.open(settings, "reasoner"), metrics=metrics, owns_bus=True)

        return make

    async def run(self) -> None:
        self._subscription = self.bus.subscribe(
            topics.reasoner_request(topics.ANY_ROBOT), ReasonerRequest, maxsize=256)
        async for received in self._subscription:
            await self._slots.acquire()
            task = asyncio.create_task(
                self._answer(received.message, received.key, received.received_at))
            self._tasks.add(task)
            task.add_done_callback(self._done)

    def _done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        self._slots.release()
        if not task.cancelled() and task.exception() is not None:
            log.error("answering a reasoner request failed", exc_info=task.exception())

    async def _answer(self, request: ReasonerRequest, key: str, received_at: float) -> None:
        robot = topics.robot_of(key)
        decision = await self.decider.decide(request, received_at=received_at)
        decision = decision.model_copy(update={"robot": robot})
        self.bus.publish(topics.reasoner_decision(robot), decision)
        if self.metrics is not None:
            self.metrics.observe(decision)

    async def stop(self) -> None:
        if self._subscription is not None:
            self._subscription.close()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        if self.owns_bus:
            self.bus.close()
