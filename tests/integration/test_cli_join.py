"""``aesop record`` and ``aesop replay`` as a newcomer types them, against aesop up's
router with no user and against an endpoint where nothing listens (issue 44): each used to
wait silently for ever (record: "0 messages" once a second; replay: the whole recording
published into nothing, for ever with ``--loop``). Now each exits 2 naming the endpoint,
the user and the line that logs in, as ``aesop watch`` does (tests/integration/
test_dashboard_watch.py), and leaves no file behind. So does ``aesop demo --attach``, before
it builds anything."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from shared.messages import Observation
from shared.process import free_port
from tests.zenoh_peers import aesop_router
from tools.recording.mcapfile import FlightWriter, read_messages

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]


@pytest.fixture
def hub(tmp_path: Path) -> Iterator[str]:
    with aesop_router(tmp_path / "zenoh") as endpoint:
        yield endpoint


@pytest.fixture
def flight(tmp_path: Path) -> Path:
    path = tmp_path / "flight.mcap"
    writer = FlightWriter(path)
    for seq in range(20):
        writer.add("aesop/robot0/observation", Observation(seq=seq, text="a red box").encode(),
                   1_763_000_000_000_000_000 + seq * 100_000_000)
    writer.close()
    return path


def aesop(*args: str, env: dict[str, str] | None = None,
          cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("AESOP_")}
    return subprocess.run([sys.executable, "-m", "tools.cli", *args], capture_output=True,
                          text=True, env=clean | (env or {}), stdin=subprocess.DEVNULL,
                          cwd=cwd, timeout=60)  # a command that still hung fails here


def assert_refused(done: subprocess.CompletedProcess[str], endpoint: str, user: str,
                   command: str) -> None:
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    assert f"cannot join the Zenoh network {user}" in done.stderr
    assert f"the router at {endpoint} refused this session or did not answer" in done.stderr
    assert f"aesop {command} --connect" in done.stderr
    assert done.stdout == ""


@pytest.mark.parametrize("where", ["aesop-ups-router", "nothing-listening"])
def test_record_that_cannot_join_exits_2_saying_how(where: str, request: pytest.FixtureRequest,
                                                     tmp_path: Path) -> None:
    endpoint = (request.getfixturevalue("hub") if where == "aesop-ups-router"
                else f"tcp/127.0.0.1:{free_port()}")
    out = tmp_path / "flight.mcap"
    done = aesop("record", "--out", str(out), "--connect", endpoint, cwd=tmp_path)
    assert_refused(done, endpoint, "with no user (AESOP_ZENOH_USER unset)", "record")
    assert "AESOP_ZENOH_USER=monitor" in done.stderr  # record reads: the read-only user
    assert not out.exists()


def test_record_with_a_wrong_password_is_refused_naming_its_user(hub: str,
                                                                 tmp_path: Path) -> None:
    done = aesop("record", "--out", str(tmp_path / "x.mcap"), "--connect", hub,
                 env={"AESOP_ZENOH_MODE": "client", "AESOP_ZENOH_USER": "monitor",
                      "AESOP_ZENOH_PASSWORD": "not-the-password"})
    assert_refused(done, hub, "as user monitor", "record")


@pytest.mark.parametrize("where", ["aesop-ups-router", "nothing-listening"])
@pytest.mark.parametrize("loop", [[], ["--loop"]], ids=["once", "loop"])
def test_replay_that_cannot_join_exits_2_saying_how(where: str, loop: list[str], flight: Path,
                                                     request: pytest.FixtureRequest) -> None:
    endpoint = (request.getfixturevalue("hub") if where == "aesop-ups-router"
                else f"tcp/127.0.0.1:{free_port()}")
    done = aesop("replay", str(flight), "--connect", endpoint, *loop)
    assert_refused(done, endpoint, "with no user (AESOP_ZENOH_USER unset)", "replay")
    # replay puts: a robot's user may put its observations and events (the monitor nothing)
    assert "AESOP_ZENOH_USER=robot-robot0" in done.stderr
    assert "replayed" not in done.stderr


def test_record_as_the_monitor_joins_aesop_ups_router(hub: str, tmp_path: Path) -> None:
    """The check lets the line docs/recordings.md gives through: the recorder joins, and
    a robot's observation put at the router is in the file."""
    import signal
    import threading

    from shared import topics
    from shared.bus import Bus
    from shared.settings import BusSettings
    from tests.zenoh_peers import wait_until

    out = tmp_path / "flight.mcap"
    env = {k: v for k, v in os.environ.items() if not k.startswith("AESOP_")} | {
        "AESOP_ZENOH_MODE": "client", "AESOP_ZENOH_USER": "monitor",
        "AESOP_ZENOH_PASSWORD_FILE": str(tmp_path / "zenoh" / "monitor.password")}
    proc = subprocess.Popen([sys.executable, "-m", "tools.cli", "record", "--out", str(out),
                             "--connect", hub, "--topics", "observation"], env=env,
                            stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
    lines: list[str] = []

    def read() -> None:
        assert proc.stderr is not None
        lines.extend(line.rstrip() for line in proc.stderr)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        robot = BusSettings(zenoh_mode="client", zenoh_connect=[hub], zenoh_user="robot-robot0",
                            zenoh_password_file=tmp_path / "zenoh" / "robot-robot0.password")
        with Bus.open(robot, "robot") as bus:
            def recorded() -> bool:
                bus.publish(topics.observation("robot0"),
                            Observation(robot="robot0", seq=1, text="a red box"))
                return any(line.startswith("recording: ") and not line.startswith(
                    "recording: 0 ") for line in lines)

            wait_until(recorded, "the recorder to record an observation", 30.0)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0, lines
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    reader.join(10)
    assert "Traceback" not in "\n".join(lines)
    assert {r.key for r in read_messages(out)} == {"aesop/robot0/observation"}


def test_demo_attach_names_the_service_that_does_not_answer(hub: str, tmp_path: Path) -> None:
    """With no detector at --embedding-url, ``demo --attach`` ended in an httpx traceback
    once the router let its robot in. Now each service it needs is asked first: a usage
    error (2) naming the URL and its flag, before anything is built."""
    (tmp_path / "admin-token").write_text("a-token-of-sixteen-chars\n")
    closed = f"http://127.0.0.1:{free_port()}"
    done = aesop("demo", "--attach", "--data-dir", str(tmp_path), "--connect", hub,
                 "--embedding-url", closed, "--out", str(tmp_path / "report"))
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and "cannot join" not in done.stderr
    assert f"nothing answers at {closed}" in done.stderr and "--embedding-url" in done.stderr
    assert not (tmp_path / "report").exists()


@pytest.mark.parametrize("where", ["aesop-ups-router", "nothing-listening"])
def test_demo_attach_that_cannot_join_exits_2_before_building_its_cache(
        where: str, request: pytest.FixtureRequest, tmp_path: Path) -> None:
    """Before: a traceback (no embedding service here; with one, a refused client's once the
    scene cache was built); now the robot's user is checked first (no service is asked)."""
    endpoint = (request.getfixturevalue("hub") if where == "aesop-ups-router"
                else f"tcp/127.0.0.1:{free_port()}")
    data = tmp_path / "data"
    (data / "zenoh").mkdir(parents=True)
    (data / "zenoh" / "robot-robot0.password").write_text("not-the-password\n")
    (data / "admin-token").write_text("a-token\n")
    done = aesop("demo", "--attach", "--data-dir", str(data), "--connect", endpoint,
                 "--embedding-url", f"http://127.0.0.1:{free_port()}", "--out",
                 str(tmp_path / "report"))
    assert_refused(done, endpoint, "as user robot-robot0", "demo --attach --data-dir <data-dir>")
    assert not (tmp_path / "report").exists()
