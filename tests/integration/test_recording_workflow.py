"""The paper's workflow from recordings, as a user runs it (issue 13): a recorded nominal
flight imported into a cache of a real ``aesop serve embedding`` (real model), the
cache calibrated, and a recorded incident re-scored against it, over REST and offline."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from shared.messages import AnomalyVerdict, ControlState, Detection, Observation
from shared.process import ServiceProcess, free_port
from tools.recording.importer import scene_id
from tools.recording.mcapfile import FlightWriter

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

TOKEN = "recording-workflow-token-0123"
T0 = 1_763_000_000_000_000_000
OBJECTS = ["a cardboard package", "a padded envelope", "a plastic tote", "a shrink-wrapped box",
           "a barcode label", "a small parcel", "a shipping crate", "a sealed carton"]
PLACES = ["on the conveyor belt", "next to the storage shelf", "on a pallet"]
NOMINAL = [f"{o} {p}" for o in OBJECTS for p in PLACES]
INCIDENT = "a smoking lithium battery on the conveyor belt"


def observation(seq: int, text: str) -> Observation:
    label, where = text.split(" on ", 1) if " on " in text else (text, None)
    return Observation(seq=seq, text=text, task="sort the parcels",
                       detections=(Detection(label=label, where=where and f"on {where}"),))


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """20 s of nominal flight (each scene seen ten times, 10 Hz), then an incident the
    detector of the day called nominal (its recorded verdict)."""
    path = tmp_path_factory.mktemp("rec") / "flight.mcap"
    writer = FlightWriter(path)
    seq = 0
    for text in NOMINAL * 10:
        writer.add("aesop/robot0/observation", observation(seq, text).encode(),
                   T0 + seq * 100_000_000)  # 10 Hz
        seq += 1
    for _ in range(5):
        at = T0 + seq * 100_000_000
        writer.add("aesop/robot0/observation", observation(seq, INCIDENT).encode(), at)
        writer.add("aesop/robot0/anomaly", AnomalyVerdict(
            seq=seq, score=0.2, threshold=0.5, is_anomaly=False, k=1, model="old",
            cache="nominal", cache_version=1, latency_ms=5.0).encode(), at + 1000)
        seq += 1
    writer.close()
    return path


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    data = tmp_path_factory.mktemp("embedding")
    port = free_port()
    with ServiceProcess(["serve", "embedding", "--port", str(port), "--data-dir", str(data)],
                        port=port, log_path=data / "server.log",
                        env={"AESOP_ADMIN_TOKEN": TOKEN,
                             "AESOP_EMBEDDING_ZENOH_WORKER": "false"}) as proc:
        yield proc


def aesop(*args: str, token: str | None = TOKEN) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("AESOP_")}
    if token:
        env["AESOP_ADMIN_TOKEN"] = token
    return subprocess.run([sys.executable, "-m", "tools.cli", *args], capture_output=True,
                          text=True, timeout=240, stdin=subprocess.DEVNULL, env=env)


def test_import_calibrate_and_rescore_over_rest(flight: Path, service: ServiceProcess) -> None:
    # the nominal part only: the incident starts at 24 s
    r = aesop("cache", "import", "--recording", str(flight), "--cache", "warehouse",
              "--until", "23.9", "--url", service.url, "--json")
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    assert got == {"cache": "warehouse", "observations": 240, "scenes": 24,
                   "already_in_cache": 0, "added": 24, "size": 24, "version": got["version"]}
    assert "240 observations, 24 distinct scenes" in r.stderr
    assert "added 24 of 24" in r.stderr and "embedded" not in r.stderr  # no line per poll
    again = aesop("cache", "import", "--recording", str(flight), "--cache", "warehouse",
                  "--until", "23.9", "--url", service.url, "--json")
    assert json.loads(again.stdout)["added"] == 0  # the same scenes: nothing twice
    assert json.loads(again.stdout)["already_in_cache"] == 24

    # 24 scenes with detections: at 0.95 the combined p-value (2/25 at least) could never
    # flag anything, and the service says so
    cal = aesop("cache", "calibrate", "--cache", "warehouse", "--url", service.url, "--json")
    assert cal.returncode == 2 and "at least 40" in cal.stderr, cal.stderr
    cal = aesop("cache", "calibrate", "--cache", "warehouse", "--url", service.url, "--json",
                "--alpha", "0.9")
    assert cal.returncode == 0, cal.stderr
    assert json.loads(cal.stdout)["n"] == 24 and json.loads(cal.stdout)["pairs"] is False
    # one detection per scene: no pair to calibrate, and the service's 409 says so
    pairs = aesop("cache", "calibrate", "--cache", "warehouse", "--url", service.url,
                  "--alpha", "0.9", "--pairs")
    assert pairs.returncode == 2 and "no pair to score against" in pairs.stderr, pairs.stderr

    r = aesop("detector", "eval", "--recording", str(flight), "--cache", "warehouse",
              "--url", service.url, "--json")
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout)
    assert result["observations"] == 245 and result["with_recorded_verdict"] == 5
    assert re.search(r"^aesop detector eval \[\d+:\d\d\] scoring 25 distinct scenes against "
                     rf"cache warehouse at {re.escape(service.url)}$", r.stderr, re.M), r.stderr
    # today's cache flags the battery the recorded detector let through
    assert result["changed"] == result["now_anomaly"] == 5 == result["anomalies_now"]
    assert result["threshold"] == json.loads(cal.stdout)["threshold"]
    changed = [row for row in result["rows"] if row["changed"]]
    assert {row["text"] for row in changed} == {INCIDENT}
    assert changed[0]["old"]["is_anomaly"] is False and changed[0]["new"]["is_anomaly"] is True

    table = aesop("detector", "eval", "--recording", str(flight), "--cache", "warehouse",
                  "--url", service.url, "--changed-only")
    assert table.returncode == 0, table.stderr
    lines = [line for line in table.stdout.splitlines() if line.startswith("*")]
    assert len(lines) == 5 and all("ANOMALY" in line and "battery" in line for line in lines)


def test_an_experience_keeps_its_detections_and_origin(flight: Path,
                                                       service: ServiceProcess) -> None:
    r = aesop("cache", "import", "--recording", str(flight), "--cache", "origin",
              "--since", "0", "--until", "0.05", "--url", service.url, "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["added"] == 1
    listed = httpx.get(f"{service.url}/v1/caches/origin",
                       headers={"Authorization": f"Bearer {TOKEN}"}).json()
    assert listed["size"] == 1
    ident = scene_id(observation(0, NOMINAL[0]))
    exp = httpx.get(f"{service.url}/v1/caches/origin/experiences/{ident}",
                    headers={"Authorization": f"Bearer {TOKEN}"}).json()
    assert exp["text"] == NOMINAL[0]
    assert exp["detections"] == [{"label": "a cardboard package", "where": "on the conveyor belt",
                                  "confidence": None}]
    assert exp["metadata"]["source"] == "flight.mcap" and exp["metadata"]["seen"] == 1


def test_rescore_offline_against_a_nominal_set(flight: Path, tmp_path: Path) -> None:
    nominal = tmp_path / "nominal.jsonl"
    nominal.write_text("".join(json.dumps({"text": t}) + "\n" for t in NOMINAL))
    r = aesop("detector", "eval", "--recording", str(flight), "--nominal", str(nominal),
              "--json")
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout)
    assert result["observations"] == 245 and result["now_anomaly"] == 5
    assert result["against"].startswith(str(nominal))
    steps = [re.sub(r"\[\d+:\d\d\] ", "", line) for line in r.stderr.splitlines()
             if line.startswith("aesop detector eval")]
    assert steps == ["aesop detector eval loading sentence-transformers/all-MiniLM-L6-v2",
                     f"aesop detector eval embedding {nominal} and scoring 25 distinct scenes"]


def test_rescore_offline_judges_each_scene_with_its_detections(flight: Path,
                                                               tmp_path: Path) -> None:
    nominal = tmp_path / "nominal.jsonl"
    nominal.write_text("".join(json.dumps({
        "text": t, "detections": [d.model_dump(exclude_none=True)
                                  for d in observation(0, t).detections]}) + "\n"
        for t in NOMINAL))
    r = aesop("detector", "eval", "--recording", str(flight), "--nominal", str(nominal),
              "--score", "combined", "--alpha", "0.9", "--json")
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout)
    # the battery is no nominal detection: flagged; every nominal scene is itself
    assert result["observations"] == 245 and result["now_anomaly"] == 5
    r = aesop("detector", "eval", "--recording", str(flight), "--nominal", str(nominal),
              "--score", "detections")
    assert r.returncode == 2 and "--score topk, mahalanobis or combined" in r.stderr


def test_until_3_imports_the_first_3_s_of_a_flight_the_recorder_began_before(
        tmp_path: Path, service: ServiceProcess) -> None:
    """docs/recordings.md on the demo's recordings (issue 44): the demo starts its recorder
    while it sets the flight up, and the camera comes on seconds later; ``--until 3`` takes
    the first 3 s of observations, not the 3 s of states before them."""
    path = tmp_path / "1-nominal.mcap"
    writer = FlightWriter(path)
    on = T0 + 3_500_000_000  # the camera comes on 3.5 s into the recording
    for i in range(70):  # 20 Hz states from the start
        writer.add("aesop/robot0/state", ControlState(
            t=i * 0.05, x=(0.0,) * 12, u=(0.0,) * 4, mode="waiting").encode(), T0 + i * 50_000_000)
    for seq in range(50):  # 10 Hz observations, three scenes over and over
        writer.add("aesop/robot0/observation",
                   observation(seq, NOMINAL[seq % 3]).encode(), on + seq * 100_000_000)
    writer.close()
    r = aesop("cache", "import", "--recording", str(path), "--cache", "first3", "--k", "1",
              "--until", "3", "--url", service.url, "--json")
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    assert (got["observations"], got["scenes"], got["added"], got["size"]) == (31, 3, 3, 3)


def test_an_import_that_selects_nothing_fails_and_stores_nothing(
        flight: Path, service: ServiceProcess) -> None:
    headers = {"Authorization": f"Bearer {TOKEN}"}
    r = aesop("cache", "import", "--recording", str(flight), "--cache", "never",
              "--since", "30", "--url", service.url, "--json")
    assert r.returncode == 2, r.stdout + r.stderr
    assert "no observations" in r.stderr and "--since 30" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and r.stdout == ""
    assert httpx.get(f"{service.url}/v1/caches/never", headers=headers).status_code == 404

    r = aesop("cache", "import", "--recording", str(flight), "--cache", "kept",
              "--until", "0.05", "--url", service.url, "--json")
    assert r.returncode == 0, r.stderr
    before = httpx.get(f"{service.url}/v1/caches/kept", headers=headers).json()
    r = aesop("cache", "import", "--recording", str(flight), "--cache", "kept", "--since",
              "40", "--until", "50", "--url", service.url)
    assert r.returncode == 2 and "no observations" in r.stderr, r.stdout + r.stderr
    assert httpx.get(f"{service.url}/v1/caches/kept", headers=headers).json() == before


@pytest.mark.parametrize(("args", "message"), [
    (["detector", "eval", "--recording", "{bad}", "--cache", "c"], "not an MCAP file"),
    (["detector", "eval", "--recording", "{flight}"], "either --nominal"),
    (["detector", "eval", "--recording", "{flight}", "--cache", "c", "--nominal", "{flight}"],
     "either --nominal"),
    (["detector", "eval", "--test", "{flight}", "--nominal", "{flight}", "--cache", "c"],
     "go with --recording"),
    (["cache", "import", "--recording", "{flight}", "--cache", "c", "--since", "9",
      "--until", "2"], "before --since"),
    (["cache", "import", "--recording", "{flight}", "--cache", "c", "--since", "soon"],
     "ISO 8601"),
    (["cache", "import", "--recording", "{flight}", "--cache", "c", "--url",
      "http://127.0.0.1:9"], "no embedding service at http://127.0.0.1:9"),
    (["replay", "{bad}"], "not an MCAP file"),
    (["replay", "{flight}", "--speed", "0"], "--speed"),
])
def test_user_errors_are_named_without_a_traceback(flight: Path, tmp_path: Path,
                                                   args: list[str], message: str) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_text("not a recording")
    r = aesop(*(a.format(bad=bad, flight=flight) for a in args))
    assert r.returncode == 2, r.stdout + r.stderr
    assert message in r.stderr and "Traceback" not in r.stderr


def test_a_wrong_token_is_the_services_401_named(flight: Path, service: ServiceProcess) -> None:
    r = aesop("cache", "import", "--recording", str(flight), "--cache", "c", "--url",
              service.url, token="wrong")
    assert r.returncode == 2 and "401" in r.stderr and "Traceback" not in r.stderr
