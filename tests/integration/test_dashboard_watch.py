"""`aesop watch` as a real process on a real Zenoh link: the demo flight as terminal lines,
and Ctrl-C (SIGINT) ends it with status 0."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from shared import topics
from shared.bus import Bus
from shared.messages import Event
from shared.process import free_port
from shared.settings import BusSettings
from tests.e2e.demo_flight import Flight
from tests.zenoh_peers import aesop_router, wait_until

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

ROBOT = "watched"


class Lines:
    """Every stdout line of ``proc``, read on a thread."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self._lines: list[str] = []
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            with self._lock:
                self._lines.append(line.rstrip("\n"))

    def all(self) -> list[str]:
        with self._lock:
            return list(self._lines)

    def having(self, *parts: str) -> list[str]:
        return [line for line in self.all() if all(p in line for p in parts)]


# started as a shell's background job starts it: SIGINT ignored from the start
IGNORING_SIGINT = ["bash", "-c", 'trap "" INT; exec "$@"', "bash"]


@pytest.mark.parametrize("launcher", [[], IGNORING_SIGINT], ids=["foreground", "background"])
def test_watch_prints_the_flight_and_exits_0_on_ctrl_c(
        listener: Bus, endpoint: str, tmp_path: Path, launcher: list[str]) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("AESOP_ZENOH")}
    env["PYTHONFAULTHANDLER"] = "1"  # SIGABRT then writes every thread's stack to watch.err
    with open(tmp_path / "watch.err", "w") as err:
        proc = subprocess.Popen(
            [*launcher, sys.executable, "-m", "tools.cli", "watch", "--robot", ROBOT,
             "--connect", endpoint, "--state-every", "0.5"],
            stdout=subprocess.PIPE, stderr=err, stdin=subprocess.DEVNULL, text=True, env=env)
    try:
        lines = Lines(proc)

        def greeted() -> bool:
            listener.publish(topics.event(ROBOT, "test"), Event(robot=ROBOT, source="test",
                                                        kind="hello"))
            return bool(lines.having("event", "[info] test/hello"))

        wait_until(greeted, "watch to follow the bus", 20.0)
        Flight(listener, ROBOT).fly(period_s=0.02)
        wait_until(lambda: bool(lines.having("state", "recovering", "y=3")), "recovering",
                   15.0)
        assert lines.having("health", "listener alive")
        assert lines.having("anomaly", "ANOMALY seq=20 score=")
        assert lines.having("anomaly", "nominal again seq=30")
        assert lines.having("request", 'K=1.50 s "a person is lying on the landing pad')
        assert lines.having("decision", "y=3 rooftop (source=llm, 870 ms)")
        assert lines.having("event", "[alarm] control/mode_change: anomaly_pending -> "
                                     "recovering (y=3)")
        states = lines.having(" state ")
        assert 3 <= len(states) < 60  # throttled, but every mode change shows
        assert not lines.having("plan")
        proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGABRT)
            proc.wait(10)
            stacks = (tmp_path / "watch.err").read_text()[-8000:]
            raise AssertionError(f"aesop watch did not stop on SIGINT; its threads:\n{stacks}"
                                 ) from None
        assert code == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert "Traceback" not in (tmp_path / "watch.err").read_text()


def test_watch_all_follows_every_robot_of_a_fleet(listener: Bus, endpoint: str,
                                                  tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("AESOP_ZENOH")}
    with open(tmp_path / "watch.err", "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "tools.cli", "watch", "--robot", "all", "--connect",
             endpoint], stdout=subprocess.PIPE, stderr=err, stdin=subprocess.DEVNULL,
            text=True, env=env)
    try:
        lines = Lines(proc)

        def greeted() -> bool:
            for robot in ("drone1", "rover2"):
                listener.publish(topics.event(robot, "test"), Event(robot=robot, source="test",
                                                                    kind="hello"))
            return all(lines.having(f" {robot} ", "[info] test/hello")
                       for robot in ("drone1", "rover2"))

        wait_until(greeted, "watch to follow both robots", 20.0)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert "every robot" in (tmp_path / "watch.err").read_text()


@pytest.fixture
def hub(tmp_path: Path) -> Iterator[str]:
    """aesop up's router (users and passwords under ``tmp_path/zenoh``): its endpoint."""
    with aesop_router(tmp_path / "zenoh", ROBOT) as endpoint:
        yield endpoint


@pytest.mark.parametrize("login", [{}, {"AESOP_ZENOH_USER": "monitor",
                                         "AESOP_ZENOH_PASSWORD": "not-the-password"}],
                         ids=["no-user", "wrong-password"])
def test_watch_refused_by_aesop_ups_router_says_how_to_log_in(
        hub: str, login: dict[str, str]) -> None:
    # docs/dashboard.md's line as a newcomer types it: it used to wait silently for ever
    env = {k: v for k, v in os.environ.items() if not k.startswith("AESOP_ZENOH")} | login
    done = subprocess.run([sys.executable, "-m", "tools.cli", "watch", "--connect", hub],
                          capture_output=True, text=True, env=env, stdin=subprocess.DEVNULL,
                          timeout=40)  # a watch that still hung fails here
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    assert f"the router at {hub} refused this session or did not answer" in done.stderr
    assert ("AESOP_ZENOH_MODE=client AESOP_ZENOH_USER=monitor "
            "AESOP_ZENOH_PASSWORD_FILE=<data-dir>/zenoh/monitor.password") in done.stderr
    assert done.stdout == ""


def test_watch_as_the_monitor_joins_aesop_ups_router(hub: str, tmp_path: Path) -> None:
    password_file = tmp_path / "zenoh" / "monitor.password"
    env = {k: v for k, v in os.environ.items() if not k.startswith("AESOP_ZENOH")} | {
        "AESOP_ZENOH_MODE": "client", "AESOP_ZENOH_USER": "monitor",
        "AESOP_ZENOH_PASSWORD_FILE": str(password_file)}
    with open(tmp_path / "watch.err", "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "tools.cli", "watch", "--robot", ROBOT,
                                 "--connect", hub], stdout=subprocess.PIPE, stderr=err,
                                stdin=subprocess.DEVNULL, text=True, env=env)
    try:
        lines = Lines(proc)
        with Bus.open(BusSettings(zenoh_mode="client", zenoh_connect=[hub],
                                  zenoh_user="embedding",
                                  zenoh_password_file=tmp_path / "zenoh" / "embedding.password"),
                      "embedding") as embedding:
            def greeted() -> bool:
                embedding.publish(topics.event(ROBOT, "embedding"),
                                  Event(robot=ROBOT, source="embedding", kind="hello"))
                return bool(lines.having("event", "embedding/hello"))

            wait_until(greeted, "watch to follow the hub", 20.0)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert "Traceback" not in (tmp_path / "watch.err").read_text()


@pytest.mark.parametrize("mode", ["peer", "client"])
def test_watch_joins_when_any_of_its_endpoints_lets_it_in(hub: str, tmp_path: Path,
                                                          mode: str) -> None:
    from tools.commands import joined

    joined(BusSettings(zenoh_mode=mode, zenoh_connect=[f"tcp/127.0.0.1:{free_port()}", hub],
                       zenoh_user="monitor",
                       zenoh_password_file=tmp_path / "zenoh" / "monitor.password"), "watch")
