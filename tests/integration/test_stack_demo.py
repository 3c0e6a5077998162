"""`aesop demo --json`: the whole stack flies the paper's four hardware scenarios."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tools.recording.mcapfile import read_messages

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(600)]


def test_demo_flies_the_papers_hardware_scenarios(tmp_path: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "tools.cli", "demo", "--json", "--random-ports",
                        "--out", str(tmp_path / "report")],
                       capture_output=True, text=True, timeout=540, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr[-3000:] + r.stdout[-3000:]
    lines = r.stdout.strip().splitlines()
    assert len(lines) == 1  # exactly one JSON object on stdout
    # its progress on stderr, not a terminal here: a line a step, each flight n of 4
    flights = re.findall(r"^aesop demo \[\d+:\d\d\] flight (\S+) \((\d) of 4\)$", r.stderr,
                         re.M)
    assert [n for _, n in flights] == ["1", "2", "3", "4"], r.stderr[-3000:]
    rows = {row["name"]: row for row in json.loads(lines[0])["scenarios"]}
    assert list(rows) == ["1-nominal", "2a-quadrotor-on-red-box", "2b-both-boxes-occupied",
                          "3-keyboard-on-ground"]
    expected = {"1-nominal": "red-box", "2a-quadrotor-on-red-box": "blue-box",
                "2b-both-boxes-occupied": "holding-zone", "3-keyboard-on-ground": "red-box"}
    decisions = {"2a-quadrotor-on-red-box": "alternative landing site",
                 "2b-both-boxes-occupied": "holding zone", "3-keyboard-on-ground": "continue"}
    for name, row in rows.items():
        assert row["outcome"] == "ok", row
        assert row["ended_in"] == row["expected"] == expected[name]
        assert row["constraint_violations"] == 0
        assert row["duration_s"] >= 11.0
    for name, decision in decisions.items():
        assert rows[name]["anomaly_at_s"] is not None
        assert rows[name]["decision"] == decision
        assert rows[name]["decision_source"] == "llm"  # the fake LLM answered within K
    report = tmp_path / "report"
    assert (report / "flights.png").stat().st_size > 10_000
    page = (report / "index.html").read_text()
    assert "<table>" in page
    # every flight recorded, linked from the report, and its file holds the flight
    for name, row in rows.items():
        rec = row["recording"]
        assert rec["file"] == f"recordings/{name}.mcap" and f'href="{rec["file"]}"' in page
        got = list(read_messages(report / rec["file"]))
        assert len(got) == rec["messages"] > 100 and rec["messages_per_s"] > 10
        kinds = {r.key.split("/", 2)[2] for r in got}
        assert {"observation", "anomaly", "state", "plan"} <= kinds, kinds
        if name in decisions:
            assert {"reasoner/request", "reasoner/decision"} <= kinds, kinds
