"""`aesop serve control` as a real process on a real Zenoh link, flying `aesop serve sim`
(another process): the loop's messages, the set-points, the reasoner round trip, the
stale-verdict and stale-state alarms, and the HTTP admin API."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Generic, TypeVar

import httpx
import numpy as np
import pytest
import zenoh

from shared import topics
from shared.bus import Bus
from shared.messages import (
    AnomalyVerdict,
    ControlState,
    Event,
    Message,
    PlanSnapshot,
    ReasonerDecision,
    ReasonerRequest,
    Regions,
    VehicleReset,
    VehicleState,
)
from shared.process import ServiceProcess, free_port
from shared.settings import BusSettings
from tests.zenoh_peers import wait_until

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

TOKEN = "control-test-token-0123"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
ROBOT = "drone1"
WAIT_S = 15.0
# A small geometry whose ticks take milliseconds; K = 1 s, T = 3 s.
SCENARIO = """\
name: light
dt: 0.1
horizon_s: 3.0
consensus_s: 1.0
start: {center: [0.0, 0.0, 1.0], half_width: 0.0}
goal: [1.0, 0.0, 1.0]
regions:
  - {index: 1, name: hold, label: holding zone, kind: hover,
     position_lo: [0.3, -0.8, 0.8], position_hi: [1.3, -0.3, 1.2]}
  - {index: 2, name: roof, label: rooftop, kind: landing,
     position_lo: [0.3, 0.3, 0.0], position_hi: [1.3, 0.8, 0.2]}
  - {index: 3, name: lot, label: parking lot, kind: landing,
     position_lo: [-0.8, -0.5, 0.0], position_hi: [-0.3, 0.5, 0.2]}
"""
REGIONS = [
    {"index": 1, "name": "hold", "label": "holding zone", "kind": "hover",
     "position_lo": [0.3, -0.8, 0.8], "position_hi": [1.3, -0.3, 1.2]},
    {"index": 2, "name": "roof", "label": "rooftop", "kind": "landing",
     "position_lo": [0.3, 0.3, 0.0], "position_hi": [1.3, 0.8, 0.2]},
]

M = TypeVar("M", bound=Message)


class Inbox(Generic[M]):
    """Every message on ``key``, decoded, in arrival order (thread-safe)."""

    def __init__(self, bus: Bus, key: str, model: type[M]) -> None:
        self.model = model
        self._lock = threading.Lock()
        self._items: list[M] = []
        self._sub = bus.session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        message = self.model.decode(sample.payload.to_bytes())
        with self._lock:
            self._items.append(message)

    def items(self) -> list[M]:
        with self._lock:
            return list(self._items)

    def mark(self) -> int:
        with self._lock:
            return len(self._items)

    def wait_for(self, cond: Callable[[M], bool], what: str, since: int = 0) -> M:
        found: list[M] = []

        def check() -> bool:
            found[:] = [m for m in self.items()[since:] if cond(m)]
            return bool(found)

        wait_until(check, what, WAIT_S)
        return found[0]


class VerdictSource:
    """A fake detector: a verdict every 50 ms while ``running``, anomalous while ``anomaly``."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.running = threading.Event()
        self.anomaly = False
        self._stop = threading.Event()
        self._seq = 0
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            if not self.running.is_set():
                continue
            self._seq += 1
            self.bus.publish(topics.anomaly(ROBOT), AnomalyVerdict(
                robot=ROBOT, seq=self._seq, score=-0.9, threshold=-0.95,
                is_anomaly=self.anomaly, k=1, model="fake", cache="scene", cache_version=1,
                latency_ms=1.0))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)


