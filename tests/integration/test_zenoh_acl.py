"""The hub of ``aesop up`` authenticates every session and applies the stack's ACL
(issue 14: identities were self-declared, anything reaching the router port could
publish ``is_anomaly: false``, one robot could publish every robot's observations, and
there was no message-size cap). A real hub process and real client sessions."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from shared import topics
from shared.bus import Bus
from shared.messages import (
    AnomalyVerdict,
    Event,
    Mode,
    Observation,
    VehicleClock,
    VehicleSetpoint,
    VehicleState,
)
from shared.process import free_port
from shared.settings import BusSettings
from tools.stack.acl import (
    control_user,
    new_passwords,
    robot_user,
    users_of,
    write_credentials,
)

pytestmark = pytest.mark.timeout(90)

ROBOTS = ("robot-a", "robot-b")


class Hub:
    def __init__(self, folder: Path) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.passwords = new_passwords(users_of(ROBOTS))
        write_credentials(folder, self.passwords)
        argv = [sys.executable, "-m", "tools.stack.router", "--listen", self.endpoint,
                "--users", str(folder / "users.txt"), "--max-message-bytes", "100000"]
        for robot in ROBOTS:
            argv += ["--robot", robot]
        self.proc = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True)
        assert self.proc.stderr is not None
        line = self.proc.stderr.readline()  # printed once it listens
        assert "listening" in line, line

    def settings(self, user: str, password: str | None = None) -> BusSettings:
        return BusSettings(zenoh_mode="client", zenoh_connect=[self.endpoint], zenoh_user=user,
                           zenoh_password=password or self.passwords[user])

    def session(self, user: str) -> Bus:
        return Bus.open(self.settings(user), user)


@pytest.fixture
def hub(tmp_path: Path) -> Iterator[Hub]:
    hub = Hub(tmp_path / "zenoh")
    yield hub
    hub.proc.terminate()
    hub.proc.wait(10)


class Heard:
    """What a monitor session receives on a key expression (raw samples)."""

    def __init__(self, bus: Bus, key_expr: str) -> None:
        self.keys: list[str] = []
        self.sizes: list[int] = []
        self.payloads: list[bytes] = []
        self._lock = threading.Lock()
        self._sub = bus.session.declare_subscriber(key_expr, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.keys.append(str(sample.key_expr))
            self.sizes.append(len(sample.payload.to_bytes()))
            self.payloads.append(sample.payload.to_bytes())

    def clear(self) -> None:
        with self._lock:
            self.keys.clear()
            self.sizes.clear()
            self.payloads.clear()

    def seqs(self, key: str) -> list[int]:
        """The seqs of the observations heard on ``key``."""
        with self._lock:
            heard = list(zip(self.keys, self.payloads, strict=True))
        return [Observation.decode(p).seq for k, p in heard if k == key]

    def senders(self) -> set[str]:
        """Which verdicts came: the detector's say ``is_anomaly: true`` here."""
        return {"embedding" if AnomalyVerdict.decode(p).is_anomaly else "someone else"
                for p in self.payloads}


def verdict(robot: str, anomaly: bool) -> AnomalyVerdict:
    return AnomalyVerdict(robot=robot, seq=1, score=0.1, threshold=0.5, is_anomaly=anomaly, k=1,
                          model="m", cache="c", cache_version=1, latency_ms=1.0)


def observation(robot: str, seq: int) -> Observation:
    return Observation(robot=robot, seq=seq, text="a red box on the ground")


def test_a_wrong_password_opens_no_session(hub: Hub) -> None:
    for user, password in (("embedding", "not-the-password"), ("intruder", "whatever")):
        with pytest.raises(zenoh.ZError):
            Bus.open(hub.settings(user, password), "embedding")
    with pytest.raises(zenoh.ZError):  # and no credentials at all
        Bus.open(BusSettings(zenoh_mode="client", zenoh_connect=[hub.endpoint]), "embedding")


