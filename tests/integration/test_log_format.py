"""Issue 44, item 12: logs came in two formats (ours and uvicorn's) with no JSON option. With
``AESOP_LOG_FORMAT=json`` every line a service writes, uvicorn's included, is one JSON
object; a value that is neither text nor json stops the command naming the variable."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from shared import topics
from shared.bus import Bus
from shared.messages import VehicleReset, VehicleState
from shared.process import ServiceProcess, free_port
from shared.settings import BusSettings
from tests.zenoh_peers import wait_until

pytestmark = pytest.mark.timeout(120)


def test_json_logs_are_one_object_per_line_for_every_logger(tmp_path: Path) -> None:
    port, log = free_port(), tmp_path / "sim.log"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {"AESOP_LOG_FORMAT": "json", "AESOP_ZENOH_LISTEN": endpoint, "AESOP_ROBOT": "r1",
           "AESOP_SIM_NOT_A_KNOB": "1"}  # said to be unknown: in JSON too
    with ServiceProcess(["serve", "sim", "--port", str(port), "--scenario", "hardware"],
                        port=port, env=env, log_path=log, ready_timeout_s=60,
                        unset=["AESOP_ADMIN_TOKEN"]), \
            Bus.open(BusSettings(zenoh_connect=[endpoint]), "tester") as bus:
        # a reset outside the fence: refused, and the simulator logs a warning of its own
        wait_until(lambda: "sim" in bus.alive(), "the simulator on the bus")
        assert bus.ask(topics.vehicle_reset("r1"), VehicleState, timeout=2.0,
                       payload=VehicleReset(robot="r1", position=(0.0, 0.0, 99.0))) == []
    lines = [line for line in log.read_text().splitlines() if line.strip()]
    records = [json.loads(line) for line in lines]  # every line: one JSON object
    assert all({"time", "level", "logger", "message", "pid"} <= set(r) for r in records)
    assert any(r["logger"].startswith("uvicorn") for r in records), records  # theirs too
    assert any(r["logger"] == "aesop" and r["level"] == "WARNING"
               and "AESOP_SIM_NOT_A_KNOB is not a setting" in r["message"] for r in records)
    assert any(r["logger"] == "services.sim.service" and r["level"] == "WARNING"
               and "reset query refused" in r["message"] for r in records), records


def test_a_log_format_that_is_not_text_or_json_is_refused() -> None:
    done = subprocess.run([sys.executable, "-m", "tools.cli", "serve", "sim", "--port", "0"],
                          env={"AESOP_LOG_FORMAT": "yaml", "PATH": "/usr/bin:/bin"},
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "AESOP_LOG_FORMAT: expected text or json, got 'yaml'" in done.stderr
