"""The ``aesop`` command's own checks, before any service is imported."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tools import cli


def test_bench_and_demo_name_the_missing_bench_extra(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "cvxpy" else real(name, *a))
    for argv in (["bench", "mpc", "--ticks", "1"], ["demo", "--json"]):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert "cvxpy not installed" in err and "aesop-stack[bench]" in err


def test_the_installed_environment_has_the_bench_extra() -> None:
    cli.require_bench_extra()  # make test installs it: no error


def test_serve_fake_llm_help_shows_the_fakes_own_flags(
        capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        cli.main(["serve", "fake-llm", "--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert "--profile" in out and "--rate-429" in out and "usage: fake-llm" in out


BLAS_THREADS = """
import sys
from tools import cli
cli.main(["serve", "control", "--scenario", sys.argv[1]])  # refused: a missing file
import numpy  # noqa: E402,F401
from threadpoolctl import threadpool_info  # noqa: E402
print(max(p["num_threads"] for p in threadpool_info()  # numpy's and scipy's
          if "scipy_openblas" in p["filepath"]))
"""


@pytest.mark.parametrize(("given", "threads"), [(None, 1), ("2", 2)])
def test_services_run_one_blas_thread_unless_told_otherwise(
        tmp_path: Path, given: str | None, threads: int) -> None:
    """OpenBLAS's pool spins between calls and takes the cores other loops need: a service
    process keeps one thread, unless its caller says OPENBLAS_NUM_THREADS."""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    r = subprocess.run([sys.executable, "-c", BLAS_THREADS, str(tmp_path / "none.yaml")],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert int(r.stdout.split()[-1]) == threads


def test_the_template_bench_refuses_a_server_without_threads(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["bench", "reasoner", "--llm", "local", "--threads", "0"]) == 2
    assert "--threads" in capsys.readouterr().err
