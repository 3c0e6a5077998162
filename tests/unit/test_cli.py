"""The ``aesop`` command's own checks, before any service is imported."""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
from collections.abc import Iterator
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


def test_the_fairness_bench_refuses_no_rounds(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["bench", "fairness", "--rounds", "0"]) == 2
    assert "--rounds" in capsys.readouterr().err


@pytest.mark.parametrize(("argv", "says"), [
    (["up", "--role", "robot", "--server", "h"], "--tls DIR"),
    (["up", "--server", "h"], "go with --role"),
    (["up", "--role", "robot", "--tls", "nowhere", "--robot", "r0"], "--server"),
    (["up", "--role", "robot", "--tls", "nowhere", "--server", "h"], "is missing"),
    (["up", "--role", "server", "--tls", "nowhere"], "aesop zenoh certs"),
    (["zenoh", "certs", "x", "--ca-cert", "ca.pem"], "go together"),
])
def test_the_roles_name_what_they_miss(argv: list[str], says: str, tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 41: a robot or server started without what it needs is a usage error (2)
    naming the flag or the command that makes the missing file, before anything starts."""
    argv = [a if a != "nowhere" else str(tmp_path / "certs") for a in argv]
    assert cli.main([*argv, "--random-ports"] if argv[0] == "up" else argv) == 2
    assert says in capsys.readouterr().err


def test_a_robot_given_a_server_address_that_cannot_be_one_is_told(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tools.stack.certs import write_certs

    write_certs(tmp_path, robots=["robot0"], services=["embedding"])
    for server in ("h:99999", "h:port", ":7447"):
        assert cli.main(["up", "--role", "robot", "--robot", "robot0", "--random-ports",
                         "--tls", str(tmp_path / "robot-robot0"), "--server", server]) == 2
        assert "give HOST or HOST:PORT" in capsys.readouterr().err


@pytest.mark.parametrize(("given", "endpoint"), [
    ("server.lan", "server.lan:7447"), ("10.0.0.5:7000", "10.0.0.5:7000"),
    ("[::1]:7447", "[::1]:7447"), ("::1", "[::1]:7447"), ("[fe80::1]", "[fe80::1]:7447"),
])
def test_a_servers_address_takes_the_routers_port_unless_given(given: str,
                                                               endpoint: str) -> None:
    from tools.stack.cli import _host_port

    assert _host_port(given) == endpoint


def test_version_prints_the_package_version(capsys: pytest.CaptureFixture[str]) -> None:
    from importlib.metadata import version

    with pytest.raises(SystemExit) as done:
        cli.main(["--version"])
    assert done.value.code == 0
    assert capsys.readouterr().out.strip() == f"aesop {version('aesop-stack')}"


@pytest.mark.parametrize(("variable", "says"), [
    ("AESOP_ZENOH_CONFIG", "AESOP_ZENOH_CONFIG: cannot read {path}"),
    ("AESOP_ZENOH_PASSWORD_FILE", "AESOP_ZENOH_PASSWORD_FILE: cannot read {path}"),
])
def test_watch_names_the_missing_file_it_was_given(
        variable: str, says: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    # a missing config file used to be reported as a router that wants a user and password,
    # and a missing password file as a traceback
    for name in list(os.environ):
        if name.startswith("AESOP_ZENOH"):
            monkeypatch.delenv(name)
    path = tmp_path / "gone"
    monkeypatch.setenv(variable, str(path))
    if variable == "AESOP_ZENOH_PASSWORD_FILE":
        monkeypatch.setenv("AESOP_ZENOH_USER", "monitor")
    assert cli.main(["watch", "--connect", "tcp/127.0.0.1:1"]) == 2
    err = capsys.readouterr().err
    assert says.format(path=path) in err
    if variable == "AESOP_ZENOH_CONFIG":
        assert "PASSWORD" not in err


def every_argument(parser: argparse.ArgumentParser, path: str = "aesop"
                   ) -> Iterator[tuple[str, argparse.Action]]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from every_argument(sub, f"{path} {name}")
        elif not isinstance(action, argparse._HelpAction | argparse._VersionAction):
            yield path, action


def test_every_flag_says_what_it_is() -> None:
    """Issue 44, item 12: 33 of 179 arguments had no help; each one has it now, and a
    default worth knowing (not None, not a switch) is in it."""
    arguments = list(every_argument(cli.build_parser()))
    assert len(arguments) > 150
    bare = [f"{path} {'/'.join(a.option_strings) or a.dest}" for path, a in arguments
            if not a.help or a.help == argparse.SUPPRESS]
    assert bare == []
    unsaid = [f"{path} {'/'.join(a.option_strings)}" for path, a in arguments
              if a.option_strings and a.help and not says_default(a)]
    assert unsaid == []


def says_default(action: argparse.Action) -> bool:
    """Whether ``action``'s help says its default: in words, or its value in it (none to
    say for a switch, None or an empty list)."""
    default = action.default
    if default in (None, False, True, argparse.SUPPRESS, []):
        return True
    assert action.help is not None
    shown = (f"{default:g}" if isinstance(default, float) else
             " ".join(map(str, default)) if isinstance(default, list) else str(default))
    return "default" in action.help or shown in action.help


def test_the_cli_offers_the_calibration_methods_the_detector_has() -> None:
    """The parser stays light (no numpy at ``aesop --help``), so ``detector eval --method``
    restates the methods: adding one to the detector must reach the CLI (issue 45's
    "add a calibration method")."""
    from typing import get_args

    from services.embedding.detector.calibration import Method

    methods = {tuple(a.choices) for path, a in every_argument(cli.build_parser())
               if "--method" in a.option_strings and path.endswith("detector eval")}
    assert methods == {get_args(Method)}


@pytest.mark.parametrize("control_frame", [None, "odom"])
def test_serve_ros2_refuses_a_config_in_a_frame_control_does_not_fly_in(
        control_frame: str | None, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    # only `aesop up --ros2` checked it: the bridge run on its own (compose's `ros2`
    # service) took `frame: wrld`, and control then refused every state it bridged
    config = (Path(__file__).parents[2] / "deploy" / "ros2" / "quadrotor.yaml").read_text()
    path = tmp_path / "bridge.yaml"
    path.write_text(config.replace("frame: world", "frame: wrld"))
    monkeypatch.delenv("AESOP_CONTROL_VEHICLE", raising=False)
    if control_frame is None:
        monkeypatch.delenv("AESOP_CONTROL_VEHICLE__FRAME", raising=False)
    else:
        monkeypatch.setenv("AESOP_CONTROL_VEHICLE__FRAME", control_frame)
    monkeypatch.setenv("AESOP_ROS2_CONFIG", str(path))
    assert cli.main(["serve", "ros2", "--port", "1"]) == 2
    err = capsys.readouterr().err
    expected = control_frame or "world"
    assert f"{path}: inputs.odometry.frame: 'wrld' is not '{expected}'" in err
