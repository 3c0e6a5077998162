"""Pure pieces of `aesop up` and `aesop demo`: the stack plan, the observation script,
where a flight ended, the judge and the summary table."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from services.control.core.scenario import load_scenario
from tools.demo.flights import add_time_lost, dashboard_text, summary_text
from tools.demo.report import (
    AGES,
    COLUMNS,
    MEASURES,
    SUMMARY,
    ended_in,
    flight_measures,
    judge,
    summary_table,
    write_report,
)
from tools.local_llm import LocalModel
from tools.scenes.hardware import GOAL, SCENARIOS, observation_text
from tools.stack.up import (
    PlanError,
    Ports,
    StackOptions,
    fleet,
    fly_command,
    hardware_scenario,
    plan_stack,
    urls_text,
)

SCENE = load_scenario(hardware_scenario())
BY_NAME = {s.name: s for s in SCENARIOS}


def rest_at(*pos: float) -> np.ndarray:
    x = np.zeros(12)
    x[:3] = pos
    return x


def test_the_keyboard_is_in_view_only_above_it() -> None:
    keyboard = BY_NAME["3-keyboard-on-ground"]
    kx, ky = keyboard.spot
    assert "a keyboard on the ground" not in keyboard.detections((kx - 1.3, ky, 0.4))
    assert "a keyboard on the ground" in keyboard.detections((kx - 1.1, ky, 0.4))
    assert "a keyboard on the ground" in keyboard.detections((kx, ky, 0.4))
    assert "a keyboard on the ground" not in keyboard.detections((kx + 1.3, ky, 0.4))
    assert keyboard.detections(SCENE.start_center) == keyboard.detections((9, 9, 1))


def test_obstructions_come_into_view_near_the_red_box_and_the_nominal_scene_never_changes():
    for name in ("2a-quadrotor-on-red-box", "2b-both-boxes-occupied"):
        demo = BY_NAME[name]
        assert demo.spot == SCENE.goal[:2]  # the scene's red box
        assert "a quadrotor on the red box" not in demo.detections(SCENE.start_center)
        assert "a quadrotor on the red box" in demo.detections(SCENE.approach)
    both = BY_NAME["2b-both-boxes-occupied"].detections(SCENE.approach)
    assert "a quadrotor on the blue box" in both
    nominal = BY_NAME["1-nominal"]
    assert nominal.detections(SCENE.start_center) == nominal.detections(SCENE.approach)
    assert all(len(s.detections(p)) <= 4 for s in SCENARIOS
               for p in (SCENE.start_center, SCENE.approach, (0.5, 0.0, 0.4)))


def test_flight_measures_read_the_appendix_behaviours() -> None:
    """A flight at 0.4 m toward the goal at 0.8 m/s, an anomaly at 2 s, 0.3 then 0.2 m/s
    while waiting, a decision at 3 s, then 0.5 and 0.6 m/s; it lands at 5 s."""
    goal = (2.0, 0.0, 0.1)
    t, states, modes = [], [], []
    x = -2.0
    for k in range(61):
        time = k * 0.1
        v = (0.8 if time < 2.0 else 0.3 if time < 2.5 else 0.2 if time < 3.0 else
             0.5 if time < 4.0 else 0.6 if time < 5.0 else 0.0)
        x = min(x + v * 0.1, goal[0]) if time < 5.0 else goal[0]
        z = 0.4 if time < 5.0 else 0.1
        t.append(time)
        states.append([x, 0.0, z, v, 0, 0] + [0] * 6)
        modes.append("anomaly_pending" if 2.0 <= time < 3.0 else "nominal")
    m = flight_measures(t, states, modes, goal, anomaly_at_s=2.0)
    assert m.approach_altitude_m == pytest.approx(0.4)
    assert m.landed_s == pytest.approx(5.0)
    assert (m.speed_before_m_s, m.speed_waiting_m_s, m.speed_after_m_s) == \
        pytest.approx((0.8, 0.2, 0.6))
    assert m.closest_to_goal_m == pytest.approx(0.0, abs=1e-9)
    quiet = flight_measures(t, states, ["nominal"] * len(t), goal, anomaly_at_s=None)
    assert quiet.speed_waiting_m_s is None and quiet.landed_s == pytest.approx(5.0)


def test_time_lost_is_the_keyboard_flights_landing_against_the_nominal_ones() -> None:
    rows = [{"name": "1-nominal", "landed_s": 12.0}, {"name": "2a-x", "landed_s": None},
            {"name": "3-keyboard-on-ground", "landed_s": 13.25}]
    add_time_lost(rows)
    assert rows[2]["time_lost_s"] == 1.25 and "time_lost_s" not in rows[0]


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
    assert set(lines[1]) == {"-", " "} and len(lines) == 4
    assert "holding zone (llm)" in lines[3] and lines[3].split()[-1] == "0"


def demo_rows() -> list[dict[str, Any]]:
    """The four flights' rows as the demo writes them (one fell back at K and failed)."""
    base = {"expected": GOAL, "decision": "continue", "decision_source": "llm",
            "decision_right": True, "answer": None, "constraint_violations": 0,
            "over_limits": {}, "duration_s": 22.0, "wall_s": 23.4, "anomaly_at_s": 3.85,
            "decision_latency_ms": 3104.2, "reasoner_requests": 1, "stale_verdict_alarms": 0,
            "stale_state_alarms": 0, "state_age_ms": [4.81, 19.2, 35.5],
            "setpoint_age_ms": [15.8, 56.8, 79.7], "approach_altitude_m": 0.4,
            "landed_s": 14.2, "speeds": [0.89, 0.18, 0.71], "closest_to_goal_m": 0.0,
            "time_lost_s": None, "anomalous_verdicts": 12, "ended_in": GOAL, "outcome": "ok",
            "what_happened": "it flew on.", "rationale": None}
    return [{**base, "name": "1-nominal", "decision": None, "decision_source": None,
             "decision_right": None, "decision_latency_ms": None, "anomaly_at_s": None},
            {**base, "name": "2a-quadrotor-on-red-box", "decision": "alternative landing site",
             "ended_in": "blue-box", "expected": "blue-box"},
            {**base, "name": "2b-both-boxes-occupied", "decision": "alternative landing site",
             "decision_source": "control fallback at K", "decision_right": False,
             "ended_in": "blue-box", "expected": "holding-zone", "constraint_violations": 3,
             "outcome": "ended in blue-box, expected holding-zone; decision 'alternative "
             "landing site', expected 'holding zone'; 3 ticks outside the limits",
             "what_happened": "the control loop raised an anomaly at 6.95 s; " * 6},
            {**base, "name": "3-keyboard-on-ground", "time_lost_s": 1.05}]


