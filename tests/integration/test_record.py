"""``aesop record``: the stack's topics into MCAP (issue 13), as a user runs it, against
a real Zenoh peer."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from mcap.exceptions import McapError
from mcap.reader import make_reader

from shared import topics
from shared.bus import Bus
from shared.messages import ControlState, Event, Observation
from tools.recording.mcapfile import model_of, read_messages

pytestmark = pytest.mark.timeout(120)


class Recorder:
    def __init__(self, endpoint: str, out: Path, *extra: str) -> None:
        env = {k: v for k, v in os.environ.items() if not k.startswith("AESOP_")}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tools.cli", "record", "--out", str(out), "--connect",
             endpoint, *extra], env=env, stderr=subprocess.PIPE, text=True,
            stdin=subprocess.DEVNULL)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.append(line.rstrip())

    def recorded(self) -> int:
        """Messages written so far, as its progress line says."""
        for line in reversed(self.lines):
            if line.startswith("recording: "):
                return int(line.split()[1])
        return 0


def feed(bus: Bus, until: threading.Event, robot: str = "robot0") -> None:
    seq = 0
    while not until.is_set():
        bus.publish(topics.observation(robot), Observation(robot=robot, seq=seq,
                                                           text=f"a red box, look {seq}"))
        bus.publish(topics.state(robot), ControlState(robot=robot, t=seq * 0.1,
                                                      x=(0.0,) * 12, u=(9.81, 0, 0, 0),
                                                      mode="nominal"))
        seq += 1
        time.sleep(0.005)


@pytest.fixture
def fed(listener: Bus) -> Iterator[None]:
    stop = threading.Event()
    thread = threading.Thread(target=feed, args=(listener, stop), daemon=True)
    thread.start()
    yield
    stop.set()
    thread.join(5)


def wait_recorded(recorder: Recorder, n: int) -> None:
    deadline = time.monotonic() + 60
    while recorder.recorded() < n:
        assert recorder.proc.poll() is None, recorder.lines
        assert time.monotonic() < deadline, recorder.lines
        time.sleep(0.1)


def test_a_recording_is_an_indexed_mcap_with_a_json_schema_per_type(
        endpoint: str, listener: Bus, fed: None, tmp_path: Path) -> None:
    out = tmp_path / "flight.mcap"
    recorder = Recorder(endpoint, out)
    wait_recorded(recorder, 50)
    listener.publish(topics.event("robot0", "test"), Event(source="test", kind="probe"))
    time.sleep(1.2)  # one more progress line, with the event in it
    recorder.proc.send_signal(signal.SIGINT)
    assert recorder.proc.wait(30) == 0, recorder.lines
    assert "recorded" in recorder.lines[-1] and "messages/s" in recorder.lines[-1]
    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None  # finished, indexed
        channels = {c.topic: c for c in summary.channels.values()}
        assert {"aesop/robot0/observation", "aesop/robot0/state",
                "aesop/robot0/event/test"} <= set(channels)
        assert all(c.message_encoding == "json" for c in channels.values())
        for schema in summary.schemas.values():
            assert schema.encoding == "jsonschema"
            assert json.loads(schema.data)["title"] == schema.name
        count = 0
        for schema, channel, message in reader.iter_messages():
            model = model_of(channel.topic)
            assert model is not None, channel.topic
            assert model.__name__ == schema.name
            model.decode(message.data)
            count += 1
    assert count == summary.statistics.message_count >= 100


def test_a_recorder_killed_with_sigkill_leaves_a_readable_file(
        endpoint: str, listener: Bus, fed: None, tmp_path: Path) -> None:
    out = tmp_path / "killed.mcap"
    recorder = Recorder(endpoint, out, "--topics", "observation")
    wait_recorded(recorder, 3000)  # several 64 KiB chunks
    recorder.proc.send_signal(signal.SIGKILL)
    recorder.proc.wait(10)
    got = list(read_messages(out))
    assert len(got) >= 500, len(got)  # every completed chunk
    assert {r.key for r in got} == {"aesop/robot0/observation"}
    seqs = [Observation.decode(r.data).seq for r in got]
    assert seqs == sorted(seqs)  # in the order received, no gaps but the lost tail
    with open(out, "rb") as f, pytest.raises(McapError):  # no footer: never finished
        make_reader(f).get_summary()


def test_an_unknown_topic_is_refused_by_name(endpoint: str, tmp_path: Path) -> None:
    run = subprocess.run([sys.executable, "-m", "tools.cli", "record", "--out",
                          str(tmp_path / "x.mcap"), "--topics", "nonsense"],
                         capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert run.returncode != 0 and "nonsense" in run.stderr and "Traceback" not in run.stderr