class Stack:
    def __init__(self, proc: ServiceProcess, sim: ServiceProcess, bus: Bus,
                 source: VerdictSource) -> None:
        self.proc, self.sim, self.bus, self.source = proc, sim, bus, source
        self.http = httpx.Client(base_url=proc.url, timeout=10, headers=AUTH)
        self.vehicle = httpx.Client(base_url=sim.url, timeout=10, headers=AUTH)
        self.states = Inbox(bus, topics.state(ROBOT), ControlState)
        self.plans = Inbox(bus, topics.plan(ROBOT), PlanSnapshot)
        self.requests = Inbox(bus, topics.reasoner_request(ROBOT), ReasonerRequest)
        self.events = Inbox(bus, topics.events(ROBOT), Event)
        self.regions = Inbox(bus, topics.regions(ROBOT), Regions)

    def nominal_flight(self) -> None:
        """A new flight from the start, nothing flagged, seen nominal: as an operator starts
        one, the detector off (the reset loop waits), the loop reset, the vehicle moved to
        the start, the detector on again."""
        self.source.anomaly = False
        self.source.running.clear()
        time.sleep(1.2)  # the newest verdict goes stale (verdict_stale_s 1.0)
        r = self.http.post("/v1/reset", json={})
        assert r.status_code == 200, r.text
        r = self.vehicle.post("/v1/reset", json={"start": [0.0, 0.0, 1.0]})
        assert r.status_code == 200, r.text
        wait_until(lambda: np.allclose(self.http.get("/v1/state").json()["state"]["x"][:3],
                                       (0.0, 0.0, 1.0), atol=0.02), "the vehicle at the start",
                   WAIT_S)
        since = self.states.mark()  # only the new flight's from here
        self.source.running.set()
        self.states.wait_for(lambda s: s.mode == "nominal" and s.t == 0.0, "the flight", since)


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    tmp = tmp_path_factory.mktemp("control")
    (tmp / "light.yaml").write_text(SCENARIO)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    port = free_port()
    env = {"AESOP_ADMIN_TOKEN": TOKEN, "AESOP_CONTROL_SCENARIO": str(tmp / "light.yaml"),
           "AESOP_ZENOH_LISTEN": endpoint, "AESOP_ROBOT": ROBOT, "AESOP_CONTROL_RATE_HZ": "10",
           "AESOP_CONTROL_VERDICT_STALE_S": "1.0"}
    proc = ServiceProcess(["serve", "control", "--port", str(port)], port=port, env=env,
                          log_path=tmp / "control.log", ready_timeout_s=60)
    sim_port = free_port()
    sim = ServiceProcess(["serve", "sim", "--port", str(sim_port), "--scenario",
                          str(tmp / "light.yaml")], port=sim_port,
                         env={"AESOP_ADMIN_TOKEN": TOKEN, "AESOP_ZENOH_CONNECT": endpoint,
                              "AESOP_ROBOT": ROBOT}, log_path=tmp / "sim.log",
                         ready_timeout_s=60)
    with proc, sim, Bus.open(BusSettings(zenoh_connect=[endpoint]), "tester") as bus:
        source = VerdictSource(bus)
        stack = Stack(proc, sim, bus, source)
        try:
            yield stack
        finally:
            source.close()
            stack.http.close()
            stack.vehicle.close()