@pytest.mark.parametrize("fleet", [False, True])
def test_what_the_demo_prints_fits_in_100_columns_and_keeps_every_column(
        fleet: bool, tmp_path: Path) -> None:
    rows = [{**r, "robot": f"robot{i}"} if fleet else r for i, r in enumerate(demo_rows())]
    result = {"ok": False, "scenarios": rows, "wall_s": 88.0}
    text = summary_text("paper-quadrotor-hardware, the fake LLM", result, tmp_path / "r.html")
    assert max(len(line) for line in text.splitlines()) <= 100
    token = tmp_path / ("a-long-folder-name-" * 3) / "data" / "admin-token"
    dashboard = dashboard_text("http://127.0.0.1:8080", token, keep_up=False).splitlines()
    assert dashboard[0].startswith("dashboard: http://127.0.0.1:8080/?token=$(cat ")
    assert max(len(line) for line in dashboard[1:]) <= 100  # all but the address itself
    # every column the one wide table had is in one of the narrow ones (the decision's
    # rightness with a real model in decisions_text; why a flight failed under the tables)
    kept = {key for group in (SUMMARY, MEASURES, AGES) for key, _ in group}
    assert {key for key, _ in COLUMNS} - kept == {
        "decision", "decision_source", "decision_right", "outcome"}
    words = " ".join(text.split())
    for _, title in SUMMARY + MEASURES + AGES:  # titles wrap: each word is in the text
        assert set(title.split()) <= set(words.split()), title
    for cell in ("3104", "0.89 / 0.18 / 0.71", "1.05", "4.81 / 19.20 / 35.50",
                 "15.80 / 56.80 / 79.70", "NO"):
        assert cell in words, cell
    # a cell too wide for what is left wraps within its column (a fleet's robot column)
    assert ("alternative landing site (llm)" in text) != fleet
    # the failure's reasons and story under the tables, wrapped
    assert "2b-both-boxes-occupied: ended in blue-box, expected holding-zone;" in words
    assert "3 ticks outside the limits" in words and "SOME FAILED" in text
    assert words.count("the control loop raised an anomaly at 6.95 s") == 6
    assert ("robot2 2b-both-boxes-occupied:" in words) == fleet


