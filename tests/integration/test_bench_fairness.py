"""``aesop bench fairness --json``, small: the hub, the embedding service with the real
model, and a flooding robot of its own process, all real, in two interleaved rounds.

The report's shape and counts are checked, and that the flood reached the detector
(its surplus refused at robot1's rate) while every one of robot0's verdicts arrived;
the latencies themselves are for people reading docs/benchmarks.md, not for asserts.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(600)]

SECONDS, ROUNDS, RATE_HZ, FLOOD_HZ = 4.0, 2, 10.0, 400.0


def test_bench_fairness_times_robot0_alone_and_flooded_in_interleaved_rounds() -> None:
    r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "fairness", "--json",
                        "--seconds", str(SECONDS), "--rounds", str(ROUNDS),
                        "--rate", str(RATE_HZ), "--flood-hz", str(FLOOD_HZ)],
                       capture_output=True, text=True, timeout=540, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(r.stdout)  # exactly one JSON object: anything else fails to parse
    assert result["through"] == "hub" and result["flood_texts"] == "distinct texts"
    assert result["rounds"] == ROUNDS and len(result["per_round_p99_ratio"]) == ROUNDS
    per_condition = round(SECONDS / ROUNDS * RATE_HZ) * ROUNDS
    for key in ("baseline_ms", "flood_ms"):
        stats = result[key]
        assert stats["n"] == per_condition, (key, stats)  # every verdict arrived
        assert 0 <= stats["p50"] <= stats["p99"] <= stats["max"], (key, stats)
    assert result["lost"] == 0 and result["baseline_lost"] == 0
    assert result["p99_ratio"] == round(result["flood_ms"]["p99"]
                                        / result["baseline_ms"]["p99"], 2)
    # robot1 flooded only while robot0 was timed flooded: about FLOOD_HZ for SECONDS
    # (and half a second a round before robot0 was timed), none while it was alone
    assert 0.5 * FLOOD_HZ * SECONDS < result["flood_sent"] < FLOOD_HZ * (SECONDS + ROUNDS)
    # the flood reached the detector: past robot1's rate its observations were refused
    assert result["dropped"].get('reason="rate",robot="robot1"', 0) > 0
    assert not any(robot == 'robot="robot0"' for robot in
                   (label.split(",")[1] for label in result["dropped"]))
    assert result["met"] == (result["p99_ratio"] <= 2.0)
