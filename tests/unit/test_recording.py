"""The pure parts of recordings (issue 13): windows, distinct scenes, replay timing and
re-scoring's comparison, over files written with the real MCAP writer."""

from __future__ import annotations

from pathlib import Path

import pytest

from shared.messages import AnomalyVerdict, ControlState, Detection, Observation
from tools.demo.report import recordings_section
from tools.recording.importer import distinct_scenes, scene_id
from tools.recording.mcapfile import FlightWriter
from tools.recording.recorded import (
    RecordingError,
    check_recording,
    observations,
    parse_when,
    verdicts,
)
from tools.recording.replay import due_s, topic_filter
from tools.recording.rescore import (
    NewScore,
    Rescored,
    compare,
    summary,
    table,
)
from tools.recording.rescore import (
    distinct_scenes as distinct_observed,
)

T0 = 1_700_000_000_000_000_000  # ns


def verdict(seq: int, score: float, anomaly: bool, robot: str = "robot0") -> AnomalyVerdict:
    return AnomalyVerdict(robot=robot, seq=seq, score=score, threshold=0.5,
                          is_anomaly=anomaly, k=1, model="m", cache="c", cache_version=3,
                          latency_ms=1.0)


@pytest.fixture
def flight(tmp_path: Path) -> Path:
    """Ten observations 1 s apart (two scenes, then one odd one), their verdicts, and
    state messages that are neither."""
    path = tmp_path / "flight.mcap"
    writer = FlightWriter(path)
    scenes = ["a red box", "a red box", "a blue box", "a red box", "a blue box",
              "a red box", "a red box", "a keyboard on the ground", "a red box", "a red box"]
    for seq, text in enumerate(scenes):
        at = T0 + seq * 1_000_000_000
        det = (Detection(label=text.split(" on ")[0], where="on the ground"),) \
            if "keyboard" in text else ()
        writer.add("aesop/robot0/observation",
                   Observation(seq=seq, text=text, detections=det).encode(), at)
        writer.add("aesop/robot0/anomaly",
                   verdict(seq, 0.9 if "keyboard" in text else 0.1, False).encode(), at + 5)
        writer.add("aesop/robot0/state", ControlState(t=seq, x=(0.0,) * 12, u=(0.0,) * 4,
                                                      mode="nominal").encode(), at + 7)
    writer.add("aesop/robot1/observation", Observation(robot="robot1", seq=0,
                                                       text="elsewhere").encode(), T0 + 1)
    writer.close()
    return path


def test_a_window_is_seconds_from_the_start_or_a_time() -> None:
    assert parse_when("2.5", T0) == T0 + 2_500_000_000
    assert parse_when("3s", T0) == T0 + 3_000_000_000
    assert parse_when("2023-11-14T22:13:20", 0) == T0  # UTC unless it says
    assert parse_when("2023-11-14T23:13:20+01:00", 0) == T0
    with pytest.raises(RecordingError, match="ISO 8601"):
        parse_when("yesterday", T0)


def test_observations_in_a_window_of_one_robot(flight: Path) -> None:
    got = list(observations(flight, robot="robot0", since="2", until="4.5"))
    assert [r.observation.seq for r in got] == [2, 3, 4]
    assert {r.observation.robot for r in observations(flight)} == {"robot0", "robot1"}
    with pytest.raises(RecordingError, match="before --since"):
        list(observations(flight, since="5", until="1"))


def demo_like(path: Path, camera_on_s: float) -> Path:
    """A recording as ``aesop demo`` makes one (issue 44): the recorder starts while the
    flight is set up, so 20 Hz states come from the start and the camera's 10 Hz
    observations only ``camera_on_s`` later, for 5 s."""
    writer = FlightWriter(path)
    on = T0 + round(camera_on_s * 1e9)
    messages = [(T0 + i * 50_000_000, "aesop/robot0/state", ControlState(
        t=i * 0.05, x=(0.0,) * 12, u=(0.0,) * 4, mode="waiting").encode())
        for i in range(round((camera_on_s + 5) * 20))]
    messages += [(on + seq * 100_000_000 + 1, "aesop/robot0/observation",
                  Observation(seq=seq, text="a red box").encode()) for seq in range(50)]
    for at, key, data in sorted(messages):
        writer.add(key, data, at)
    writer.close()
    return path


def test_a_window_counts_from_the_first_observation_not_the_recorders_start(
        tmp_path: Path) -> None:
    """docs/recordings.md's ``--until 3``: the first 3 s of what the camera saw, however long
    the recorder ran before the camera came on."""
    path = demo_like(tmp_path / "late.mcap", camera_on_s=3.5)
    assert [r.observation.seq for r in observations(path, until="3")] == list(range(31))
    assert [r.observation.seq for r in observations(path, since="1", until="1.25")] == [
        10, 11, 12]
    assert [r.observation.seq for r in observations(path, robot="robot0", until="0")] == [0]


