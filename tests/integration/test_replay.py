"""``aesop replay`` as a user runs it, into a real Zenoh peer (issue 13): the recorded
payloads on their keys in order, the recorded timing scaled (on the test's own clock,
no time measured), only the topics asked for, and over again with ``--loop`` until
Ctrl-C."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from shared import topics
from shared.bus import Bus, zenoh_config
from shared.messages import ControlState, Event, Observation
from shared.process import free_port
from shared.settings import BusSettings
from tools.recording.mcapfile import FlightWriter, read_messages
from tools.recording.record import record
from tools.recording.replay import replay as replay_file

pytestmark = pytest.mark.timeout(120)

T0 = 1_763_000_000_000_000_000
N = 20
PERIOD_NS = 100_000_000  # 10 Hz: the recording spans 1.9 s


@pytest.fixture
def flight(tmp_path: Path) -> Path:
    path = tmp_path / "flight.mcap"
    writer = FlightWriter(path)
    for seq in range(N):
        at = T0 + seq * PERIOD_NS
        writer.add("aesop/robot0/observation",
                   Observation(seq=seq, text=f"a red box, look {seq}").encode(), at)
        writer.add("aesop/robot0/state", ControlState(t=seq * 0.1, x=(0.0,) * 12,
                                                      u=(9.81, 0, 0, 0), mode="nominal"
                                                      ).encode(), at + 1)
    writer.close()
    return path


class Heard:
    """Everything that arrives on ``aesop/**`` at a listening peer, in order."""

    def __init__(self, endpoint: str) -> None:
        self.endpoint = endpoint
        self.got: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()
        self.session = zenoh.open(zenoh_config(BusSettings(zenoh_listen=[endpoint])))
        self.sub = self.session.declare_subscriber("aesop/**", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.got.append((str(sample.key_expr), sample.payload.to_bytes()))

    def count(self) -> int:
        with self._lock:
            return len(self.got)

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


@pytest.fixture
def heard(endpoint: str) -> Iterator[Heard]:
    h = Heard(endpoint)
    yield h
    h.close()


def replay(*args: str) -> subprocess.Popen[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("AESOP_")}
    return subprocess.Popen([sys.executable, "-m", "tools.cli", "replay", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            stdin=subprocess.DEVNULL)


def test_replay_publishes_the_recording_in_order_at_its_pace(flight: Path, endpoint: str,
                                                             heard: Heard) -> None:
    proc = replay(str(flight), "--connect", endpoint, "--speed", "2")
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    recorded = [(r.key, r.data) for r in read_messages(flight)]
    assert heard.got == recorded  # payloads untouched, in order
    assert f"replayed {2 * N} messages" in err


def test_each_message_waits_for_its_recorded_time_scaled(flight: Path, endpoint: str,
                                                         heard: Heard) -> None:
    """The schedule on a clock of the test's own: the waits replay asks for."""
    now, waits = [0.0], []

    def wait(seconds: float) -> bool:
        waits.append(seconds)
        now[0] += seconds
        return False

    done = replay_file(BusSettings(zenoh_connect=[endpoint]), flight, speed=2.0,
                       stop=threading.Event(), say=lambda _: None, clock=lambda: now[0],
                       wait=wait)
    assert done.messages == 2 * N
    # the settling pause, then each message's gap to the one before, halved: 50 ms
    # before each observation but the first, 0.5 ns before the state 1 ns after it
    gaps = [(b.log_time_ns - a.log_time_ns) / 1e9 / 2
            for a, b in itertools.pairwise(read_messages(flight))]
    assert waits == pytest.approx([0.5, *gaps], rel=1e-9, abs=1e-12)
    assert sum(waits) == pytest.approx(0.5 + (N - 1) * PERIOD_NS / 1e9 / 2 + 0.5e-9)


def test_replay_of_some_topics_in_a_loop_until_ctrl_c(flight: Path, endpoint: str,
                                                      heard: Heard) -> None:
    proc = replay(str(flight), "--connect", endpoint, "--speed", "20", "--topics",
                  "observation", "--loop")
    deadline = time.monotonic() + 60
    while heard.count() < 2 * N + 1:  # the second pass has begun
        assert proc.poll() is None, proc.communicate()[1]
        assert time.monotonic() < deadline, heard.count()
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    keys = {key for key, _ in heard.got}
    assert keys == {"aesop/robot0/observation"}
    seqs = [Observation.decode(data).seq for _, data in heard.got]
    assert seqs[:2 * N] == list(range(N)) * 2


def test_an_unknown_topic_is_named(flight: Path) -> None:
    proc = replay(str(flight), "--topics", "nonsense")
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and "nonsense" in err and "Traceback" not in err


def recorded_flight(endpoint: str, listener: Bus, out: Path) -> Path:
    """A flight recorded by ``aesop record``'s recorder from a live peer: observations and
    states, the control loop's alarms and the detector's events, each source on its own
    key (``aesop/<robot>/event/<source>``)."""
    stop, ready, lines = threading.Event(), threading.Event(), []
    thread = threading.Thread(target=record, args=(BusSettings(zenoh_connect=[endpoint]), out),
                              kwargs={"stop": stop, "say": lines.append, "every_s": 0.05,
                                      "ready": ready}, daemon=True)
    thread.start()
    assert ready.wait(30)

    def recorded() -> int:
        said = [line for line in lines if line.startswith("recording: ")]
        return int(said[-1].split()[1]) if said else 0

    deadline = time.monotonic() + 30
    while recorded() == 0:  # the route is up
        listener.publish(topics.observation("robot0"), Observation(seq=0, text="a probe"))
        assert time.monotonic() < deadline
        time.sleep(0.1)
    sent = recorded()
    for seq in range(1, 21):
        listener.publish(topics.observation("robot0"), Observation(seq=seq, text=f"look {seq}"))
        listener.publish(topics.state("robot0"), ControlState(
            t=seq * 0.1, x=(0.0,) * 12, u=(9.81, 0, 0, 0), mode="nominal"))
        sent += 2
        if seq % 5 == 0:
            listener.publish(topics.event("robot0", "control"), Event(
                source="control", kind="anomaly", severity="warning", message=f"alarm {seq}"))
            listener.publish(topics.event("robot0", "embedding"), Event(
                source="embedding", kind="detector", message=f"flagged {seq}"))
            sent += 2
        time.sleep(0.01)
    deadline = time.monotonic() + 30
    while recorded() < sent:
        assert time.monotonic() < deadline, (recorded(), sent)
        time.sleep(0.05)
    stop.set()
    thread.join(30)
    return out


def test_a_recorded_flights_events_are_replayed(endpoint: str, listener: Bus,
                                                tmp_path: Path) -> None:
    """Issue 44: a replayed flight lost every event (the dashboard showed no alarm)."""
    path = recorded_flight(endpoint, listener, tmp_path / "flight.mcap")
    recorded = [(r.key, r.data) for r in read_messages(path)]
    events = [(key, data) for key, data in recorded if "/event/" in key]
    assert {key for key, _ in events} == {"aesop/robot0/event/control",
                                          "aesop/robot0/event/embedding"}
    assert len(events) == 8

    heard = Heard(f"tcp/127.0.0.1:{free_port()}")
    try:
        proc = replay(str(path), "--connect", heard.endpoint, "--speed", "4")
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err
        assert heard.got == recorded  # every message, the events among them, in order
        assert f"replayed {len(recorded)} messages" in err

        proc = replay(str(path), "--connect", heard.endpoint, "--speed", "4", "--topics",
                      "event")
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err
        assert heard.got[len(recorded):] == events
    finally:
        heard.close()
