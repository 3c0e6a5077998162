"""Issue 14: the reasoner's Zenoh worker applies the limits HTTP applies, over two real
Zenoh peers. A request over them is dropped (no decision), counted and logged."""

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
from tests.zenoh_peers import DEADLINE_S, routed

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
        listener: Bus, connector: Bus, caplog: pytest.LogCaptureFixture) -> None:
    backend, registry = Recording(), CollectorRegistry()
    worker = ReasonerWorker(Decider([backend], DeciderConfig()), listener, settings=LIMITS,
                            metrics=ReasonerMetrics(registry))
    task = asyncio.create_task(worker.run())
    decisions = connector.subscribe(topics.reasoner_decision(topics.ANY_ROBOT),
                                    ReasonerDecision)
    await routed(connector, listener)
    await routed(listener, connector)
    bad = [request("long", text="x" * 101), request("late", deadline_s=10.5),
           request("crowded", options=(*OPTIONS, Option(index=3, label="land")))]
    with caplog.at_level(logging.WARNING, logger="services.reasoner.worker"):
        # not a request at all (an infinite deadline is not JSON a request may carry)
        connector.session.put(topics.reasoner_request("drone7"),
                              request("inf").encode().replace(b'"deadline_s":5.0',
                                                              b'"deadline_s":Infinity'))
        for message in [*bad, request("good")]:
            connector.publish(topics.reasoner_request("drone7"), message)
        got = await asyncio.wait_for(anext(decisions), DEADLINE_S)
        await worker.stop()  # every handler has finished
    await asyncio.wait_for(task, DEADLINE_S)
    # one publisher's messages arrive in order: once this one is here, everything the
    # worker published is
    end = ReasonerDecision(robot="drone7", request_id="end", choice=0, source="llm",
                           latency_ms=0.0)
    listener.publish(topics.reasoner_decision("drone7"), end)
    answered = [got.message.request_id]
    while answered[-1] != "end":
        answered.append((await asyncio.wait_for(anext(decisions), DEADLINE_S)).message.request_id)
    assert answered == ["good", "end"] and got.message.source == "llm"
    assert backend.calls == 1
    for field in ("observation.text", "deadline_s", "options", "message"):
        assert registry.get_sample_value("aesop_reasoner_bus_rejected_total",
                                         {"field": field}) == 1
        assert field == "message" or any(
            field in r.getMessage() and "dropped 1 reasoner request(s)" in r.getMessage()
            for r in caplog.records)