def test_the_report_json_and_html_keep_every_value(tmp_path: Path) -> None:
    rows = demo_rows()
    result = {"ok": False, "scenarios": rows, "scene": "paper-quadrotor-hardware",
              "llm": "the fake LLM", "rate_hz": 20.0, "state_rate_hz": 100.0, "wall_s": 88.0}
    write_report(tmp_path, result, {}, load_scenario(hardware_scenario()))
    assert json.loads((tmp_path / "result.json").read_text())["scenarios"] == rows
    page = (tmp_path / "index.html").read_text()
    for title in ("right", "outcome", "stale alarms", "state age at the loop p50 / p99 / max"):
        assert f"<th>{title}" in page, title


def options(tmp: Path) -> StackOptions:
    return StackOptions(data_dir=tmp, ports=Ports(1, 2, 3, 4, 5, 6, 7), rate_hz=5.0, python="py")


def test_plan_starts_the_fake_llm_without_a_backend_and_generates_the_token(
        tmp_path: Path) -> None:
    plan = plan_stack(options(tmp_path), {"AESOP_ZENOH_LISTEN": "tcp/0.0.0.0:7447"}, "t" * 24)
    names = [s.name for s in plan.services]
    assert names == ["fake-llm", "embedding", "reasoner", "sim", "control", "dashboard"]
    assert plan.token_generated and plan.fake_llm
    env = plan.services[2].env
    assert env["AESOP_REASONER_LLM_BASE_URL"] == "http://127.0.0.1:6/v1"
    assert env["AESOP_ADMIN_TOKEN"] == "t" * 24
    assert env["AESOP_ZENOH_CONNECT"] == "tcp/127.0.0.1:1"
    assert env["AESOP_ZENOH_LISTEN"] == ""  # no endpoint of its own: it joins the hub
    control = plan.services[4].env
    assert control["AESOP_CONTROL_RATE_HZ"] == "5.0" and control["AESOP_CONTROL_PORT"] == "4"
    # the vehicle: the robot's user, the same scene, as fast as the loop flies it
    sim = plan.services[3].env
    assert sim["AESOP_SIM_SCENARIO"] == control["AESOP_CONTROL_SCENARIO"] == str(plan.scenario)
    assert float(sim["AESOP_SIM_TIME_SCALE"]) == pytest.approx(5.0 * 0.05)  # hardware dt
    assert sim["AESOP_SIM_PORT"] == "7" and sim["AESOP_ZENOH_USER"] == "robot-robot0"
    assert control["AESOP_CONTROL_VERDICT_STALE_S"] == "0.5"  # every setting, defaults too
    assert json.loads(control["AESOP_CONTROL_TUNING"])["mpc_max_iter"] is None  # the MPC's own
    assert "AESOP_REASONER_LLM_BASE_URL" not in control  # only its own and the shared ones
    assert plan.hub.ready == "tcp" and plan.hub.argv[-1] == "tcp/127.0.0.1:1"
    assert not any(k.startswith("AESOP_") for k in plan.hub.env)
    assert plan.services[1].env["AESOP_DATA_DIR"] == str(tmp_path / "embedding")
    assert plan.services[1].env["AESOP_EMBEDDING_DETECTOR_CACHE"] == "quadrotor"
    # every service is a client of the hub with a user of its own; the hub checks them
    for spec in plan.services[1:]:
        user = {"sim": "robot-robot0", "control": "control-robot0"}.get(spec.name, spec.name)
        assert spec.env["AESOP_ZENOH_MODE"] == "client", spec.name
        assert spec.env["AESOP_ZENOH_USER"] == user
        assert spec.env["AESOP_ZENOH_PASSWORD"] == plan.passwords[user]
    assert len(set(plan.passwords.values())) == len(plan.passwords)  # one each
    assert set(plan.passwords) == {"embedding", "reasoner", "control-robot0", "dashboard",
                                   "monitor", "robot-robot0"}
    assert plan.hub.argv[plan.hub.argv.index("--users") + 1] == str(plan.zenoh_dir / "users.txt")
    assert plan.hub.argv[plan.hub.argv.index("--robot") + 1] == "robot0"
    assert "AESOP_ZENOH_USER" not in plan.services[0].env  # the fake LLM has no bus


