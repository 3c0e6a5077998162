"""``aesop bench detector`` as a user runs it: one JSON object on stdout, sane values.

Only the cheap parts (``loo``, ``search``, ``restart``, and ``latency`` with its 50
observations per backend) run here, in quick mode. Nothing is asserted about how fast
anything is: timings belong in the benchmark's output, not in tests.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from services.embedding.models.embedders import pool_key
from shared.tables import table
from tools.bench.detector.common import BACKENDS, QUICK, jsonable

pytestmark = pytest.mark.realtime

ROOT = Path(__file__).resolve().parents[2]


def aesop(*args: str, timeout: float, env: dict[str, str] | None = None
          ) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "tools.cli", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout, check=False,
                          env=None if env is None else {**os.environ, **env})


def positive(value: Any) -> bool:
    return isinstance(value, int | float) and math.isfinite(value) and value > 0


def check_stats(stats: dict[str, Any], n: int) -> None:
    assert stats["n"] == n
    assert positive(stats["median_ms"]) and positive(stats["p99_ms"])
    assert stats["p99_ms"] >= stats["median_ms"]


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_quick_loo_search_and_kinds_print_one_json_object() -> None:
    proc = aesop("bench", "detector", "--quick", "--json", "--only", "loo", "--only", "search",
                 "--only", "kinds", timeout=840)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.endswith("\n") and proc.stdout.count("\n") == 1, proc.stdout[:500]
    result = json.loads(proc.stdout)  # the whole of stdout is one object (no NaN allowed)

    assert set(result) == {"meta", "search", "loo", "kinds"}
    assert result["meta"]["quick"] is True
    assert set(result["meta"]["parts"]) == {"search", "loo", "kinds"}

    # the quick sets leave the combined score enough nominal scenes with detections to flag
    # at alpha 0.95 (with 100 the vehicle domain had 58 and the part failed)
    kinds = result["kinds"]
    assert "error" not in kinds, kinds
    assert set(kinds["domains"]) == {"warehouse", "vehicle", "vtol", "quadrotor"}
    for domain in kinds["domains"].values():
        assert all(0.0 <= k["auroc"] <= 1.0 for k in domain["kinds"].values())

    search = result["search"]
    assert "error" not in search, search
    assert [row["n"] for row in search["sizes"]] == list(QUICK.search_sizes)
    for row in search["sizes"]:
        assert 0.0 <= row["recall_at_5"] <= 1.0
        for key in ("exact", "exact_1_thread"):
            check_stats(row[key], search["queries"])
        for key in ("hnsw", "hnsw_1_thread"):
            check_stats(row[key], search["queries"])
        assert positive(row["hnsw_build_s"]) and positive(row["flat_build_s"])
        assert positive(row["speedup_exact_over_hnsw"])
        assert row["hnsw_m"] in (8, 16, 32)
        sweep = row["ef_search_sweep"]  # every efSearch on the same graph
        assert [e["ef_search"] for e in sweep] == [64, 128, 256, 512]
        default = next(e for e in sweep if e["ef_search"] == row["hnsw_ef_search"] == 128)
        assert default["recall_at_5"] == row["recall_at_5"]  # the default, measured again
        assert all(0.0 <= e["recall_at_5"] <= 1.0 for e in sweep)
        assert all(positive(e["median_ms"]) and e["p99_ms"] >= e["median_ms"] for e in sweep)

    loo = result["loo"]
    assert "error" not in loo, loo
    assert (loo["n"], loo["dim"], loo["k"]) == (QUICK.loo_size, 384, 5)
    assert positive(loo["loo_scores_s"]) and positive(loo["faiss_search_s"])
    assert positive(loo["ratio_faiss_over_loo"])
    assert loo["max_abs_diff"] < 1e-4  # Cache.loo_scores agrees with FAISS's exact search
    assert loo["verdict"] in ("pass", "FAIL")


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_quick_restart_loads_the_saved_hnsw_graph() -> None:
    proc = aesop("bench", "detector", "--quick", "--json", "--only", "restart", timeout=540)
    assert proc.returncode == 0, proc.stderr[-3000:]
    restart = json.loads(proc.stdout)["restart"]
    assert "error" not in restart, restart
    assert restart["n"] == QUICK.restart_cache and restart["graph_loaded"] is True
    for key in ("commit_s", "graph_build_s", "index_save_s", "restart_with_index_s",
                "restart_without_index_s", "database_mb", "ratio"):
        assert positive(restart[key]), key


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_quick_latency_times_each_backend(tmp_path: Path) -> None:
    env = {"XDG_CACHE_HOME": str(tmp_path)}  # the ONNX exports go here, made by the probes
    proc = aesop("bench", "detector", "--quick", "--json", "--only", "latency", timeout=600,
                 env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    latency = json.loads(proc.stdout)["latency"]
    runs = latency["backends"]
    assert [(run["model"], run["threads"]) for run in runs] == \
        [(pool_key(model), threads) for model, threads in BACKENDS]
    for run in runs:
        assert run["n"] == QUICK.latency_n
        check_stats(run["end_to_end"], QUICK.latency_n)
        check_stats(run["embed_only"], QUICK.latency_n)
    assert latency["end_to_end"] == runs[0]["end_to_end"]
    assert (tmp_path / "aesop" / "onnx").is_dir()


def test_unknown_part_is_a_user_error() -> None:
    proc = aesop("bench", "detector", "--json", "--only", "nope", timeout=120)
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert "unknown part" in proc.stderr and "nope" in proc.stderr


def test_results_become_strict_json() -> None:
    import numpy as np

    raw = {"a": np.float32(1.5), "b": float("nan"), "c": (np.int64(3), np.inf), 4: [np.True_]}
    clean = jsonable(raw)
    assert clean == {"a": 1.5, "b": None, "c": [3, None], "4": [True]}
    json.dumps(clean, allow_nan=False)


def test_table_aligns_columns() -> None:
    text = table("title", [{"name": "x", "ms": 1.23456, "none": None},
                            {"name": "longer", "ms": 1234.5, "none": 2}])
    lines = text.splitlines()
    assert lines[0] == "title"
    assert len({len(line) for line in lines[1:]}) == 1
    assert "1.235" in text and "1234" in text and " -" in text
