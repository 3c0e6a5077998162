"""``aesop demo --json``: a real service process, the real model, REST and Zenoh together."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]


def test_demo_flags_the_papers_scenarios_as_expected() -> None:
    r = subprocess.run([sys.executable, "-m", "services.cli", "demo", "--detector-only", "--json"],
                       capture_output=True, text=True, timeout=540, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(r.stdout)
    assert result["ok"] is True
    assert result["cache"]["size"] == 385  # every combination of 1..4 of 10 detections
    cal = result["cache"]["calibration"]
    assert cal["method"] == "tpr-target" and cal["tpr"] >= 0.9
    rows = {row["name"]: row for row in result["scenarios"]}
    assert set(rows) == {"nominal", "quadrotor_on_red_box", "both_boxes_occupied",
                         "keyboard_on_ground"}
    assert rows["nominal"]["is_anomaly"] is False
    for name in ("quadrotor_on_red_box", "both_boxes_occupied", "keyboard_on_ground"):
        assert rows[name]["is_anomaly"] is True
        assert rows[name]["score"] > rows[name]["threshold"]
    assert rows["nominal"]["similarity"] == pytest.approx(1.0, abs=1e-4)  # a cached scene