def test_plan_uses_a_configured_backend_and_token(tmp_path: Path) -> None:
    environ = {"AESOP_REASONER_LLM_BASE_URL": "https://api.openai.com/v1",
               "AESOP_ADMIN_TOKEN": "given-token-0123456789"}
    plan = plan_stack(options(tmp_path), environ, "unused")
    assert "fake-llm" not in [s.name for s in plan.services]
    assert not plan.token_generated and plan.token == "given-token-0123456789"
    assert plan.services[1].env["AESOP_REASONER_LLM_BASE_URL"] == "https://api.openai.com/v1"


@pytest.mark.parametrize(("name", "value", "field"), [
    ("AESOP_CONTROL_VERDICT_STALE_S", "-1", "verdict_stale_s"),
    ("AESOP_SIM_START_POSITION", "[0, 1]", "start_position"),
    ("AESOP_SIM_REPORTS__RATE_HZ", "0", "rate_hz"),
    ("AESOP_REASONER_FALLBACK", "panic", "fallback"),
    ("AESOP_EMBEDDING_LIMITS__MAX_ITEMS", "lots", "max_items"),
    ("AESOP_ROBOT", "no spaces", "robot"),
])
def test_a_bad_setting_fails_the_plan_naming_the_field(tmp_path: Path, name: str, value: str,
                                                       field: str) -> None:
    with pytest.raises(ValidationError, match=field):
        plan_stack(options(tmp_path), {name: value}, "t" * 24)


def test_the_plan_keeps_what_the_environment_sets(tmp_path: Path) -> None:
    environ = {"AESOP_CONTROL_VERDICT_STALE_S": "0.8", "AESOP_EMBEDDING_DETECTOR_CACHE": "mine",
               "AESOP_ROBOT": "r5", "PATH": "/usr/bin", "AESOP_CONTROL_PORT": "1"}
    plan = plan_stack(options(tmp_path), environ, "t" * 24)
    control = next(s for s in plan.services if s.name == "control")
    embedding = next(s for s in plan.services if s.name == "embedding")
    assert control.env["AESOP_CONTROL_VERDICT_STALE_S"] == "0.8" and control.env["PATH"]
    assert control.env["AESOP_CONTROL_PORT"] == "4"  # the stack's port wins
    assert embedding.env["AESOP_EMBEDDING_DETECTOR_CACHE"] == "mine"
    assert plan.robot == "r5" and embedding.env["AESOP_ROBOT"] == "r5"


