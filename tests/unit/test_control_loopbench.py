"""``aesop bench loop``: the flight script and one short run of the real loop (no timing
assertions: the numbers are the benchmark's business)."""

import asyncio
import json
import subprocess
import sys

from services.control.core.scenario import load_scenario, resolve_scenario
from tools.bench.loop import FlightScript, fly_rate

SCENARIO = load_scenario()


def test_script_flags_one_anomaly_per_cycle_and_answers_it_later():
    script = FlightScript(0.1, cycle_s=3.0, anomaly_s=0.5, answer_s=0.3)
    flagged = [k for k in range(90) if script.verdict(k).is_anomaly]
    assert flagged == [5, 35, 65]
    assert [k for k in range(90) if script.reset_after(k)] == [29, 59, 89]
    script.answered(5, "req-1", 2)
    assert script.decision(7) is None
    decision = script.decision(8)
    assert decision is not None and decision.request_id == "req-1" and decision.choice == 2
    assert script.verdict(6).seq == 6 and not script.verdict(6).is_anomaly


def test_a_short_run_times_every_tick_through_an_anomaly_and_a_reset():
    """Against a simulator process: the state over the bus, the set-points back."""
    script = FlightScript(SCENARIO.dt, cycle_s=3.0, anomaly_s=0.5, answer_s=0.3)
    result = asyncio.run(fly_rate(SCENARIO, resolve_scenario("paper"), 50.0, 35, 0, script))
    assert result["ticks"] == 35 and result["requests"] == 1 and result["resets"] == 1
    assert result["setpoints"] > 0 and result["state_age_p50_ms"] is not None
    assert 0 <= result["jitter_p50_ms"] <= result["jitter_p99_ms"] <= result["jitter_max_ms"]
    assert result["tick_p50_ms"] <= result["tick_p99_ms"]
    assert result["overruns"] <= 35 and result["simulated_s"] == 3.5


def test_cli_json_and_bad_arguments():
    run = [sys.executable, "-m", "tools.cli", "bench", "loop"]
    out = subprocess.run([*run, "--minutes", "0.02", "--rates", "20", "--json"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert result["ticks"] == 12 and [r["rate_hz"] for r in result["runs"]] == [20.0]
    bad = subprocess.run([*run, "--minutes", "0"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--minutes" in bad.stderr and bad.stdout == ""
