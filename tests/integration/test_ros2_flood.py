"""The ROS 2 bridge under a flood from the ROS side (issue 43, finding 4), on real Zenoh
peers with a plain zenoh-python session as the robot's nodes (the ``ros2`` credential).

The finding: one 1,024-item drop-oldest queue and one thread for both directions, so a
flood of malformed CDR or attachment-less samples coming in starved the set-points going
out (112 -> 18 per 6 s) and the robot's good odometry, and 900 KB samples grew the bridge
to ~700 MiB. What must hold, shown by counts and by the bridge's own accounting, never by
a time or RSS:

* the set-points go out on their own queue and thread while the inbound side is stuck and
  flooded (its worker held on one odometry by the test);
* a sample refused at the subscriber's callback (no attachment, CDR whose layout is wrong,
  over the topic's size) is counted there, never queued, even while the inbound worker is
  stuck; one that only decoding finds out waits on its own topic's queue;
* a flood on one ROS topic fills only that topic's queue: the good odometry queued before
  it all comes in;
* every inbound queue stays under its byte limit, and oversized samples are refused
  before they are copied.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
import zenoh
from fastapi.testclient import TestClient

from services.ros2 import convert, wire
from services.ros2.api import create_app
from services.ros2.bridge import IN_ITEMS
from services.ros2.settings import Ros2Settings
from shared import topics
from shared.bus import Bus, zenoh_config
from shared.messages import Mode, VehicleSetpoint, VehicleState
from shared.settings import BusSettings
from tests.integration.test_ros2_bridge import (
    CONFIG,
    QUADROTOR,
    ROBOT,
    TOKEN,
    Robot,
    key,
    state,
    status,
)
from tests.zenoh_peers import endpoint, wait_until  # noqa: F401  (a fixture)
from tools.fakes.ros2_cdr import detections_cdr, odometry_cdr, string_cdr

# a CDR header (little-endian) and garbage: the callback's skim of the layout refuses it
GARBAGE = b"\x00\x01\x00\x00" + b"\xff" * 800
# what only decoding finds out: an odometry with a NaN, detections cut inside their
# sequence (the skim stops there), a scene whose string is not UTF-8
NAN_ODOMETRY = odometry_cdr(state(3, (math.nan, 0.0, 1.0)))
CUT_DETECTIONS = detections_cdr([("0", 0.9), ("1", 0.8)])[:200]
NOT_UTF8 = b"\x00\x01\x00\x00\x03\x00\x00\x00\xff\xfe\x00"
FLOOD = 3000  # of each kind
SETPOINTS = 50


def put(robot: Robot, role: str, payload: bytes, *, attachment: bool = True) -> None:
    """As :meth:`Robot.put`, blocking rather than dropping when the link is busy, so every
    sample of a flood reaches the bridge and its counts can be compared exactly."""
    robot.seq += 1
    att = wire.Attachment(robot.seq, 1, robot.gid).encode() if attachment else None
    robot.session.put(key(role), payload, attachment=att,
                      congestion_control=zenoh.CongestionControl.BLOCK)


def setpoint(seq: int) -> VehicleSetpoint:
    t = 20.0 + 0.05 * seq
    return VehicleSetpoint(robot=ROBOT, seq=seq, state_seq=1, state_stamp=t, t=t,
                           valid_until=t + 0.2, mode=Mode.NOMINAL,
                           acceleration=(0.1, 0.0, 0.0), position=(0.0, 0.0, 1.0),
                           velocity=(0.0, 0.0, 0.0))


def stamps(robot: Robot) -> set[float]:
    out = set()
    for raw, _ in list(robot.heard.get("setpoint", [])):
        accel = convert.typestore().deserialize_cdr(raw, "geometry_msgs/msg/AccelStamped")
        out.add(round(convert.seconds(accel.header.stamp), 3))
    return out


def queues(bridge: TestClient) -> dict[str, dict[str, Any]]:
    answer = bridge.get("/v1/bridge")
    assert answer.status_code == 200
    return {q["name"]: q for q in answer.json()["queues"]}


@dataclass
class Rig:
    bridge: TestClient  # the bridge's app
    stack: Bus
    robot: Robot
    release: Callable[[], None]  # lets the inbound worker go on


@pytest.fixture
def stuck(endpoint: str, monkeypatch: pytest.MonkeyPatch) -> Iterator[Rig]:  # noqa: F811
    """The bridge with both routes made (an odometry in, a set-point out) and then its
    inbound worker held inside the conversion of one good odometry until the test calls
    ``release`` (or ends)."""
    settings = Ros2Settings(port=0, config=QUADROTOR, admin_token=TOKEN)
    app = create_app(settings, CONFIG, bus_factory=lambda: Bus.open(
        BusSettings(zenoh_listen=[endpoint], robot=ROBOT), "ros2"))
    armed, gate, holding = threading.Event(), threading.Event(), threading.Event()
    original = convert.vehicle_state

    def held(*args: Any, **kwargs: Any) -> VehicleState:
        if armed.is_set():
            holding.set()
            gate.wait(60.0)
        return original(*args, **kwargs)

    monkeypatch.setattr(convert, "vehicle_state", held)
    with TestClient(app, headers={"Authorization": f"Bearer {TOKEN}"}) as bridge, \
            Bus.open(BusSettings(zenoh_connect=[endpoint]), "stack") as stack, \
            zenoh.open(zenoh_config(BusSettings(zenoh_connect=[endpoint]))) as session:
        robot, sent = Robot(session), 0
        states = stack.latest(topics.vehicle_state(ROBOT), VehicleState)

        def odometry(seq: int) -> None:
            nonlocal sent
            put(robot, "odometry", odometry_cdr(state(seq)))
            sent += 1

        wait_until(lambda: odometry(1) or states.get() is not None,
                   "a first odometry through the bridge")
        wait_until(lambda: stack.publish(topics.vehicle_setpoint(ROBOT), setpoint(0))
                   or bool(robot.heard.get("setpoint")), "a first set-point on the ROS topic")
        armed.set()
        wait_until(lambda: odometry(2) or holding.is_set(),
                   "the inbound worker holding an odometry")
        # the odometry put just before the worker took one may still be on its way: a test
        # that counts the queue from here must not see it arrive later
        wait_until(lambda: status(bridge)["odometry"]["received"] == sent,
                   "every odometry put so far at the bridge")
        try:
            yield Rig(bridge, stack, robot, gate.set)
        finally:
            gate.set()


def test_set_points_go_out_while_a_flood_fills_the_stuck_inbound_side(
        stuck: Rig) -> None:
    bridge, stack, robot = stuck.bridge, stuck.stack, stuck.robot
    good = odometry_cdr(state(4))
    before = queues(bridge)  # the odometry the fixture put past the one held, if any
    for i in range(1, SETPOINTS + 1):
        for _ in range(FLOOD // SETPOINTS):
            put(robot, "odometry", NAN_ODOMETRY)  # queued
            put(robot, "detections", CUT_DETECTIONS)  # queued
            put(robot, "odometry", GARBAGE)  # refused at the callback
            put(robot, "odometry", good, attachment=False)  # refused at the callback
        stack.publish(topics.vehicle_setpoint(ROBOT), setpoint(i))
    wanted = {round(setpoint(i).t, 3) for i in range(1, SETPOINTS + 1)}
    wait_until(lambda: wanted <= stamps(robot), "every set-point while the inbound side is stuck")
    # refused at the callback, so counted while the worker is still stuck; the last
    # counted came after every sample queued (one link's callbacks run in order)
    wait_until(lambda: status(bridge)["odometry"]["dropped"].get("attachment") == FLOOD
               and status(bridge)["odometry"]["dropped"].get("cdr") == FLOOD,
               "the attachment-less and garbage samples counted at the callback")
    lanes = queues(bridge)
    for role in ("odometry", "detections"):
        lane = lanes[role]
        assert lane["direction"] == "in"
        assert 0 < lane["items"] <= lane["max_items"] < FLOOD, lane
        assert lane["peak_bytes"] <= lane["max_bytes"], lane
        # the queue held only what needs decoding, the newest: the rest went oldest first
        assert status(bridge)[role]["dropped"]["queue"] == \
            FLOOD + before[role]["items"] - lane["items"], (role, status(bridge)[role])
    assert lanes["setpoint"]["direction"] == "out"
    assert "queue" not in status(bridge)["setpoint"]["dropped"]
    stuck.release()
    states = stack.latest(topics.vehicle_state(ROBOT), VehicleState)
    # put once, so that it pushes at most one queued NaN out: a put every poll would push
    # out one per poll for as long as the worker decodes the queue, however slow it is
    put(robot, "odometry", odometry_cdr(state(5, (7.0, 0.0, 1.0))))
    wait_until(lambda: (got := states.get()) is not None
               and got.message.position == (7.0, 0.0, 1.0), "a good odometry after the flood")
    wait_until(lambda: status(bridge)["detections"]["dropped"].get("cdr")
               == lanes["detections"]["items"], "the queued detections decoded")
    # each queued odometry with a NaN decoded, or pushed out by an older (the ones the
    # fixture put past the held one) or a newer (the good one, just after the release)
    dropped = status(bridge)["odometry"]["dropped"]
    assert dropped["non_finite"] + dropped["queue"] == FLOOD + before["odometry"]["items"]
    assert dropped["non_finite"] >= lanes["odometry"]["items"] - 1, dropped


def test_a_flood_on_one_ros_topic_leaves_another_topics_queued_odometry_alone(
        stuck: Rig) -> None:
    bridge, stack, robot = stuck.bridge, stuck.stack, stuck.robot
    seen: list[tuple[float, float, float]] = []
    stack.each(topics.vehicle_state(ROBOT), VehicleState,
               lambda got: seen.append(got.message.position))
    goods = [(10.0 + i, 0.0, 1.0) for i in range(20)]
    for i, position in enumerate(goods):  # queued before the flood: the oldest there is
        put(robot, "odometry", odometry_cdr(state(10 + i, position)))
    for _ in range(FLOOD):
        put(robot, "detections", CUT_DETECTIONS)
        put(robot, "scene", NOT_UTF8)
    wait_until(lambda: status(bridge)["detections"]["received"] >= FLOOD
               and status(bridge)["scene"]["received"] >= FLOOD, "the flood at the bridge")
    stuck.release()
    wait_until(lambda: set(goods) <= set(seen), "every good odometry queued before the flood")
    assert "queue" not in status(bridge)["odometry"]["dropped"]
    wait_until(lambda: all(status(bridge)[role]["dropped"].get("queue", 0) >= FLOOD - IN_ITEMS
                           for role in ("detections", "scene")), "the flood's queues' drops")


def test_oversized_samples_are_refused_uncopied_and_the_queues_stay_under_their_bytes(
        stuck: Rig) -> None:
    bridge, robot = stuck.bridge, stuck.robot
    big = b"\x00\x01\x00\x00" + b"x" * 900_000  # under the router's 1 MiB, over every topic's
    for _ in range(30):
        put(robot, "scene", big)
        put(robot, "odometry", big)
        put(robot, "detections", big)
    wait_until(lambda: all(status(bridge)[r]["dropped"].get("size") == 30
                           for r in ("scene", "odometry", "detections")),
               "the oversized samples counted at the callback")
    assert queues(bridge)["scene"]["items"] == 0
    # each as large as the scene topic takes, many more than its queue's bytes hold
    text = string_cdr("a" * 60_000)
    for _ in range(200):
        put(robot, "scene", text)
    wait_until(lambda: status(bridge)["scene"]["dropped"].get("queue", 0)
               + queues(bridge)["scene"]["items"] == 200, "the large scenes queued or dropped")
    lane = queues(bridge)["scene"]
    assert lane["peak_bytes"] <= lane["max_bytes"] < 200 * len(text), lane
    assert lane["bytes"] == lane["items"] * len(text), lane
    assert status(bridge)["scene"]["dropped"]["queue"] == 200 - lane["items"]
    total = sum(q["max_bytes"] for q in queues(bridge).values() if q["direction"] == "in")
    assert total <= 16 * 1024 * 1024  # what the inbound side may hold, all topics together
    metrics = bridge.get("/metrics").text
    assert 'aesop_ros2_dropped_total{reason="size",topic="/camera/scene"} 30.0' in metrics