def test_plan_serves_a_local_model_and_asks_it_as_its_server_wants(tmp_path: Path) -> None:
    """``aesop up --llm local``: llama.cpp's server with the model instead of the fake LLM,
    the reasoner pointed at it in JSON mode; a knob the environment sets still wins."""
    model = LocalModel(tmp_path / "smol.gguf", "smol")
    environ = {"AESOP_REASONER_REQUEST__MAX_TOKENS": "123"}
    plan = plan_stack(replace(options(tmp_path), local_model=model), environ, "t" * 24)
    names = [s.name for s in plan.services]
    assert names == ["llm", "embedding", "reasoner", "sim", "control", "dashboard"]
    assert not plan.fake_llm and plan.local_model == model
    server = plan.services[0]
    assert server.ready == "tcp" and server.port == 6
    assert server.argv[server.argv.index("--model") + 1] == str(model.path)
    assert server.argv[server.argv.index("--model_alias") + 1] == "smol"
    assert server.argv[server.argv.index("--port") + 1] == "6"
    assert not any(k.startswith("AESOP_") for k in server.env)
    reasoner = plan.services[2].env
    assert reasoner["AESOP_REASONER_LLM_BASE_URL"] == "http://127.0.0.1:6/v1"
    assert reasoner["AESOP_REASONER_LLM_MODEL"] == "smol"
    assert reasoner["AESOP_REASONER_VARIANT"] == "single"  # what the small model follows best
    request = json.loads(reasoner["AESOP_REASONER_REQUEST"])
    assert request["json_schema"] is True and request["response_format"] == "json_object"
    assert request["max_reasoning_chars"] == 200 and request["max_tokens"] == 123
    # the banner's demo command, with K measured on that model first (not on the fake LLM)
    reasoner_url = plan.url("reasoner")
    assert f"add --measure-k --reasoner-url {reasoner_url}\n" in urls_text(plan, None)
    assert "--measure-k" not in urls_text(plan_stack(options(tmp_path), {}, "t" * 24), None)


def test_a_fleet_plan_gives_each_robot_its_loop_vehicle_and_user_and_replicas_a_store(
        tmp_path: Path) -> None:
    fleet_options = replace(options(tmp_path), robots=3, replicas=2)
    plan = plan_stack(fleet_options, {"AESOP_ROBOT": "drone7"}, "t" * 24)
    names = [s.name for s in plan.services]
    assert names == ["postgres", "fake-llm", "embedding", "embedding-2", "reasoner",
                     "sim-drone7", "control-drone7", "sim-drone8", "control-drone8",
                     "sim-drone9", "control-drone9", "dashboard"]
    assert plan.robots == ("drone7", "drone8", "drone9") and plan.robot == "drone7"
    env = {s.name: s.env for s in plan.services}
    for i, robot in enumerate(plan.robots):
        control, sim = env[f"control-{robot}"], env[f"sim-{robot}"]
        assert control["AESOP_ROBOT"] == sim["AESOP_ROBOT"] == robot
        assert sim["AESOP_ZENOH_USER"] == f"robot-{robot}"
        assert sim["AESOP_ZENOH_PASSWORD"] == plan.passwords[f"robot-{robot}"]
        # the first robot's ports are the stack's; the others' 100 apart
        assert control["AESOP_CONTROL_PORT"] == str(4 + 100 * i)
        assert sim["AESOP_SIM_PORT"] == str(7 + 100 * i)
        assert plan.robot_urls(robot) == (f"http://127.0.0.1:{4 + 100 * i}",
                                          f"http://127.0.0.1:{7 + 100 * i}")
    assert plan.hub.argv.count("--robot") == 3
    # the replicas: one store (the stack's PostgreSQL, by its socket), a name each
    assert plan.postgres is not None and plan.postgres.root == tmp_path / "postgres"
    for name in ("embedding", "embedding-2"):
        assert env[name]["AESOP_EMBEDDING_STORE"] == plan.postgres.socket_url
        assert env[name]["AESOP_EMBEDDING_REPLICA"] == name
        assert env[name]["AESOP_DATA_DIR"] == str(tmp_path / name)
    assert env["embedding-2"]["AESOP_EMBEDDING_PORT"] == "102"
    assert plan.services[0].ready == "tcp" and "-D" in plan.services[0].argv
    assert "postgresql://aesop@/aesop?host=" in plan.postgres.socket_url  # no password


