"""The ROS 2 bridge as a service (``aesop serve ros2``'s app) on real Zenoh peers, with a
plain zenoh-python session in the role of the robot's rmw_zenoh nodes.

* Bad samples (no attachment, another type's hash, truncated CDR, NaN fields, a pose in
  another frame, an unknown class id) are dropped, counted per topic and reason in
  ``GET /v1/bridge`` and ``/metrics``, logged once per topic and reason, and the next good
  sample goes through.
* Out: the set-point as ``AccelStamped`` with rmw_zenoh's 33-byte attachment (sequence from
  1, the bridge's publisher GID), the mode, decision (with its option's label) and alarms as
  String JSON.
* The ROS graph: the node's and each endpoint's liveliness token, as ``ros2 node list``
  reads them.
"""

from __future__ import annotations

import json
import logging
import math
import secrets
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from fastapi.testclient import TestClient

from services.ros2 import convert, wire
from services.ros2.api import create_app
from services.ros2.config import load_config
from services.ros2.settings import Ros2Settings
from shared import topics
from shared.bus import Bus, zenoh_config
from shared.messages import (
    ControlState,
    Event,
    Mode,
    Observation,
    Option,
    ReasonerDecision,
    ReasonerRequest,
    VehicleSetpoint,
    VehicleState,
)
from shared.settings import BusSettings
from tests.zenoh_peers import endpoint, wait_until  # noqa: F401  (a fixture)
from tools.fakes.ros2_cdr import detections_cdr, odometry_cdr, string_cdr

QUADROTOR = Path(__file__).resolve().parents[2] / "deploy" / "ros2" / "quadrotor.yaml"
CONFIG = load_config(QUADROTOR)
ROBOT = CONFIG.robot
MAPPED = {m.role: m for m in CONFIG.topics()}
TOKEN = secrets.token_urlsafe(24)


def key(role: str, ros_type: str | None = None) -> str:
    m = MAPPED[role]
    ros_type = ros_type or m.ros_type
    return wire.data_key(0, m.name, ros_type, convert.type_hash(ros_type))


def state(seq: int, position: tuple[float, float, float] = (1.0, 2.0, 3.0)) -> VehicleState:
    return VehicleState(robot=ROBOT, seq=seq, stamp=50.0 + seq, position=position,
                        velocity=(0.5, 0.0, 0.0))


