"""``aesop bench reasoner --json``: real fake-LLM processes, one JSON object on stdout."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys

import pytest

from shared import topics
from shared.bus import Bus, Received
from shared.messages import ReasonerDecision, ReasonerRequest
from shared.settings import BusSettings
from tools.bench import reasoner as bench

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(300)]

REQUIRED = {"requests", "deadline_s", "deadline_misses", "overshoot_ms", "fallback_rate",
            "overhead_ms", "hedging"}


def test_bench_reasoner_json_is_one_object_with_the_required_keys() -> None:
    r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "reasoner",
                        "--requests", "60", "--scale", "0.05", "--json"],
                       capture_output=True, text=True, timeout=280, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(r.stdout)  # the whole of stdout: exactly one JSON object
    assert isinstance(result, dict)
    assert set(result) >= REQUIRED
    assert result["requests"] == 60
    assert isinstance(result["deadline_misses"], int) and result["deadline_misses"] >= 0
    assert 0.0 <= result["fallback_rate"] <= 1.0
    assert {"p50", "p99", "max"} <= set(result["overshoot_ms"])
    assert {"p50", "p99"} <= set(result["overhead_ms"])
    hedging = result["hedging"]
    assert {"hedge_after_s", "p95_latency_ratio", "fallback_rate_ratio"} <= set(hedging)
    assert hedging["hedged_run"]["requests"] == 60


async def test_a_request_never_answered_is_a_miss_and_the_bench_goes_on(endpoint: str) -> None:
    """CI: under load the keeper's fallback woke 24 ms late, was dropped (nothing leaves
    past its deadline: the robot takes its own fallback at K), and the bench's robot, which
    waited for every decision, failed the whole run after K + 30 s. A request unanswered
    UNANSWERED_AFTER_S past its K is now None (a deadline miss) and the next one goes."""
    with Bus.open(BusSettings(zenoh_listen=[endpoint]), "bench") as robot, \
            Bus.open(BusSettings(zenoh_connect=[endpoint]), "reasoner") as reasoner:

        def answer(got: Received[ReasonerRequest]) -> None:
            request = got.message
            if request.request_id != "bench-2":  # its decision was dropped, late
                reasoner.publish(topics.reasoner_decision(request.robot), ReasonerDecision(
                    robot=request.robot, request_id=request.request_id, choice=1,
                    source="timeout", latency_ms=1.0))

        reasoner.each(topics.reasoner_request(topics.ANY_ROBOT), ReasonerRequest, answer)
        heard = await asyncio.wait_for(bench._closed_loop(robot, 6, 0.2, 2), 30.0)
    assert [h is None for h in heard] == [False, False, True, False, False, False]
    assert all(h[0].request_id == f"bench-{i}" for i, h in enumerate(heard) if h is not None)
    samples = [bench.Sample(*h) for h in heard if h is not None]
    summary = bench._phase_summary(samples, 0.2, requests=6)
    assert (summary["requests"], summary["unanswered"], summary["deadline_misses"]) == (6, 1, 1)
