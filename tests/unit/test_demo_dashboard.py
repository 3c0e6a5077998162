"""``aesop demo``'s dashboard can be opened, and ``--keep-up`` keeps the stack supervised
(issue 44, item 3).

The demo's stack is the real :class:`tools.stack.up.Stack` of the real plan (its data
directory claimed, its ports checked), with its children left unstarted and the flights
replaced by one canned row: what is checked is what the demo writes and prints around
them. The dashboard takes ``/?token=<admin token>`` once and keeps a session cookie
(services/dashboard/routes.py), so the printed address must, as a shell expands it, carry
the very token the dashboard child was given, read from a 0600 file, never printed itself.
"""

from __future__ import annotations

import os
import re
import signal
import stat
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest

from shared.process import Child, ChildSpec
from tools.demo import flights
from tools.stack.up import Ports, Stack, StackOptions, data_dir_holder, hardware_scenario

ROW = {"name": "1-nominal", "expected": "red-box", "outcome": "ok", "ended_in": "red-box",
       "anomaly_at_s": None, "decision": None, "decision_source": None,
       "constraint_violations": 0, "what_happened": "it flew the nominal route"}


class Unflown(Stack):
    """The real stack, its children never started; ``dies``: a service (a real process)
    that exits with status 3 whenever it starts, as one that crashes after the flights (it
    is started again after 0.05 s, doubling, as `aesop up`'s supervision does after 1 s)."""

    last: ClassVar[Unflown | None] = None
    dies: ClassVar[bool] = False

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **{"restart_delay_s": 0.05, **kwargs})
        Unflown.last = self

    def start(self) -> None:
        self.claim()
        if self.dies:
            spec = ChildSpec("control", (sys.executable, "-c", "raise SystemExit(3)"), 0,
                             dict(os.environ))
            self.children = [Child(spec, self.sink)]
            self.children[0].start()


def fly_nothing(*_: Any, **__: Any) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    return ({"ok": True, "scenarios": [dict(ROW)], "detector": {}, "state_rate_hz": 100.0},
            {"1-nominal": np.zeros((0, 12))})


@pytest.fixture
def demo(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    monkeypatch.setattr(flights, "Stack", Unflown)
    monkeypatch.setattr(flights, "fly_scenarios", fly_nothing)
    Unflown.last, Unflown.dies = None, False
    before = signal.getsignal(signal.SIGTERM)  # the demo turns SIGTERM into Ctrl-C
    yield
    signal.signal(signal.SIGTERM, before)


def options(out: Path) -> StackOptions:
    return StackOptions(data_dir=out / "data", ports=Ports.free(), scenario=hardware_scenario())


def token_given_to(stack: Stack, child: str) -> str:
    spec = next(c.spec for c in stack.children if c.name == child)
    return spec.env["AESOP_ADMIN_TOKEN"]


def test_the_demo_keeps_its_token_0600_and_prints_a_dashboard_address_that_logs_in(
        demo: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "report"
    result = flights.run_stack_demo(options(out), {}, out)
    token_file = out / "data" / "admin-token"
    assert stat.S_IMODE(token_file.lstat().st_mode) == 0o600
    token = token_file.read_text().strip()
    assert Unflown.last is not None
    assert token_given_to(Unflown.last, "dashboard") == token  # the dashboard's own
    url = result["dashboard"]
    assert url and url.startswith("http://127.0.0.1:")
    printed = capsys.readouterr()
    address = f"{url}/?token=$(cat {token_file})"
    assert f"dashboard: {address}" in printed.out  # the summary's line
    assert address in printed.err  # and the one before the flights, to watch them live
    assert str(token_file) in printed.out
    # as a person pastes it into a shell (xdg-open "..."): the dashboard's login address
    expanded = subprocess.run(["bash", "-c", f'printf %s "{address}"'], capture_output=True,
                              text=True, check=True).stdout
    assert expanded == f"{url}/?token={token}"
    # the token itself is in none of what is printed or kept, but its file
    assert token not in printed.out + printed.err
    kept = [p for p in out.rglob("*") if p.is_file() and p != token_file]
    assert kept and not [p for p in kept if token in p.read_text(errors="replace")]
    assert data_dir_holder(out / "data") is None  # the stack stopped with the demo


def test_a_token_from_the_environment_is_neither_written_nor_printed(
        demo: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "report"
    token = "from-the-environment-" + "x" * 16
    result = flights.run_stack_demo(options(out), {"AESOP_ADMIN_TOKEN": token}, out)
    assert not (out / "data" / "admin-token").exists()
    printed = capsys.readouterr()
    assert f"dashboard: {result['dashboard']}/?token=$AESOP_ADMIN_TOKEN" in printed.out
    assert token not in printed.out + printed.err


def test_keep_up_supervises_the_stack_as_aesop_up_does_and_ends_when_a_service_keeps_dying(
        demo: None, tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "report"
    Unflown.dies = True
    monkeypatch.setattr(flights, "write_report", lambda out, *_: out / "index.html")
    rescued = threading.Event()

    def rescue() -> None:  # the demo must not wait on a dead stack: end it after 60 s
        if Unflown.last is not None and not Unflown.last.stopping.is_set():
            rescued.set()
            Unflown.last.stopping.set()

    timer = threading.Timer(60.0, rescue)
    timer.start()
    try:
        result = flights.run_stack_demo(options(out), {}, out, keep_up=True)
    finally:
        timer.cancel()
    assert not rescued.is_set(), "--keep-up waited on a stack whose control loop had died"
    assert Unflown.last is not None and Unflown.last.restarts["control"] >= 1  # supervised
    assert result["stack_stopped"].startswith("control exited with status 3")
    printed = capsys.readouterr()
    assert "the stack stays up" in printed.err
    assert re.search(r"control exited with status 3 .*; stopping the stack", printed.err)
    assert data_dir_holder(out / "data") is None  # stopped, its data dir let go


def test_the_command_fails_when_the_kept_stack_dies(monkeypatch: pytest.MonkeyPatch,
                                                    tmp_path: Path) -> None:
    from tools.demo import cli

    def died(*_: Any, **__: Any) -> dict[str, Any]:
        return {"ok": True, "scenarios": [], "stack_stopped": "control exited with status 3"}

    monkeypatch.setattr(flights, "run_stack_demo", died)
    monkeypatch.setattr("tools.stack.cli.stack_options", lambda *_: None)
    args = cli.argparse.Namespace(attach=False, out=tmp_path, model=None, json=False,
                                  keep_up=True)
    assert cli.cmd_demo(args) == 1
