"""``aesop bench mpc|closed-loop --json``: one JSON object on stdout, the agreed keys."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(300)]


def _aesop(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tools.cli", *args], capture_output=True,
                          text=True, timeout=280, stdin=subprocess.DEVNULL)


def test_bench_closed_loop_json(tmp_path) -> None:
    plot = tmp_path / "cl.png"
    r = _aesop("bench", "closed-loop", "--scenarios", "2", "--workers", "2",
               "--inconsequential", "1", "--plot", str(plot), "--json")
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(r.stdout)
    assert result["scenarios"] == 2 and result["seed"] == 0
    (only,) = result["conditions"]
    assert only["state"] == {"rate_hz": 100.0, "delay_ms": 0.0}
    assert set(only["methods"]) == {"naive", "fsmpc", "aesop"}
    for row in only["methods"].values():
        assert {"success_rate", "constraint_violations", "mean_time_to_region_s",
                "mean_speed_m_s"} <= set(row)
        assert 0.0 <= row["success_rate"] <= 1.0
    assert only["inconsequential"]["cases"] == 1
    assert plot.stat().st_size > 10_000  # a real PNG figure


def test_bench_closed_loop_state_delay_and_rate_make_one_condition_each() -> None:
    r = _aesop("bench", "closed-loop", "--scenarios", "1", "--workers", "2",
               "--inconsequential", "0", "--methods", "aesop", "--state-rate-hz", "50",
               "--state-delay-ms", "0", "50", "--json")
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(r.stdout)
    assert [c["state"] for c in result["conditions"]] == [
        {"rate_hz": 50.0, "delay_ms": 0.0}, {"rate_hz": 50.0, "delay_ms": 50.0}]
    assert all(set(c["methods"]) == {"aesop"} for c in result["conditions"])
    # stderr not a terminal: a line a step (the method at each condition, n of N) and the
    # line each keeps, not one per case
    steps = [line for line in r.stderr.splitlines() if line.startswith("aesop bench ")]
    assert len(steps) == 2, r.stderr[-3000:]
    assert re.fullmatch(r"aesop bench closed-loop \[\d+:\d\d\] aesop at 50 Hz, 0 ms \(1 of 2\)",
                        steps[0]), steps
    assert steps[1].endswith("aesop at 50 Hz, 50 ms (2 of 2)"), steps
    assert "bench closed-loop: aesop at 50 Hz, 50 ms done" in r.stderr
    assert "cases" not in r.stderr  # the count within a step: on a live line only


def test_bench_mpc_json() -> None:
    r = _aesop("bench", "mpc", "--flights", "1", "--ticks", "4", "--reference-every", "2",
               "--json")
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(r.stdout)
    assert {"p50", "p99"} <= set(result["step_ms"]) <= set(result["reference_step_ms"])
    assert result["step_ms"]["n"] == 3 and result["reference_step_ms"]["n"] == 2
    assert result["speedup_p50"] > 0
    assert result["objective_rel_diff_max"] is None or result["objective_rel_diff_max"] < 1e-2
    assert re.search(r"^aesop bench mpc \[\d+:\d\d\] paper-quadrotor-sim, N = 40, dt = 0.1 s "
                     r"\(1 of 1\)$", r.stderr, re.M), r.stderr[-3000:]


def test_bench_mpc_prints_its_table_for_one_horizon() -> None:
    """One ``--horizons`` value fits no growth exponent (None): the table still prints."""
    r = _aesop("bench", "mpc", "--flights", "1", "--ticks", "4", "--reference-every", "2",
               "--horizons", "20")
    assert r.returncode == 0, r.stderr[-3000:]
    assert re.search(r"^ +20 +0\.200 ", r.stdout, re.M), r.stdout
    assert "growth of the step's p50" not in r.stdout


def test_bench_rejects_bad_arguments() -> None:
    r = _aesop("bench", "closed-loop", "--scenarios", "0", "--json")
    assert r.returncode == 2 and "--scenarios" in r.stderr and r.stdout == ""
    r = _aesop("bench", "closed-loop", "--state-rate-hz", "0", "--json")
    assert r.returncode == 2 and "--state-rate-hz" in r.stderr and r.stdout == ""
