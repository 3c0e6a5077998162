"""A server's router and two robots' own routers linked to it over mutual TLS (issue 41):
real router processes (``python -m tools.stack.router --role server | robot``) with the
certificates ``aesop zenoh certs`` makes. Each robot's link is one subject, its certificate's
common name, at the server: it may put its own robot's keys and nothing else, and it hears
only its own robot's messages; a robot's own router is open to the robot's processes."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from shared import topics
from shared.bus import Bus
from shared.messages import AnomalyVerdict, Mode, Observation, VehicleSetpoint
from shared.process import free_port
from shared.settings import BusSettings
from tools.stack.acl import robot_user, server_users
from tools.stack.certs import write_certs

pytestmark = pytest.mark.timeout(120)

ROBOTS = ("robot-a", "robot-b")


@dataclass
class Site:
    certs: Path
    server: str  # the server router's endpoint
    robots: dict[str, str]  # robot -> its own router's endpoint

    def at_server(self, name: str) -> Bus:
        return Bus.open(BusSettings(
            zenoh_mode="client", zenoh_connect=[self.server], zenoh_tls_ca=self.certs / "ca.pem",
            zenoh_tls_cert=self.certs / f"{name}.pem",
            zenoh_tls_key=self.certs / f"{name}-key.pem"), name)

    def on_robot(self, robot: str) -> Bus:
        return Bus.open(BusSettings(zenoh_mode="client", zenoh_connect=[self.robots[robot]]),
                        "control")


def _router(argv: list[str]) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-m", "tools.stack.router", *argv],
                            stderr=subprocess.PIPE, text=True)
    assert proc.stderr is not None
    line = proc.stderr.readline()  # printed once it listens
    assert "listening" in line, line
    return proc


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    certs = tmp_path_factory.mktemp("certs")
    write_certs(certs, robots=ROBOTS, services=server_users())
    server = f"tls/127.0.0.1:{free_port()}"
    procs = [_router(["--role", "server", "--tls", str(certs), "--listen", server,
                      *(a for r in ROBOTS for a in ("--linked", r))])]
    robots = {r: f"tcp/127.0.0.1:{free_port()}" for r in ROBOTS}
    for robot, endpoint in robots.items():
        procs.append(_router(["--role", "robot", "--robot", robot, "--listen", endpoint,
                              "--connect", server,
                              "--tls", str(certs / robot_user(robot))]))
    try:
        yield Site(certs, server, robots)
    finally:
        for proc in procs:
            proc.terminate()
            proc.wait(10)


class Heard:
    """The keys (and payloads) a session receives on ``aesop/**``."""

    def __init__(self, bus: Bus) -> None:
        self.got: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()
        self._sub = bus.session.declare_subscriber("aesop/**", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.got.append((str(sample.key_expr), sample.payload.to_bytes()))

    def heard(self) -> set[str]:
        with self._lock:
            return {k for k, _ in self.got}

    def count(self) -> int:
        with self._lock:
            return len(self.got)


def routed(publish: Callable[[], None], heard: Heard, what: str) -> None:
    """Publish until ``heard`` has one more message (the routes settle); anything sent
    just before has arrived once it has."""
    before = heard.count()
    deadline = time.monotonic() + 30
    while heard.count() == before:
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        publish()
        time.sleep(0.1)
    time.sleep(0.3)


def setpoint(robot: str, seq: int) -> VehicleSetpoint:
    return VehicleSetpoint(robot=robot, seq=seq, state_seq=1, state_stamp=1.0, t=1e6,
                           valid_until=1e6 + 0.15, mode=Mode.NOMINAL,
                           acceleration=(0.0, 0.0, 0.0), position=(0.0, 0.0, 1.0),
                           velocity=(0.0, 0.0, 0.0))


def verdict(robot: str) -> AnomalyVerdict:
    return AnomalyVerdict(robot=robot, seq=1, score=0.1, threshold=0.5, is_anomaly=False, k=1,
                          model="m", cache="c", cache_version=1, latency_ms=1.0)


def test_a_robots_certificate_reaches_only_its_own_keys(site: Site) -> None:
    """robot-a's processes (its router open to them) forge robot-b's set-point (seq 2^62,
    a far-future t, as the review did with the shared control user), robot-b's observation
    and a verdict for themselves: none leaves robot-a; its own observation does."""
    with site.at_server("monitor") as monitor, site.on_robot("robot-a") as on_a, \
            site.on_robot("robot-b") as on_b:
        server, at_b = Heard(monitor), Heard(on_b)
        own = topics.observation("robot-a")
        seen = Observation(robot="robot-a", seq=1, text="a red box on the ground")
        routed(lambda: on_a.publish(own, seen), server, "robot-a's observation at the server")
        routed(lambda: on_b.publish(topics.observation("robot-b"), seen), at_b,
               "robot-b's own traffic on its own router")
        on_a.publish(topics.vehicle_setpoint("robot-b"), setpoint("robot-b", 2**62))
        forged = Observation(robot="robot-b", seq=666, text="robot-a speaking for robot-b")
        on_a.publish(topics.observation("robot-b"), forged)
        on_a.publish(topics.anomaly("robot-a"), verdict("robot-a"))  # the detector's key
        routed(lambda: on_a.publish(own, seen), server, "robot-a's observation again")
    assert own in server.heard()
    assert server.heard() & {topics.vehicle_setpoint("robot-b"), topics.anomaly("robot-a")} \
        == set()
    assert topics.vehicle_setpoint("robot-b") not in at_b.heard()
    assert forged.encode() not in {payload for _, payload in server.got}


def test_a_robot_hears_its_own_verdicts_and_never_another_robots(site: Site) -> None:
    with site.at_server("embedding") as embedding, site.on_robot("robot-a") as on_a:
        at_a = Heard(on_a)
        routed(lambda: embedding.publish(topics.anomaly("robot-a"), verdict("robot-a")), at_a,
               "robot-a's verdict on robot-a")
        embedding.publish(topics.anomaly("robot-b"), verdict("robot-b"))
        routed(lambda: embedding.publish(topics.anomaly("robot-a"), verdict("robot-a")), at_a,
               "robot-a's verdict again")
    assert at_a.heard() == {topics.anomaly("robot-a")}


def test_a_session_without_a_certificate_of_the_ca_opens_nothing_at_the_server(
        site: Site, tmp_path: Path) -> None:
    with pytest.raises(zenoh.ZError):  # no certificate at all
        Bus.open(BusSettings(zenoh_mode="client", zenoh_connect=[site.server],
                             zenoh_tls_ca=site.certs / "ca.pem"), "intruder")
    other = tmp_path / "other"
    write_certs(other, robots=["robot-a"], services=["monitor"])  # the same names, another CA
    with pytest.raises(zenoh.ZError):
        Bus.open(BusSettings(zenoh_mode="client", zenoh_connect=[site.server],
                             zenoh_tls_ca=site.certs / "ca.pem",
                             zenoh_tls_cert=other / "monitor.pem",
                             zenoh_tls_key=other / "monitor-key.pem"), "intruder")
