"""The ``aesop`` command's own checks, before any service is imported."""

from __future__ import annotations

import importlib.util

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
