"""Zenoh worker: reasoner requests in, decisions out, each by its deadline.

Subscribes ``aesop/*/reasoner/request`` and answers every ``ReasonerRequest``
with a ``ReasonerDecision`` on ``aesop/{robot}/reasoner/decision``. The
deadline counts from the moment the request reached this process, and the decision is
published by then whatever the event loop's load (``Decider.decide_and_send``: a timer
thread publishes the fallback if the loop is late).

A request over the limits that HTTP applies (:func:`.limits.check_request`: the
observation's length, the number of options, a finite deadline no longer than
``max_deadline_s``) is dropped: no decision is published for it, rather than a fallback
decision. The control loop takes a missing decision as silence and commits to its own
fallback at K, so dropping is safe; answering is not: the controller keeps only the newest
decision on the robot's topic, so an answer to a bad request (from a misconfigured or
hostile publisher) could displace the answer to the robot's real question before it is
read. Every drop is counted in ``aesop_reasoner_bus_rejected_total{field}`` and logged,
at most one line per field per 10 s, which says how many drops it covers.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from shared import topics
from shared.bus import Bus, Received
from shared.messages import ReasonerDecision, ReasonerRequest
from shared.pump import MessagePump

from .deciding import Decider
from .limits import LimitError, check_request
from .settings import ReasonerSettings

log = logging.getLogger(__name__)

LOG_INTERVAL_S = 10.0  # at most one line per field this often about dropped requests


class ReasonerWorker:
    """See the module docstring. ``settings`` gives the limits (None: their defaults);
    ``clock`` times the log lines about dropped requests."""

    def __init__(self, decider: Decider, bus: Bus, *, settings: ReasonerSettings | None = None,
                 metrics: Any = None, owns_bus: bool = False, max_in_flight: int = 64,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.decider = decider
        self.bus = bus
        self.settings = settings or ReasonerSettings.model_construct()
        self.metrics = metrics
        self.owns_bus = owns_bus
        self._clock = clock
        self._logged_at: dict[str, float] = {}
        self._unlogged: Counter[str] = Counter()
        self._pump = MessagePump(bus, topics.reasoner_request(topics.ANY_ROBOT),
                                 ReasonerRequest, self._answer, max_in_flight=max_in_flight,
                                 on_undecodable=self._undecodable)

    @classmethod
    def factory(cls, settings: ReasonerSettings) -> Callable[[Decider, Any], ReasonerWorker]:
        def make(decider: Decider, metrics: Any) -> ReasonerWorker:
            return cls(decider, Bus.open(settings, "reasoner"), settings=settings,
                       metrics=metrics, owns_bus=True)

        return make

    async def run(self) -> None:
        await self._pump.run()

    async def _answer(self, received: Received[ReasonerRequest]) -> None:
        robot = topics.robot_of(received.key)
        request = received.message
        try:
            check_request(self.settings, observation=request.observation,
                          options=request.options, deadline_s=request.deadline_s)
        except LimitError as exc:
            self._dropped(received.key, exc)
            return
        def send(decision: ReasonerDecision) -> None:  # from the loop or the timer thread
            self.bus.publish(topics.reasoner_decision(robot),
                             decision.model_copy(update={"robot": robot}))

        decision = await self.decider.decide_and_send(request, send,
                                                      received_at=received.received_at)
        if self.metrics is not None:
            self.metrics.observe(decision)

    def _undecodable(self) -> None:  # on a Zenoh thread; the bus logs it, rate-limited
        if self.metrics is not None:
            self.metrics.reject("message")

    def _dropped(self, key: str, exc: LimitError) -> None:
        """Count a dropped request; log at most once per field per ``LOG_INTERVAL_S``."""
        if self.metrics is not None:
            self.metrics.reject(exc.field)
        now = self._clock()
        self._unlogged[exc.field] += 1
        last = self._logged_at.get(exc.field)
        if last is not None and now - last < LOG_INTERVAL_S:
            return
        self._logged_at[exc.field] = now
        count = self._unlogged.pop(exc.field)
        log.warning("dropped %d reasoner request(s) over the %s limit, unanswered "
                    "(latest on %s: %s)", count, exc.field, key, exc.problem)

    async def stop(self) -> None:
        await self._pump.stop()
        if self.owns_bus:
            self.bus.close()