class Robot:
    """The robot's side: puts samples as rmw_zenoh does and records what comes back."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session, self.seq = session, 0
        self.gid = wire.gid(f"the robot's publisher of {session.zid()}")
        self.heard: dict[str, list[tuple[bytes, bytes | None]]] = {}
        for role in ("setpoint", "mode", "decision", "alarms"):
            session.declare_subscriber(key(role), self._on(role))

    def _on(self, role: str) -> Any:
        def on_sample(sample: zenoh.Sample) -> None:
            att = None if sample.attachment is None else sample.attachment.to_bytes()
            self.heard.setdefault(role, []).append((sample.payload.to_bytes(), att))
        return on_sample

    def put(self, role: str, payload: bytes, *, on: str | None = None,
            attachment: bool = True) -> None:
        self.seq += 1
        att = wire.Attachment(self.seq, 1, self.gid).encode() if attachment else None
        self.session.put(on or key(role), payload, attachment=att)

    def strings(self, role: str) -> list[dict[str, Any]]:
        return [json.loads(convert.typestore().deserialize_cdr(raw, "std_msgs/msg/String").data)
                for raw, _ in list(self.heard.get(role, []))]


@pytest.fixture
def bridge(endpoint: str) -> Iterator[TestClient]:  # noqa: F811
    settings = Ros2Settings(port=0, config=QUADROTOR, admin_token=TOKEN)
    app = create_app(settings, CONFIG, bus_factory=lambda: Bus.open(
        BusSettings(zenoh_listen=[endpoint], robot=ROBOT), "ros2"))
    with TestClient(app, headers={"Authorization": f"Bearer {TOKEN}"}) as client:
        yield client


@pytest.fixture
def stack(endpoint: str, bridge: TestClient) -> Iterator[Bus]:  # noqa: F811
    with Bus.open(BusSettings(zenoh_connect=[endpoint]), "stack") as bus:
        yield bus


@pytest.fixture
def robot(endpoint: str, bridge: TestClient) -> Iterator[Robot]:  # noqa: F811
    with zenoh.open(zenoh_config(BusSettings(zenoh_connect=[endpoint]))) as session:
        yield Robot(session)


def status(bridge: TestClient) -> dict[str, dict[str, Any]]:
    answer = bridge.get("/v1/bridge")
    assert answer.status_code == 200
    return {t["role"]: t for t in answer.json()["topics"]}


def test_bad_samples_are_dropped_counted_logged_once_and_the_next_good_one_passes(
        bridge: TestClient, stack: Bus, robot: Robot, caplog: pytest.LogCaptureFixture) -> None:
    states = stack.latest(topics.vehicle_state(ROBOT), VehicleState)
    events: list[Event] = []
    stack.each(topics.event(ROBOT, "ros2"), Event, lambda got: events.append(got.message))
    observations = stack.latest(topics.observation(ROBOT), Observation)
    good = odometry_cdr(state(1))
    wait_until(lambda: robot.put("odometry", good) or states.get() is not None,
               "a first odometry through the bridge")
    with caplog.at_level(logging.WARNING, logger="services.ros2.bridge"):
        bad_odometry = [
            dict(payload=good, attachment=False),  # rmw_zenoh drops these too
            dict(payload=good, attachment=False),  # counted again, not logged again
            dict(payload=string_cdr("x"), on=key("odometry", "std_msgs/msg/String")),
            dict(payload=good[:30]),  # truncated CDR
            dict(payload=odometry_cdr(state(2, (math.nan, 0.0, 0.0)))),
            dict(payload=odometry_cdr(state(3), frame_id="odom")),
        ]
        for sample in bad_odometry:
            robot.put("odometry", **sample)
        robot.put("detections", detections_cdr([("0", 0.9), ("99", 0.9)]))  # 99: unknown
        robot.put("odometry", odometry_cdr(state(4, (4.0, 0.0, 1.0))))
        robot.put("detections", detections_cdr([("0", 0.9), ("10", 0.8)]))
        wait_until(lambda: (got := states.get()) is not None
                   and got.message.position == (4.0, 0.0, 1.0), "the good odometry after")
        wait_until(lambda: observations.get() is not None, "the good detections after")
    obs = observations.get()
    assert obs is not None
    assert [d.label for d in obs.message.detections] == \
        ["a red box on the ground", "a quadrotor on the red box"]
    assert obs.message.task == "landing on the red box"
    after = states.get()
    assert after is not None and after.message.frame == "world"
    assert after.message.velocity == pytest.approx((0.5, 0.0, 0.0))
    odometry, detections = status(bridge)["odometry"], status(bridge)["detections"]
    assert odometry["dropped"] == {"attachment": 2, "type": 1, "cdr": 1, "non_finite": 1,
                                   "frame": 1}
    assert detections["dropped"] == {"unknown_class": 1}
    warned = [r.getMessage() for r in caplog.records if "dropped a sample" in r.getMessage()]
    assert len(warned) == 6  # once per topic and reason
    assert any("99" in w for w in warned) and any("no attachment" in w for w in warned)
    wait_until(lambda: len(events) == 6, "an event per topic and reason")
    assert {(e.data["topic"], e.data["reason"]) for e in events} >= {
        ("/mavros/local_position/odom", "attachment"), ("/camera/detections", "unknown_class")}
    assert {e.kind for e in events} == {"ros2_dropped"}
    metrics = bridge.get("/metrics").text
    assert 'aesop_ros2_dropped_total{reason="attachment",topic="/mavros/local_position/odom"}' \
        ' 2.0' in metrics


def test_the_stack_comes_out_on_ros_topics_with_rmw_zenohs_attachment(
        bridge: TestClient, stack: Bus, robot: Robot) -> None:
    sp = VehicleSetpoint(robot=ROBOT, seq=1, state_seq=1, state_stamp=10.0, t=10.05,
                         valid_until=10.2, mode=Mode.NOMINAL, acceleration=(0.5, 0.0, -0.1),
                         position=(0.0, 0.0, 1.0), velocity=(0.2, 0.0, 0.0))
    wait_until(lambda: stack.publish(topics.vehicle_setpoint(ROBOT), sp)
               or bool(robot.heard.get("setpoint")), "a set-point on the ROS topic")
    stack.publish(topics.vehicle_setpoint(ROBOT), sp.model_copy(update={"seq": 2, "t": 10.1}))

    def stamp(raw: bytes) -> float:
        accel = convert.typestore().deserialize_cdr(raw, "geometry_msgs/msg/AccelStamped")
        return float(convert.seconds(accel.header.stamp))

    # the first set-point may have been heard more than once while the route was being
    # made (it is published until one arrives): the second is the one stamped 10.1
    wait_until(lambda: any(stamp(r) == pytest.approx(10.1)
                           for r, _ in robot.heard.get("setpoint", [])), "the second set-point")
    raw, att = robot.heard["setpoint"][-1]
    accel = convert.typestore().deserialize_cdr(raw, "geometry_msgs/msg/AccelStamped")
    assert convert.seconds(accel.header.stamp) == pytest.approx(10.1)
    assert (accel.accel.linear.x, accel.accel.linear.z) == (0.5, -0.1)
    assert att is not None and len(att) == 33
    first, last = (wire.parse_attachment(a) for _, a in
                   (robot.heard["setpoint"][0], robot.heard["setpoint"][-1]))
    # the GID is the hash of the publisher's graph token, as the robot's graph shows it
    topic = wire.mangle(wire.fully_qualified(MAPPED["setpoint"].name))
    publishers = [str(reply.ok.key_expr) for reply in robot.session.liveliness().get(
        f"{wire.LIVELINESS}/0/**", timeout=5.0) if reply.ok is not None
        and "/MP/" in str(reply.ok.key_expr) and f"/{topic}/" in str(reply.ok.key_expr)]
    assert len(publishers) == 1, publishers
    assert first.gid == last.gid == wire.gid(publishers[0])
    assert last.sequence_number == len(robot.heard["setpoint"])  # from 1, one per sample
    request = ReasonerRequest(
        robot=ROBOT, request_id="r1", deadline_s=4.0,
        observation=Observation(robot=ROBOT, seq=1, text="a quadrotor on the red box"),
        options=(Option(index=0, label="continue"), Option(index=1, label="land on blue")))
    stack.publish(topics.reasoner_request(ROBOT), request)
    stack.publish(topics.state(ROBOT), ControlState(robot=ROBOT, t=1.0, x=(0.0,) * 12,
                                                    u=(0.0,) * 3, mode=Mode.PENDING))
    stack.publish(topics.event(ROBOT, "control"), Event(
        robot=ROBOT, source="control", kind="state_stale", severity="alarm", message="late"))
    stack.publish(topics.event(ROBOT, "control"), Event(
        robot=ROBOT, source="control", kind="tick", severity="info"))  # not an alarm
    wait_until(lambda: bool(robot.strings("mode")) and bool(robot.strings("alarms")),
               "the mode and the alarm")
    stack.publish(topics.reasoner_decision(ROBOT), ReasonerDecision(
        robot=ROBOT, request_id="r1", choice=1, source="llm", latency_ms=900.0))
    wait_until(lambda: bool(robot.strings("decision")), "the decision")
    assert robot.strings("mode")[0]["mode"] == "anomaly_pending"
    assert [a["kind"] for a in robot.strings("alarms")] == ["state_stale"]
    assert robot.strings("decision")[0] | {} == {
        "robot": ROBOT, "request_id": "r1", "choice": 1, "label": "land on blue",
        "source": "llm", "rationale": "", "latency_ms": 900.0, "model": ""}


def test_ros_tools_see_the_bridges_node_and_endpoints(bridge: TestClient, robot: Robot) -> None:
    zid = bridge.get("/v1/bridge").json()["zid"]
    expected = {wire.Node(0, zid, CONFIG.node).token(),
                *(wire.Node(0, zid, CONFIG.node).entity_token(
                    m.entity_id, "MS" if m.direction == "in" else "MP", m.name, m.ros_type,
                    convert.type_hash(m.ros_type), wire.qos_keyexpr(depth=10))
                  for m in CONFIG.topics())}
    seen: set[str] = set()

    def graph() -> set[str]:
        replies = robot.session.liveliness().get(f"{wire.LIVELINESS}/0/**", timeout=2.0)
        seen.update(str(r.ok.key_expr) for r in replies if r.ok is not None)
        return seen

    wait_until(lambda: graph() >= expected, "the bridge's liveliness tokens")
    assert f"{wire.LIVELINESS}/0/{zid}/0/0/NN/%/%/aesop_bridge" in seen


def test_bench_ros2_reports_both_ways_and_loses_nothing() -> None:
    """``aesop bench ros2 --json``, small: a real bridge process. Shape and consistency
    only; the numbers are for docs/benchmarks.md."""
    r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "ros2", "--json",
                        "--seconds", "1", "--rate", "50"], capture_output=True, text=True,
                       timeout=120, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(r.stdout)
    for way in ("in", "out"):
        stats = result[way]
        assert stats["sent"] == 50 and stats["n"] + stats["lost"] == 50, stats
        assert stats["lost"] == 0, stats  # loopback, 50 Hz: nothing may be lost
        assert 0 <= stats["p50"] <= stats["p99"] <= stats["max"], stats
    bad = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "ros2", "--rate", "0"],
                         capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert bad.returncode == 2 and "--rate" in bad.stderr