def routed(publish: Callable[[], None], heard: Heard, what: str) -> None:
    """Publish until ``heard`` has one more message (routes and declarations settle)."""
    before = len(heard.keys)
    deadline = time.monotonic() + 20
    while len(heard.keys) == before:
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        publish()
        time.sleep(0.1)
    time.sleep(0.2)  # anything sent just before has arrived by now


def test_only_the_detector_may_publish_verdicts(hub: Hub) -> None:
    with hub.session("monitor") as monitor, hub.session("embedding") as embedding, \
            hub.session(robot_user("robot-a")) as robot, hub.session("dashboard") as dashboard:
        heard = Heard(monitor, "aesop/*/anomaly")
        key = "aesop/robot-a/anomaly"
        routed(lambda: embedding.publish(key, verdict("robot-a", True)), heard, "a verdict")
        heard.clear()
        robot.publish(key, verdict("robot-a", anomaly=False))
        dashboard.publish(key, verdict("robot-a", anomaly=False))
        routed(lambda: embedding.publish(key, verdict("robot-a", True)), heard, "a verdict")
    assert set(heard.keys) == {key} and len(heard.keys) >= 1
    assert all(size > 0 for size in heard.sizes)
    assert heard.senders() == {"embedding"}


def test_a_robot_publishes_only_its_own_observations(hub: Hub) -> None:
    with hub.session("monitor") as monitor, hub.session(robot_user("robot-a")) as robot_a:
        heard = Heard(monitor, "aesop/*/observation")
        own = "aesop/robot-a/observation"
        routed(lambda: robot_a.publish(own, observation("robot-a", 1)), heard, "its own")
        robot_a.publish("aesop/robot-b/observation", observation("robot-b", 2))
        routed(lambda: robot_a.publish(own, observation("robot-a", 3)), heard, "its own")
    assert "aesop/robot-b/observation" not in heard.keys


def test_a_message_past_the_size_cap_is_dropped_and_the_session_goes_on(hub: Hub) -> None:
    with hub.session("monitor") as monitor, hub.session(robot_user("robot-a")) as robot_a:
        heard = Heard(monitor, "aesop/robot-a/observation")
        own = "aesop/robot-a/observation"
        routed(lambda: robot_a.publish(own, observation("robot-a", 1)), heard, "a message")
        robot_a.session.put(own, b"x" * 200_000)
        routed(lambda: robot_a.publish(own, observation("robot-a", 2)), heard,
               "a small message after the big one")
    assert max(heard.sizes) < 100_000


