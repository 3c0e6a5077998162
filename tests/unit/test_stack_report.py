"""Pure pieces of `aesop up` and `aesop demo`: the stack plan, the observation script,
where a flight ended, the judge and the summary table."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.control.scenario import load_scenario
from services.stack.report import (
    GOAL,
    SCENARIOS,
    ended_in,
    judge,
    observation_text,
    summary_table,
)
from services.stack.up import Ports, StackOptions, hardware_scenario, plan_stack

SCENE = load_scenario(hardware_scenario())
BY_NAME = {s.name: s for s in SCENARIOS}


def rest_at(*pos: float) -> np.ndarray:
    x = np.zeros(12)
    x[:3] = pos
    return x


def test_the_keyboard_is_in_view_only_for_its_window() -> None:
    keyboard = BY_NAME["3-keyboard-on-ground"]
    assert "a keyboard on the ground" not in keyboard.detections(0.9)
    assert "a keyboard on the ground" in keyboard.detections(1.0)
    assert "a keyboard on the ground" not in keyboard.detections(2.6)


def test_a_quadrotor_on_the_red_box_stays_in_view_and_the_nominal_scene_never_changes() -> None:
    red = BY_NAME["2a-quadrotor-on-red-box"]
    assert "a quadrotor on the red box" in red.detections(11.0)
    nominal = BY_NAME["1-nominal"]
    assert nominal.detections(0.0) == nominal.detections(11.0)
    assert all(len(s.detections(t)) <= 4 for s in SCENARIOS for t in (0.0, 1.5, 5.0))


def test_observation_text_is_one_detection_per_line_in_cache_order() -> None:
    text = observation_text(["a drill on the ground", "a red box on the ground"])
    assert text == "a red box on the ground\na drill on the ground"


def test_ended_in_names_the_goal_the_regions_or_nothing() -> None:
    assert ended_in(rest_at(*SCENE.goal), SCENE) == GOAL
    moving = rest_at(*SCENE.goal)
    moving[3] = 0.5
    assert ended_in(moving, SCENE) is None
    for region in SCENE.regions:
        assert ended_in(rest_at(*region.center[:3]), SCENE) == region.name
    assert ended_in(rest_at(0.0, 0.0, 1.5), SCENE) is None  # mid-arena, in no region


def test_judge_accepts_the_expected_ending_and_names_each_problem() -> None:
    red = BY_NAME["2a-quadrotor-on-red-box"]
    assert judge(red, ended="blue-box", detector_alarms=5, anomaly_at_s=1.2,
                 decision="alternative landing site", violations=0) == []
    problems = judge(red, ended=None, detector_alarms=0, anomaly_at_s=None,
                     decision=None, violations=3)
    assert len(problems) == 4
    nominal = BY_NAME["1-nominal"]
    assert judge(nominal, ended=GOAL, detector_alarms=0, anomaly_at_s=2.4,
                 decision="continue", violations=0) == []  # a late verdict, fail-safe
    assert judge(nominal, ended=GOAL, detector_alarms=2, anomaly_at_s=1.0,
                 decision="continue", violations=0) == [
        "the detector flagged the nominal scene 2 times"]


def test_summary_table_has_a_row_per_scenario() -> None:
    rows = [{"name": "1-nominal", "anomaly_at_s": None, "decision": None,
             "decision_source": None, "ended_in": GOAL, "constraint_violations": 0,
             "duration_s": 12.0, "stale_verdict_alarms": 0, "outcome": "ok"},
            {"name": "2b-both-boxes-occupied", "anomaly_at_s": 1.21, "decision": "holding zone",
             "decision_source": "llm", "ended_in": "holding-zone", "constraint_violations": 0,
             "duration_s": 12.0, "stale_verdict_alarms": 1, "outcome": "ok"}]
    lines = summary_table(rows).splitlines()
    assert lines[0].startswith("scenario") and "ended in" in lines[0]
    assert len(lines) == 4
    assert "holding zone" in lines[3] and "1.2" in lines[3]


def options(tmp: Path) -> StackOptions:
    return StackOptions(data_dir=tmp, ports=Ports(1, 2, 3, 4, 5, 6), rate_hz=5.0,
                        goal=(1.5, 0.0, 0.1), python="py")


def test_plan_starts_the_fake_llm_without_a_backend_and_generates_the_token(
        tmp_path: Path) -> None:
    plan = plan_stack(options(tmp_path), {"AESOP_ZENOH_LISTEN": "tcp/0.0.0.0:7447"}, "t" * 24)
    names = [s.name for s in plan.services]
    assert names == ["fake-llm", "embedding", "reasoner", "control", "dashboard"]
    assert plan.token_generated and plan.fake_llm
    env = plan.services[2].env
    assert env["AESOP_LLM_BASE_URL"] == "http://127.0.0.1:6/v1"
    assert env["AESOP_ADMIN_TOKEN"] == "t" * 24
    assert env["AESOP_ZENOH_CONNECT"] == "tcp/127.0.0.1:1"
    assert "AESOP_ZENOH_LISTEN" not in env  # every peer listens on its own port
    assert env["AESOP_RATE_HZ"] == "5" and env["AESOP_VERDICT_STALE_S"] == "1"
    assert plan.hub.ready == "tcp" and plan.hub.argv[-1] == "tcp/127.0.0.1:1"
    assert plan.services[1].argv[-2:] == ("--data-dir", str(tmp_path / "embedding"))


def test_plan_uses_a_configured_backend_and_token(tmp_path: Path) -> None:
    environ = {"AESOP_LLM_BASE_URL": "https://api.openai.com/v1",
               "AESOP_ADMIN_TOKEN": "given-token-0123456789"}
    plan = plan_stack(options(tmp_path), environ, "unused")
    assert "fake-llm" not in [s.name for s in plan.services]
    assert not plan.token_generated and plan.token == "given-token-0123456789"
    assert plan.services[1].env["AESOP_LLM_BASE_URL"] == "https://api.openai.com/v1"
