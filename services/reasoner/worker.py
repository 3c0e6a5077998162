"""Zenoh worker: reasoner requests in, decisions out, each by its deadline.

Subscribes ``aesop/*/reasoner/request`` and answers every ``ReasonerRequest``
with a ``ReasonerDecision`` on ``aesop/{robot}/reasoner/decision``. The
deadline counts from the moment the request reached this process.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from shared import topics
from shared.bus import Bus, Received
from shared.messages import ReasonerRequest
from shared.pump import MessagePump

from .deciding import Decider
from .settings import ReasonerSettings


class ReasonerWorker:
    def __init__(self, decider: Decider, bus: Bus, *, metrics: Any = None,
                 owns_bus: bool = False, max_in_flight: int = 64) -> None:
        self.decider = decider
        self.bus = bus
        self.metrics = metrics
        self.owns_bus = owns_bus
        self._pump = MessagePump(bus, topics.reasoner_request(topics.ANY_ROBOT),
                                 ReasonerRequest, self._answer, max_in_flight=max_in_flight)

    @classmethod
    def factory(cls, settings: ReasonerSettings) -> Callable[[Decider, Any], ReasonerWorker]:
        def make(decider: Decider, metrics: Any) -> ReasonerWorker:
            return cls(decider, Bus.open(settings, "reasoner"), metrics=metrics, owns_bus=True)

        return make

    async def run(self) -> None:
        await self._pump.run()

    async def _answer(self, received: Received[ReasonerRequest]) -> None:
        robot = topics.robot_of(received.key)
        decision = await self.decider.decide(received.message, received_at=received.received_at)
        decision = decision.model_copy(update={"robot": robot})
        self.bus.publish(topics.reasoner_decision(robot), decision)
        if self.metrics is not None:
            self.metrics.observe(decision)

    async def stop(self) -> None:
        await self._pump.stop()
        if self.owns_bus:
            self.bus.close()