def test_aesop_watch_without_credentials_says_what_it_needs(hub: Hub) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("AESOP_")}
    run = subprocess.run([sys.executable, "-m", "tools.cli", "watch", "--connect",
                          hub.endpoint], env={**env, "AESOP_ZENOH_MODE": "client"},
                         capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert run.returncode != 0
    assert "AESOP_ZENOH_USER" in run.stderr and "Traceback" not in run.stderr, run.stderr


def vehicle_state(robot: str, seq: int) -> VehicleState:
    return VehicleState(robot=robot, seq=seq, position=(0.0, 0.0, 1.0), velocity=(0.0, 0.0, 0.0))


def setpoint(robot: str, seq: int) -> VehicleSetpoint:
    return VehicleSetpoint(robot=robot, seq=seq, state_seq=1, state_stamp=1.0, t=1.0,
                           valid_until=1.15, mode=Mode.NOMINAL, acceleration=(0.0, 0.0, 0.0),
                           position=(0.0, 0.0, 1.0), velocity=(0.0, 0.0, 0.0))


def test_a_robot_publishes_only_its_own_vehicle_state(hub: Hub) -> None:
    with hub.session("monitor") as monitor, hub.session(robot_user("robot-a")) as robot_a, \
            hub.session(control_user("robot-a")) as control:
        heard = Heard(monitor, "aesop/*/vehicle/state")
        own = topics.vehicle_state("robot-a")
        routed(lambda: robot_a.publish(own, vehicle_state("robot-a", 1)), heard, "its own")
        robot_a.publish(topics.vehicle_state("robot-b"), vehicle_state("robot-b", 2))
        control.publish(own, vehicle_state("robot-a", 3))  # control reads states, never writes
        routed(lambda: robot_a.publish(own, vehicle_state("robot-a", 4)), heard, "its own")
    assert set(heard.keys) == {own}
    assert 3 not in {VehicleState.decode(p).seq for p in heard.payloads}


def test_only_control_publishes_set_points(hub: Hub) -> None:
    with hub.session("monitor") as monitor, hub.session(control_user("robot-a")) as control, \
            hub.session(robot_user("robot-a")) as robot_a, hub.session("dashboard") as dashboard:
        heard = Heard(monitor, "aesop/*/vehicle/setpoint")
        key = topics.vehicle_setpoint("robot-a")
        routed(lambda: control.publish(key, setpoint("robot-a", 1)), heard, "a set-point")
        robot_a.publish(key, setpoint("robot-a", 1000))
        dashboard.publish(key, setpoint("robot-a", 1001))
        routed(lambda: control.publish(key, setpoint("robot-a", 2)), heard, "a set-point")
    assert max(VehicleSetpoint.decode(p).seq for p in heard.payloads) < 1000


def ask_clock(bus: Bus, robot: str) -> list[float]:
    """The vehicle clock readings one query on ``robot``'s clock brings back."""
    return [got.message.stamp for got in bus.ask(topics.vehicle_clock(robot), VehicleClock,
                                                 timeout=1.0)]


def test_control_asks_a_robot_its_clock_and_no_one_else_may_answer_or_ask(hub: Hub) -> None:
    with hub.session(control_user("robot-a")) as control, \
            hub.session(robot_user("robot-a")) as robot_a, \
            hub.session(robot_user("robot-b")) as robot_b, \
            hub.session("dashboard") as dashboard:
        robot_a.answer(topics.vehicle_clock("robot-a"),
                       lambda: VehicleClock(robot="robot-a", stamp=1000.0))
        robot_b.answer(topics.vehicle_clock("robot-a"),  # an impostor for robot-a's clock
                       lambda: VehicleClock(robot="robot-a", stamp=2000.0))
        deadline = time.monotonic() + 20
        while not (got := ask_clock(control, "robot-a")):
            assert time.monotonic() < deadline, "no answer to control's clock query"
            time.sleep(0.1)
        assert set(got) == {1000.0}
        assert ask_clock(dashboard, "robot-a") == []


def test_a_robot_flooding_its_observations_is_cut_to_its_rate_at_the_hub(hub: Hub) -> None:
    """Issue 26, finding 1, at the router: robot-a's flood at about 2 kHz reaches the
    subscribers at the hub's per-session observation rate; robot-b, on its own session,
    loses nothing."""
    with hub.session("monitor") as monitor, hub.session(robot_user("robot-a")) as robot_a, \
            hub.session(robot_user("robot-b")) as robot_b:
        heard = Heard(monitor, "aesop/*/observation")
        a, b = "aesop/robot-a/observation", "aesop/robot-b/observation"
        routed(lambda: robot_b.publish(b, observation("robot-b", 0)), heard, "robot-b")
        time.sleep(1.0)  # a second of quiet: the hub's window for robot-a starts afresh
        heard.clear()
        sent_b = 0
        for flood in range(1, 4001):  # as fast as this thread can, about 2 kHz
            robot_a.publish(a, observation("robot-a", flood))
            if flood % 200 == 0:  # robot-b about every 100 ms meanwhile
                sent_b += 1
                robot_b.publish(b, observation("robot-b", sent_b))
            time.sleep(0.0005)
        while 9999 not in heard.seqs(b):  # a probe after them: robot-b's are all in by then
            robot_b.publish(b, observation("robot-b", 9999))
            time.sleep(0.1)
    assert sorted(set(heard.seqs(b)) - {9999}) == list(range(1, sent_b + 1))  # none lost
    # robot-a's flood, cut at the hub: at 50 a second, most of 4,000 never arrive
    assert heard.keys.count(a) < 4000 // 4


def test_each_publisher_puts_events_on_its_own_key_only(hub: Hub) -> None:
    """Issue 26, finding 5: robot-a could put ``aesop/robot-a/event``, the key embedding
    and control publish their events on, and so forge theirs."""
    with hub.session("monitor") as monitor, hub.session(robot_user("robot-a")) as robot_a, \
            hub.session("embedding") as embedding:
        heard = Heard(monitor, "aesop/*/event/**")
        own = topics.event("robot-a", "robot")
        detector = topics.event("robot-a", "embedding")
        said = Event(robot="robot-a", source="embedding", kind="proposal_proposed")
        routed(lambda: robot_a.publish(own, said), heard, "the robot's own events")
        robot_a.publish(detector, said)  # the detector's key: refused
        robot_a.publish(topics.event("robot-a", "control"), said)
        robot_a.publish("aesop/robot-a/event", said)  # the old shared key: nobody's
        routed(lambda: embedding.publish(detector, said), heard, "the detector's events")
        embedding.publish(topics.event("robot-a", "control"), said)  # not its key either
        routed(lambda: robot_a.publish(own, said), heard, "the robot's own events again")
    assert set(heard.keys) == {own, detector}
    assert heard.keys.count(detector) >= 1


def test_a_robots_control_loop_cannot_put_another_robots_set_points(hub: Hub) -> None:
    """Issue 41 (and 43, finding 1): every robot's control loop logged in as one user
    ``control``; with it, one forged set-point moved another robot's vehicle. Each loop is
    now ``control-<robot>`` and may put its own robot's keys only."""
    with hub.session("monitor") as monitor, \
            hub.session(control_user("robot-a")) as control_a, \
            hub.session(control_user("robot-b")) as control_b:
        heard = Heard(monitor, "aesop/robot-b/**")
        key = topics.vehicle_setpoint("robot-b")
        routed(lambda: control_b.publish(key, setpoint("robot-b", 1)), heard, "b's set-point")
        control_a.publish(key, setpoint("robot-b", 2**62))  # robot-a's loop: refused
        control_a.publish(topics.plan("robot-b"), setpoint("robot-b", 2**62))
        control_a.publish(topics.event("robot-b", "control"), setpoint("robot-b", 2**62))
        routed(lambda: control_b.publish(key, setpoint("robot-b", 2)), heard, "b's set-point")
    assert set(heard.keys) == {key}
    assert max(VehicleSetpoint.decode(p).seq for p in heard.payloads) < 2**62


def test_a_robots_sessions_receive_only_its_own_robots_messages(hub: Hub) -> None:
    """A robot's credentials cannot reach another robot's keys, reading included: robot-a's
    vehicle and control loop hear robot-a's verdicts, never robot-b's set-points or
    verdicts; the monitor hears both."""
    with hub.session("monitor") as monitor, hub.session("embedding") as embedding, \
            hub.session(robot_user("robot-a")) as robot_a, \
            hub.session(control_user("robot-a")) as control_a, \
            hub.session(control_user("robot-b")) as control_b:
        everything = Heard(monitor, "aesop/**")
        heard = {name: Heard(bus, "aesop/**") for name, bus in
                 (("robot", robot_a), ("control", control_a))}
        own, other = topics.anomaly("robot-a"), topics.anomaly("robot-b")
        for who in heard.values():
            routed(lambda: embedding.publish(own, verdict("robot-a", True)), who, "a's verdict")
        embedding.publish(other, verdict("robot-b", True))
        control_b.publish(topics.vehicle_setpoint("robot-b"), setpoint("robot-b", 1))
        routed(lambda: embedding.publish(other, verdict("robot-b", True)), everything,
               "b's verdict at the monitor")
        for who in heard.values():
            routed(lambda: embedding.publish(own, verdict("robot-a", True)), who, "a's verdict")
    assert other in everything.keys
    for name, who in heard.items():
        assert {k for k in who.keys if k.startswith("aesop/robot-b/")} == set(), name