def test_verdicts_are_keyed_by_robot_and_seq(flight: Path) -> None:
    old = verdicts(flight)
    assert len(old) == 10 and old[("robot0", 7)].score == 0.9


def test_a_file_that_is_not_mcap_is_refused(tmp_path: Path) -> None:
    bad = tmp_path / "x.mcap"
    bad.write_text("hello")
    with pytest.raises(RecordingError, match="not an MCAP"):
        check_recording(bad)
    with pytest.raises(RecordingError, match="cannot read"):
        check_recording(tmp_path / "missing.mcap")


def test_each_scene_once_with_its_count_and_a_content_id(flight: Path) -> None:
    scenes = distinct_scenes(observations(flight, robot="robot0"))
    assert [(s.first.observation.text, s.seen) for s in scenes] == [
        ("a red box", 7), ("a blue box", 2), ("a keyboard on the ground", 1)]
    # the same scene has the same id wherever and whenever it was seen; detections count
    assert scene_id(Observation(seq=1, text="a red box")) == \
        scene_id(Observation(seq=99, robot="r9", text="a red box"))
    assert scene_id(Observation(seq=1, text="a red box")) != scene_id(Observation(
        seq=1, text="a red box", detections=(Detection(label="red box"),)))
    item = scenes[2].item()
    assert item["id"] == scenes[2].id and item["text"] == "a keyboard on the ground"
    assert item["detections"] == [{"label": "a keyboard", "where": "on the ground"}]
    assert item["metadata"]["seen"] == 1 and item["metadata"]["source"] == "flight.mcap"


def test_replay_keeps_the_recorded_timing_scaled() -> None:
    assert due_s(T0 + 3_000_000_000, T0, 1.0) == 3.0
    assert due_s(T0 + 3_000_000_000, T0, 2.0) == 1.5
    assert due_s(T0 - 5, T0, 1.0) == 0.0  # out of order by a hair: at once
    keep = topic_filter(["observation", "reasoner/request"])
    assert keep("aesop/robot0/observation") and keep("aesop/r1/reasoner/request")
    assert not keep("aesop/robot0/state") and not keep("aesop/health/embedding")
    events = topic_filter(["event"])  # one key per source: aesop/<robot>/event/<source>
    assert events("aesop/robot0/event/control") and events("aesop/r1/event/embedding")
    assert not events("aesop/robot0/observation")
    every = topic_filter(None)
    assert every("aesop/robot0/event/robot") and every("aesop/robot0/vehicle/state")
    with pytest.raises(ValueError, match="nonsense"):
        topic_filter(["nonsense"])


def test_rescoring_pairs_old_and_new_verdicts_and_marks_changes(flight: Path) -> None:
    recorded = list(observations(flight, robot="robot0"))
    scenes = distinct_observed(recorded)  # text and detections
    keyboard = (Detection(label="a keyboard", where="on the ground"),)
    assert scenes == [("a red box", ()), ("a blue box", ()),
                      ("a keyboard on the ground", keyboard)]
    new = {scenes[0]: NewScore(0.1, False), scenes[1]: NewScore(0.2, False),
           scenes[2]: NewScore(0.8, True)}
    rows = compare(recorded, verdicts(flight), new)
    assert len(rows) == 10 and rows[7].t_s == 7.0
    assert [r.seq for r in rows if r.changed] == [7]
    got = summary(rows, 0.5)
    assert got == {"observations": 10, "with_recorded_verdict": 10, "threshold": 0.5,
                   "anomalies_recorded": 0, "anomalies_now": 1, "changed": 1,
                   "now_anomaly": 1, "now_nominal": 0}
    lines = table(rows).splitlines()
    assert len(lines) == 11 and lines[8].startswith("*") and "ANOMALY 0.8000" in lines[8]
    assert "nominal 0.9000" in lines[8]  # what the old detector said
    assert len(table(rows, only_changed=True).splitlines()) == 2
    assert rows[7].row()["old"]["cache_version"] == 3 and rows[7].row()["changed"]


def test_an_observation_without_a_recorded_verdict_is_no_change(flight: Path) -> None:
    recorded = list(observations(flight, robot="robot1"))
    rows = compare(recorded, verdicts(flight), {("elsewhere", ()): NewScore(0.9, True)})
    assert rows[0].old is None and not rows[0].changed
    assert "—" in table(rows)
    two_lines = Rescored("robot0", 1, 0.0, "a red box\na drill", None, NewScore(0.1, False))
    assert table([two_lines]).splitlines()[1].endswith("a red box / a drill")
    assert summary(rows, None)["with_recorded_verdict"] == 0


def test_the_report_links_each_recording() -> None:
    rows = [{"name": "1-nominal", "recording": {
        "file": "recordings/1-nominal.mcap", "messages": 900, "file_bytes": 120_000,
        "messages_per_s": 37.5, "bytes_per_s": 21_000}}, {"name": "no recording"}]
    page = recordings_section(rows)
    assert '<a href="recordings/1-nominal.mcap">' in page and "37.5 messages/s" in page
    assert recordings_section([{"name": "x"}]) == ""