def test_state_and_plans_stream_one_per_tick(stack: Stack) -> None:
    """Every tick publishes a state one plant step (dt) after the last, or a whole number of
    steps where the loop skipped deadlines after an overrun (a busy machine), each skip counted
    in `missed_ticks`; the loop's wall-clock rate is measured on /metrics and in benchmarks,
    not asserted here."""
    stack.nominal_flight()
    since_state, since_plan = stack.states.mark(), stack.plans.mark()
    wait_until(lambda: len(stack.states.items()) - since_state >= 10
               and len(stack.plans.items()) - since_plan >= 5, "10 states and 5 plans", WAIT_S)
    states = stack.states.items()[since_state:]
    plans = stack.plans.items()[since_plan:]
    steps = np.diff([s.t for s in states])
    whole = np.round(steps / 0.1)
    assert np.all(whole >= 1) and np.allclose(steps, whole * 0.1, atol=1e-6), steps
    assert all(s.robot == ROBOT and len(s.x) == 12 and len(s.u) == 4 for s in states)
    assert all(s.mode == "nominal" for s in states)
    assert len(plans[-1].nominal) == 31 and plans[-1].consensus_steps == 10
    assert set(plans[-1].recovery) <= {1, 2, 3} and plans[-1].recovery
    body = stack.http.get("/v1/state").json()
    assert body["mode"] == "nominal" and body["state"]["robot"] == ROBOT
    assert body["method"] == "aesop" and body["scenario"] == "light"
    loop = body["loop"]
    assert loop["rate_hz"] == 10 and loop["ticks"] > 10
    assert loop["jitter_p50_ms"] is not None and loop["jitter_p99_ms"] >= loop["jitter_p50_ms"]
    assert loop["overruns"] >= 0 and loop["last_step_ms"] > 0
    assert loop["missed_ticks"] >= int(np.sum(whole - 1)), (steps, loop)
    vehicle = body["vehicle"]
    assert vehicle["fresh"] and vehicle["clock"] == "sync" and vehicle["setpoints"] > 0
    assert stack.vehicle.get("/v1/state").json()["setpoints"]["received"] > 0
    assert {"control", "sim"} <= stack.bus.alive()


def test_an_anomaly_asks_the_reasoner_and_its_decision_starts_the_recovery(
        stack: Stack) -> None:
    stack.nominal_flight()
    since_req, since_state = stack.requests.mark(), stack.states.mark()
    since_event = stack.events.mark()
    stack.source.anomaly = True
    request = stack.requests.wait_for(lambda r: True, "a reasoner request", since_req)
    assert request.robot == ROBOT and request.options[0].index == 0
    assert request.options[0].label == "continue" and 0 < request.deadline_s <= 1.0
    choice = request.options[1].index
    decision = ReasonerDecision(robot=ROBOT, request_id=request.request_id, choice=choice,
                                source="llm", latency_ms=12.0)
    stack.bus.publish(topics.reasoner_decision(ROBOT), decision)
    state = stack.states.wait_for(lambda s: s.mode == "recovering", "recovering", since_state)
    assert state.chosen == choice
    event = stack.events.wait_for(lambda e: e.data.get("to") == "recovering",
                                  "the mode change", since_event)
    assert event.kind == "mode_change" and event.data["fallback"] is False
    stack.source.anomaly = False


def test_silent_detector_raises_one_stale_alarm(stack: Stack) -> None:
    stack.nominal_flight()
    since = stack.events.mark()
    stack.source.running.clear()
    alarm = stack.events.wait_for(lambda e: e.kind == "verdict_stale", "a stale alarm", since)
    assert alarm.severity == "alarm" and alarm.source == "control"
    stack.source.running.set()
    stack.events.wait_for(lambda e: e.kind == "verdict_fresh", "verdicts again", since)
    assert [e.kind for e in stack.events.items()[since:]].count("verdict_stale") == 1


def test_a_vehicle_that_falls_silent_is_an_anomaly_and_its_return_ends_it(
        stack: Stack) -> None:
    stack.nominal_flight()
    since_event, since_req = stack.events.mark(), stack.requests.mark()
    r = stack.vehicle.post("/v1/faults", json={"dropout_s": 1.0})
    assert r.status_code == 200 and r.json()["faults"]["dropout_left_s"] > 0
    alarm = stack.events.wait_for(lambda e: e.kind == "state_stale", "the stale-state alarm",
                                  since_event)
    assert alarm.severity == "alarm" and alarm.source == "control"
    request = stack.requests.wait_for(lambda r: True, "a request about the vehicle", since_req)
    assert "vehicle's state" in request.observation.text
    assert 0 not in [o.index for o in request.options]
    stack.events.wait_for(lambda e: e.kind == "silence_ended", "the state back", since_event)
    assert stack.http.get("/v1/state").json()["mode"] == "nominal"


