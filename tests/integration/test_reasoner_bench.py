"""``aesop bench reasoner --json``: real fake-LLM processes, one JSON object on stdout."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

REQUIRED = {"requests", "deadline_s", "deadline_misses", "overshoot_ms", "fallback_rate",
            "overhead_ms", "hedging"}


def test_bench_reasoner_json_is_one_object_with_the_required_keys() -> None:
    r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "reasoner",
                        "--requests", "60", "--scale", "0.05", "--json"],
                       capture_output=True, text=True, timeout=280, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(r.stdout)  # the whole of stdout: exactly one JSON object
    assert isinstance(result, dict)
    assert set(result) >= REQUIRED
    assert result["requests"] == 60
    assert isinstance(result["deadline_misses"], int) and result["deadline_misses"] >= 0
    assert 0.0 <= result["fallback_rate"] <= 1.0
    assert {"p50", "p99", "max"} <= set(result["overshoot_ms"])
    assert {"p50", "p99"} <= set(result["overhead_ms"])
    hedging = result["hedging"]
    assert {"hedge_after_s", "p95_latency_ratio", "fallback_rate_ratio"} <= set(hedging)
    assert hedging["hedged_run"]["requests"] == 60