def test_a_fleet_cannot_be_one_ros2_robot_and_counts_from_one(tmp_path: Path) -> None:
    with pytest.raises(PlanError, match="--ros2 flies the one robot"):
        plan_stack(replace(options(tmp_path), robots=2,
                           ros2=Path("deploy/ros2/quadrotor.yaml")), {}, "t" * 24)
    with pytest.raises(PlanError, match="count from 1"):
        plan_stack(replace(options(tmp_path), replicas=0), {}, "t" * 24)
    assert fleet("robot0", 3) == ("robot0", "robot1", "robot2")
    assert fleet("drone", 2) == ("drone0", "drone1") and fleet("x9", 1) == ("x9",)


def test_an_external_vehicle_plan_starts_none_and_says_how_each_robots_own_joins(
        tmp_path: Path) -> None:
    """Issue 46: `aesop up --vehicle external` runs the stack without its simulator; the
    banner says how each robot's vehicle joins (its robot's user and password file) and
    flies the demo against it over the bus."""
    plan = plan_stack(replace(options(tmp_path), robots=2, vehicle="external"),
                      {"AESOP_ROBOT": "drone7"}, "t" * 24)
    names = [s.name for s in plan.services]
    assert names == ["fake-llm", "embedding", "reasoner", "control-drone7", "control-drone8",
                     "dashboard"]
    assert plan.robot_urls("drone8") == ("http://127.0.0.1:104", None)
    assert "robot-drone8" in plan.passwords  # its vehicle logs in as the robot
    text = urls_text(plan, None)
    for robot in ("drone7", "drone8"):
        assert (f"AESOP_ROBOT={robot} AESOP_ZENOH_MODE=client AESOP_ZENOH_CONNECT="
                f"{plan.endpoint} AESOP_ZENOH_USER=robot-{robot} AESOP_ZENOH_PASSWORD_FILE="
                f"{plan.zenoh_dir / f'robot-{robot}.password'} python my_vehicle.py") in text
    fly = fly_command(plan)
    assert fly is not None and fly.endswith("--vehicle bus") and "--sim-url" not in fly
    assert "simulated vehicle" not in text
    with pytest.raises(PlanError, match="--vehicle external"):
        plan_stack(replace(options(tmp_path), vehicle="external",
                           ros2=Path("deploy/ros2/quadrotor.yaml")), {}, "t" * 24)


def test_a_server_plan_runs_the_detector_reasoner_and_dashboard_behind_a_tls_router(
        tmp_path: Path) -> None:
    """Issue 41: ``aesop up --role server``: the parts robots share, each session with its
    certificate; the robots link in, each as one subject."""
    certs = tmp_path / "certs"
    plan = plan_stack(replace(options(tmp_path), role="server", tls=certs,
                              linked=("robot0", "robot1")),
                      {"AESOP_ZENOH_USER": "someone", "AESOP_ZENOH_PASSWORD": "x"}, "t" * 24)
    assert [s.name for s in plan.services] == ["fake-llm", "embedding", "reasoner", "dashboard"]
    assert plan.hub.name == "router" and plan.passwords == {} and plan.fleet == ()
    argv = plan.hub.argv
    assert argv[argv.index("--role") + 1] == "server" and argv[argv.index("--tls") + 1] == \
        str(certs)
    assert argv[argv.index("--listen") + 1] == "tls/[::]:1"
    assert [argv[i + 1] for i, a in enumerate(argv) if a == "--linked"] == ["robot0", "robot1"]
    assert plan.endpoint == "tls/localhost:1" and plan.robots == ()
    assert plan.linked == ("robot0", "robot1")
    for spec in plan.services[1:]:
        assert spec.env["AESOP_ZENOH_CONNECT"] == "tls/localhost:1"
        assert spec.env["AESOP_ZENOH_TLS_CA"] == str(certs / "ca.pem")
        assert spec.env["AESOP_ZENOH_TLS_CERT"] == str(certs / f"{spec.name}.pem")
        assert spec.env["AESOP_ZENOH_TLS_KEY"] == str(certs / f"{spec.name}-key.pem")
        assert "AESOP_ZENOH_USER" not in spec.env and "AESOP_ZENOH_PASSWORD" not in spec.env
    monitor = plan.bus_settings("monitor")
    assert monitor.zenoh_tls_cert == certs / "monitor.pem" and monitor.zenoh_user is None