def test_regions_routes(stack: Stack) -> None:
    http = stack.http
    listing = http.get("/v1/regions").json()
    assert len(listing["goal"]) == 3  # the nominal goal (m), for the dashboard
    before = listing["regions"]
    assert [r["name"] for r in before] == ["hold", "roof", "lot"]
    assert httpx.post(f"{stack.proc.url}/v1/regions", json={"regions": REGIONS}).status_code == 401
    assert httpx.get(f"{stack.proc.url}/v1/regions").status_code == 401  # reads too
    bad = [({"regions": [{k: v for k, v in REGIONS[0].items() if k != "name"}]},
            "regions[0].name"),
           ({"regions": [{k: v for k, v in REGIONS[0].items() if k != "position_hi"}]},
            "regions[0].position_hi"),
           ({"regions": [REGIONS[0], {**REGIONS[1], "kind": "orbit"}]}, "regions[1].kind"),
           ({"regions": [REGIONS[0], {**REGIONS[1], "index": 1}]}, "regions"),  # 1..d
           ({"regions": [{**REGIONS[0], "position_lo": [1.0, 1.0]}]},
            "regions[0].position_lo[2]"),
           ({"regions": []}, "regions"),
           ({"regions": [{**REGIONS[0], "position_hi": [1.3, 99.0, 1.2]}]}, "regions[0]"),
           ({}, "regions")]
    for body, field in bad:
        r = http.post("/v1/regions", headers=AUTH, json=body)
        assert r.status_code == 422, (body, r.text)
        assert r.json()["error"]["field"] == field, (body, r.json())
    assert http.get("/v1/regions").json()["regions"] == before

    stack.nominal_flight()
    since = stack.states.mark()
    stack.source.anomaly = True
    stack.states.wait_for(lambda s: s.mode != "nominal", "leaving nominal", since)
    r = http.post("/v1/regions", headers=AUTH, json={"regions": REGIONS})
    assert r.status_code == 409 and r.json()["error"]["field"] == "mode"
    assert http.get("/v1/regions").json()["regions"] == before

    stack.nominal_flight()
    since = stack.events.mark()
    r = http.post("/v1/regions", headers=AUTH, json={"regions": REGIONS})
    assert r.status_code == 200, r.text
    assert [x["name"] for x in http.get("/v1/regions").json()["regions"]] == ["hold", "roof"]
    event = stack.events.wait_for(lambda e: e.kind == "regions_updated", "the swap", since)
    assert event.data["count"] == 2
    seen = stack.regions.wait_for(lambda m: len(m.regions) == 2, "the new regions on the bus")
    assert [r.model_dump(mode="json") for r in seen.regions] == REGIONS
    assert seen.goal == (1.0, 0.0, 1.0)


def test_the_regions_and_goal_go_out_on_the_bus_again_for_late_subscribers(
        stack: Stack) -> None:
    since = stack.regions.mark()
    first = stack.regions.wait_for(lambda m: True, "the regions on the bus", since)
    again = stack.regions.wait_for(lambda m: m.stamp > first.stamp, "them again", since)
    listing = stack.http.get("/v1/regions").json()
    assert [r.model_dump(mode="json") for r in again.regions] == listing["regions"]
    assert list(again.goal) == listing["goal"]


