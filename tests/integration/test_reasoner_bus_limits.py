"""Issue 14: the reasoner on the bus applies the limits HTTP applies, over two real Zenoh
peers (the test's and the deadline keeper's). A request over them is dropped (no
decision), counted and logged."""

from __future__ import annotations

import asyncio
import logging

import pytest
from prometheus_client import CollectorRegistry

from services.reasoner.deciding import Decider, DeciderConfig
from services.reasoner.metrics import ReasonerMetrics
from services.reasoner.settings import ReasonerLimits, ReasonerSettings
from services.reasoner.worker import ReasonerWorker
from shared import topics
from shared.bus import Bus
from shared.messages import Observation, Option, ReasonerDecision, ReasonerRequest
from tests.fakes.chat_backends import Recording
from tests.zenoh_peers import DEADLINE_S, async_wait_until, wait_until

pytestmark = pytest.mark.timeout(60)

LIMITS = ReasonerSettings(limits=ReasonerLimits(max_observation_chars=100, max_options=3,
                                                max_deadline_s=10.0))
OPTIONS = (Option(index=0, label="continue"),
           Option(index=1, label="alternative landing site", description="the blue box"),
           Option(index=2, label="holding zone", description="hover and wait"))


def request(request_id: str, *, text: str = "a quadrotor on the red box",
            options: tuple[Option, ...] = OPTIONS, deadline_s: float = 5.0) -> ReasonerRequest:
    return ReasonerRequest(robot="drone7", request_id=request_id, deadline_s=deadline_s,
                           observation=Observation(robot="drone7", seq=1, text=text,
                                                   task="landing on the red box"),
                           options=options)


async def test_requests_over_the_limits_are_dropped(
        listener: Bus, endpoint: str, caplog: pytest.LogCaptureFixture) -> None:
    backend, registry = Recording(), CollectorRegistry()
    settings = LIMITS.model_copy(update={"zenoh_connect": [endpoint]})
    worker = ReasonerWorker(Decider([backend], DeciderConfig()), settings,
                            metrics=ReasonerMetrics(registry))
    task = asyncio.create_task(worker.run())
    decisions = listener.subscribe(topics.reasoner_decision(topics.ANY_ROBOT),
                                   ReasonerDecision)
    await async_wait_until(lambda: worker.listening, "the deadline keeper", DEADLINE_S * 6)
    await asyncio.to_thread(wait_until, lambda: "reasoner" in listener.alive(),
                            "the keeper on the bus")
    bad = [request("long", text="x" * 101), request("late", deadline_s=10.5),
           request("crowded", options=(*OPTIONS, Option(index=3, label="land")))]
    with caplog.at_level(logging.WARNING, logger="services.reasoner.worker"):
        # not a request at all (an infinite deadline is not JSON a request may carry)
        listener.session.put(topics.reasoner_request("drone7"),
                              request("inf").encode().replace(b'"deadline_s":5.0',
                                                              b'"deadline_s":Infinity'))
        for message in [*bad, request("good")]:
            listener.publish(topics.reasoner_request("drone7"), message)
        got = await asyncio.wait_for(anext(decisions), DEADLINE_S)
        await worker.stop()  # every decision has finished, every report is counted
    await asyncio.wait_for(task, DEADLINE_S)
    # the keeper published one decision: the one it says left, the good one's
    assert got.message.request_id == "good" and got.message.source == "llm"
    assert registry.get_sample_value("aesop_reasoner_decisions_total", {"source": "llm"}) == 1
    assert sum(s.value for m in registry.collect() if m.name == "aesop_reasoner_decisions"
               for s in m.samples if s.name.endswith("_total")) == 1
    assert backend.calls == 1
    for field in ("observation.text", "deadline_s", "options", "message"):
        assert registry.get_sample_value("aesop_reasoner_bus_rejected_total",
                                         {"field": field}) == 1
        assert field == "message" or any(
            field in r.getMessage() and "dropped 1 reasoner request(s)" in r.getMessage()
            for r in caplog.records)