def test_a_robot_plan_runs_its_own_router_its_loop_and_its_vehicle(tmp_path: Path) -> None:
    """``aesop up --role robot``: a router open on the robot's loopback (as rmw_zenohd),
    linked to the server with the robot's certificate; the loop and the vehicle its
    clients, with no credentials whatever the environment says."""
    mine = tmp_path / "robot-robot3"
    plan = plan_stack(replace(options(tmp_path), role="robot", tls=mine, server="10.9.0.1:7447"),
                      {"AESOP_ROBOT": "robot3", "AESOP_ZENOH_USER": "someone",
                       "AESOP_ZENOH_PASSWORD": "x"}, "t" * 24)
    assert [s.name for s in plan.services] == ["sim", "control"]
    assert plan.robots == ("robot3",) and plan.passwords == {}
    argv = plan.hub.argv
    assert argv[argv.index("--role") + 1] == "robot" and argv[argv.index("--robot") + 1] == \
        "robot3"
    assert argv[argv.index("--connect") + 1] == "tls/10.9.0.1:7447"
    assert [argv[i + 1] for i, a in enumerate(argv) if a == "--listen"] == [
        "tcp/127.0.0.1:1", "tcp/[::1]:1"]
    for spec in plan.services:
        assert spec.env["AESOP_ZENOH_CONNECT"] == "tcp/127.0.0.1:1"
        assert not {"AESOP_ZENOH_USER", "AESOP_ZENOH_PASSWORD", "AESOP_ZENOH_TLS_CERT"} & set(
            spec.env), spec.name
    assert plan.bus_settings("robot-robot3").zenoh_user is None


@pytest.mark.parametrize(("change", "says"), [
    ({"role": "robot", "server": "h:1"}, "--tls"),
    ({"role": "robot", "tls": Path("r")}, "--server"),
    ({"role": "server", "tls": Path("c"), "ros2": Path("deploy/ros2/quadrotor.yaml")},
     "on the robot"),
    ({"role": "robot", "tls": Path("r"), "server": "h:1", "replicas": 2}, "on the server"),
])
def test_a_role_without_what_it_needs_is_a_plan_error(tmp_path: Path, change: dict[str, Any],
                                                     says: str) -> None:
    with pytest.raises(PlanError, match=says):
        plan_stack(replace(options(tmp_path), **change), {}, "t" * 24)


def test_the_stacks_llm_server_wants_the_key_the_reasoner_holds(tmp_path: Path) -> None:
    """Issue 43: the LLM servers answered without a key, so any local process could hold
    llama.cpp's one thread. The stack's own server (the fake, or llama.cpp's) is keyed with
    the stack's token, and the reasoner presents it; a backend of the user's keeps theirs."""
    plan = plan_stack(options(tmp_path), {}, "t" * 24)
    fake, reasoner = plan.services[0].env, plan.services[2].env
    assert fake["AESOP_ADMIN_TOKEN"] == reasoner["AESOP_REASONER_LLM_API_KEY"] == "t" * 24
    local = plan_stack(replace(options(tmp_path), local_model=LocalModel(tmp_path / "m.gguf",
                                                                         "m")), {}, "u" * 24)
    assert local.services[0].env["API_KEY"] == "u" * 24  # llama.cpp's server reads API_KEY
    assert local.services[2].env["AESOP_REASONER_LLM_API_KEY"] == "u" * 24
    theirs = plan_stack(options(tmp_path), {"AESOP_REASONER_LLM_BASE_URL": "http://x/v1",
                                            "AESOP_REASONER_LLM_API_KEY": "sk-theirs"}, "t" * 24)
    assert theirs.services[1].env["AESOP_REASONER_LLM_API_KEY"] == "sk-theirs"
