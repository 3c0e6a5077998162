"""``aesop demo --llm local`` (issue 27), on the whole stack as processes.

* K from the model: the reasoner's calibration job times the served model while the robot
  flies the nominal scenario, and the control loop is started again on the scene with that
  K; the flights then use it. Timed here on the fake LLM answering in 0.3 s (so the
  60 answers take a minute, not the real model's few).
* The trained model in the loop: SmolLM2-135M on llama.cpp's server decides scenario 2a
  within the scene's K. Whatever it answers (a 135M model may be wrong, or late), the
  flight must end safely where its decision sent it, and the row must say what the model
  wrote, how long it took and whether it was the expected decision.
"""

from __future__ import annotations

import asyncio
import json
import secrets
from pathlib import Path

import pytest

from services.control.client import ControlClient
from services.control.core.scenario import load_scenario
from tests.demo_stack import running_stack
from tools.demo.flights import fly_scenarios, fly_with_k
from tools.local_llm import bundled_model
from tools.stack.up import hardware_scenario

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(900)]

TOKEN = secrets.token_urlsafe(24)
SCENE = load_scenario(hardware_scenario())
RED_BOX = "2a-quadrotor-on-red-box"


async def flown_scene(url: str) -> str:
    async with ControlClient(url, token=TOKEN) as control:
        return (await control.state()).scenario


def test_k_is_measured_on_the_served_model_and_the_loop_flies_with_it(tmp_path: Path) -> None:
    fast = {"AESOP_FAKE_LLM_FIXED_S": "0.3"}
    with running_stack(tmp_path, TOKEN, environ=fast) as up:
        choice, scenario = fly_with_k(up.stack, up.plan, up.options, up.environ, SCENE,
                                      tmp_path / "out")
        assert choice.calibrated and 0.3 <= choice.k_s <= 1.5, choice
        assert choice.report["n"] == 60 and choice.report["quantiles_s"]["p50"] >= 0.3
        assert scenario.consensus_s == choice.k_s != SCENE.consensus_s
        url = up.plan.url("control")
        assert url is not None
        assert asyncio.run(flown_scene(url)) == scenario.name  # the restarted loop's scene
        result, _ = fly_scenarios(up.plan, [RED_BOX], scenario=scenario)
        [row] = result["scenarios"]
        assert row["outcome"] == "ok", json.dumps(row, default=str)
        assert row["decision_latency_ms"] <= choice.k_s * 1000.0 + 50.0  # by the new K


def test_the_trained_model_decides_and_the_flight_ends_where_its_decision_sent_it(
        tmp_path: Path) -> None:
    with running_stack(tmp_path, TOKEN, local_model=bundled_model()) as up:
        result, _ = fly_scenarios(up.plan, [RED_BOX])
    [row] = result["scenarios"]
    said = json.dumps(row, default=str)  # whole: a failure on a loaded machine says why
    assert row["outcome"] == "ok", said  # safe, where its decision sent it
    assert row["constraint_violations"] == 0 and row["anomaly_at_s"] is not None
    assert row["decision_source"] in {"llm", "parse_error", "timeout", "control fallback at K"}
    assert row["decision_right"] == (row["decision"] == "alternative landing site")
    assert row["decision_latency_ms"] <= SCENE.consensus_s * 1000.0 + 50.0
    if row["decision_source"] in {"llm", "parse_error"}:
        assert row["answer"], row  # what the model wrote, as it wrote it