def test_the_sim_answers_the_contracts_reset_query_and_publishes_its_truth(
        stack: Stack) -> None:
    """Issue 46: `aesop demo --vehicle bus` starts a flight by the contract's reset query
    and judges it on the vehicle's truth topic; the simulator answers one and publishes
    the other. A reset outside the fence is refused: no answer, nothing moved."""
    truths = Inbox(stack.bus, topics.vehicle_truth(ROBOT), VehicleState)
    key = topics.vehicle_reset(ROBOT)
    [answer] = stack.bus.ask(key, VehicleState, timeout=5.0,
                             payload=VehicleReset(robot=ROBOT, position=(0.5, -0.5, 1.0)))
    assert answer.message.position == (0.5, -0.5, 1.0)
    assert answer.message.velocity == (0.0, 0.0, 0.0)
    assert np.allclose(stack.vehicle.get("/v1/state").json()["truth"]["position"], (0.5, -0.5, 1.0),
                       atol=0.05)
    truths.wait_for(lambda s: np.allclose(s.position, (0.5, -0.5, 1.0), atol=0.05),
                    "the truth there")
    assert stack.bus.ask(key, VehicleState, timeout=1.0,
                         payload=VehicleReset(robot=ROBOT, position=(0.0, 0.0, 99.0))) == []
    assert stack.vehicle.get("/v1/state").json()["truth"]["position"][2] < 5.0


def test_reset_and_ops_routes(stack: Stack) -> None:
    http = stack.http
    assert httpx.post(f"{stack.proc.url}/v1/reset", json={}).status_code == 401
    r = http.post("/v1/reset", json={"start": [0.0, 0.0, 1.0]})  # control moves no vehicle
    assert r.status_code == 422 and r.json()["error"]["field"] == "start"
    assert http.post("/v1/reset").status_code == 200  # no body
    r = stack.vehicle.post("/v1/reset", json={"start": [0.0, 0.0, 99.0]})
    assert r.status_code == 422 and r.json()["error"]["field"] == "start"
    r = stack.vehicle.post("/v1/faults", json={"jump": [1.0, 0.0, 0.0]})
    assert r.status_code == 422 and r.json()["error"]["field"] == "jump_s"
    assert http.get("/healthz").json() == {"status": "ok"}
    assert http.get("/readyz").status_code == 200
    metrics = http.get("/metrics").text
    for series in ("aesop_control_ticks_total", "aesop_control_jitter_seconds_bucket",
                   "aesop_control_overruns_total", "aesop_control_missed_ticks_total",
                   "aesop_control_step_seconds_bucket", 'aesop_control_mode{mode="nominal"}',
                   "aesop_control_stale_verdict_ticks_total",
                   "aesop_control_stale_verdict_alarms_total",
                   "aesop_control_reasoner_requests_total",
                   "aesop_control_state_age_seconds_bucket", "aesop_control_setpoints_total",
                   "aesop_control_stale_state_ticks_total"):
        assert series in metrics, series
    assert "aesop_control_tick_errors_total 0.0" in metrics


def test_a_bad_scenario_stops_the_command_with_the_field(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(SCENARIO.replace("goal: [1.0, 0.0, 1.0]\n", ""))
    env = {"AESOP_CONTROL_SCENARIO": str(path), "PATH": "/usr/bin:/bin"}
    done = subprocess.run([sys.executable, "-m", "tools.cli", "serve", "control"],
                          env=env, capture_output=True, text=True, timeout=60,
                          cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 2 and "goal: required" in done.stderr


def test_serve_control_takes_the_scenario_as_a_flag(tmp_path: Path) -> None:
    env = {"PATH": "/usr/bin:/bin"}
    root = Path(__file__).resolve().parents[2]
    missing = tmp_path / "missing.yaml"
    done = subprocess.run([sys.executable, "-m", "tools.cli", "serve", "control",
                           "--scenario", str(missing)],
                          env=env, capture_output=True, text=True, timeout=60, cwd=root)
    assert done.returncode == 2, done.stderr
    assert f"--scenario: {missing}: No such file" in done.stderr, done.stderr
    other = subprocess.run([sys.executable, "-m", "tools.cli", "serve", "embedding",
                            "--scenario", "hardware"],
                           env=env, capture_output=True, text=True, timeout=60, cwd=root)
    assert other.returncode == 2, other.stderr
    assert "--scenario: only `aesop serve control` and `aesop serve sim` take a scenario" \
        in other.stderr, other.stderr
