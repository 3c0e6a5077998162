"""Issue 46: a vehicle nobody here wrote, first-class. `aesop up --vehicle external` starts
no vehicle and says how the robot's own joins; the example vehicle of
docs/architecture.md 3a, run as written with the line the banner prints, is flown through
scenarios 2a and 1 by the `aesop demo --attach` line the banner prints (each started by the
contract's reset query, judged on the states the vehicle reports)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.integration.test_stack_up import interrupt
from tests.integration.test_vehicle_contract import example

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(420)]

ROOT = Path(__file__).resolve().parents[2]


def test_aesop_up_with_an_external_vehicle_flies_the_documented_one_to_the_blue_box(
        tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("AESOP_") or k == "AESOP_LOG_LEVEL"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "up", "--vehicle", "external", "--random-ports",
         "--no-dashboard", "--data-dir", str(tmp_path / "data")], env=env,
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL, text=True)
    vehicle = None
    try:
        assert proc.stdout is not None
        banner: list[str] = []
        for line in proc.stdout:
            banner.append(line)
            if line.startswith("Ctrl-C stops everything"):
                break
        assert not any(line.split()[:1] == ["sim"] for line in banner), banner  # none started
        (join,) = [line.split() for line in banner if line.rstrip().endswith("my_vehicle.py")]
        (fly,) = [line.split() for line in banner if "aesop demo --attach" in line]
        assert fly[:3] == ["aesop", "demo", "--attach"] and "--vehicle" in fly, fly
        assert "--sim-url" not in fly
        script = tmp_path / "my_vehicle.py"
        script.write_text(example())
        variables = dict(word.split("=", 1) for word in join[:-2])
        assert variables["AESOP_ZENOH_USER"] == "robot-robot0", join  # the robot's own user
        vehicle = subprocess.Popen([sys.executable, str(script)], stdin=subprocess.DEVNULL,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                   env={**env, **variables, "PYTHONPATH": str(ROOT)})
        # 2a ends on the blue box: 1 starts there only if the reset query moved it home
        done = subprocess.run([sys.executable, "-m", "tools.cli", *fly[1:], "--scenario-name",
                               "2a", "--scenario-name", "1", "--json", "--out",
                               str(tmp_path / "report")], env=env,
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-3000:]
        assert "answers no reset query" not in done.stderr
        blue, red = json.loads(done.stdout.splitlines()[-1])["scenarios"]
        assert blue["ended_in"] == "blue-box" and red["ended_in"] == "red-box", (blue, red)
        for row in (blue, red):
            assert row["constraint_violations"] == 0, row
            assert row["setpoint_age_ms"] == [None, None, None]  # the vehicle does not say
        assert vehicle.poll() is None  # it flew on its own all along
    finally:
        if vehicle is not None:
            vehicle.kill()
            vehicle.wait()
        interrupt(proc)
