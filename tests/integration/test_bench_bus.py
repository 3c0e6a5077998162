"""``aesop bench bus --json``, small: real processes, the real model, real Zenoh.

Only the report's shape and internal consistency are checked; the numbers
themselves are for people reading the benchmark (README), not for asserts.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(600)]

OBSERVATIONS, ANOMALIES, RATE_HZ = 30, 3, 20.0


def test_bench_bus_reports_consistent_latencies() -> None:
    r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "bus", "--json",
                        "--observations", str(OBSERVATIONS), "--anomalies", str(ANOMALIES),
                        "--rate", str(RATE_HZ), "--cache-detections", "2"],
                       capture_output=True, text=True, timeout=540, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(r.stdout)  # exactly one JSON object: anything else fails to parse
    assert result["observations"] == OBSERVATIONS and result["anomalies"] == ANOMALIES
    assert result["rate_hz"] == RATE_HZ and result["control_rate_hz"] > 0
    assert result["model"] == "onnx:sentence-transformers/all-MiniLM-L6-v2"  # the default
    assert result["cache_size"] == 55  # 10 single detections and 45 pairs
    counts = {"verdict_ms": OBSERVATIONS, "reaction_ms": ANOMALIES,
              "reaction_after_verdict_ms": ANOMALIES}
    for key, n in counts.items():
        stats = result[key]
        assert set(stats) == {"n", "p50", "p99", "max"}, key
        assert stats["n"] == n, key
        assert 0 <= stats["p50"] <= stats["p99"] <= stats["max"], (key, stats)
    # a reaction waits for its verdict first, then for the control loop's tick
    assert result["reaction_ms"]["max"] >= result["reaction_after_verdict_ms"]["max"]
    # progress goes to stderr, a line a step (not a tty here): the two phases, n of 2
    steps = [re.sub(r"\[\d+:\d\d\] ", "", line) for line in r.stderr.splitlines()
             if line.startswith("aesop bench bus [")]
    assert f"aesop bench bus {OBSERVATIONS} observations at {RATE_HZ:g} Hz (1 of 2)" in steps, \
        r.stderr[-3000:]
    assert any(s.startswith(f"aesop bench bus {ANOMALIES} anomalies, control at ")
               and s.endswith("(2 of 2)") for s in steps), r.stderr[-3000:]


def test_bench_bus_refuses_bad_arguments() -> None:
    r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "bus", "--json",
                        "--observations", "0"], capture_output=True, text=True, timeout=60,
                       stdin=subprocess.DEVNULL)
    assert r.returncode == 2 and r.stdout == ""
    assert "--observations" in r.stderr
