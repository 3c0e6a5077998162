"""Issue 44, item 1: a second stack on a data dir in use, or on a port in use, is refused at
once, before it writes a credential or starts a process. A second `aesop up` on the data
dir of a running one used to rewrite its Zenoh passwords and admin token, start most of a
stack and only stop when embedding found its lock: the first stack's `aesop watch` line
stopped working, and once its hub restarted no service could log in again.

The first stack here is a process holding ``<data-dir>/aesop-up.lock`` as ``aesop up``
does; the plans' children would exit at once (``true``), so even without the checks no
real service starts."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from shared.process import Child, free_port
from tools import cli
from tools.stack import up
from tools.stack.acl import write_credentials
from tools.stack.up import PlanError, Ports, Stack, StackOptions, plan_stack

LOCK = "aesop-up.lock"
TRUE = shutil.which("true") or "/bin/true"
HOLD = """
import fcntl, os, sys
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o600)
fcntl.flock(fd, fcntl.LOCK_EX)
os.ftruncate(fd, 0)
os.write(fd, f"{os.getpid()}\\n".encode())
print("held", flush=True)
sys.stdin.read()
"""
PROBE = """
import fcntl, os, sys
fd = os.open(sys.argv[1], os.O_RDONLY)
try:
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
except BlockingIOError:
    sys.exit(1)
"""


def first_stack(data: Path) -> dict[Path, tuple[bytes, int]]:
    """What a running stack left in ``data``: its credentials and token; each file's bytes
    and mtime."""
    write_credentials(data / "zenoh", {"monitor": "first-monitor", "embedding": "first-emb"})
    (data / "admin-token").write_text("first-token\n")
    return snapshot(data)


def snapshot(data: Path) -> dict[Path, tuple[bytes, int]]:
    return {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(data.rglob("*"))
            if p.is_file()}


@pytest.fixture
def holder(tmp_path: Path) -> Iterator[subprocess.Popen[str]]:
    """Another process holding ``tmp_path/data``'s lock, as a running ``aesop up`` does."""
    (tmp_path / "data").mkdir()
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(tmp_path / "data" / LOCK)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "held\n"
        yield proc
    finally:
        proc.kill()
        proc.wait()


def plan_in(data: Path) -> up.StackPlan:
    return plan_stack(StackOptions(data_dir=data, ports=Ports.free(), python=TRUE),
                      {"PATH": "/usr/bin:/bin"}, "t" * 24)


def held(lock: Path) -> bool:
    return subprocess.run([sys.executable, "-c", PROBE, str(lock)]).returncode == 1


def test_a_stack_refuses_a_data_dir_another_process_holds_touching_nothing(
        tmp_path: Path, holder: subprocess.Popen[str]) -> None:
    data = tmp_path / "data"
    before = first_stack(data)
    stack = Stack(plan_in(data), lambda *_: None, ready_timeout_s=5.0)
    try:
        with pytest.raises(PlanError) as refused:
            stack.start()
        assert stack.pids == {}  # nothing started
    finally:
        stack.stop(grace_s=1.0)
    assert str(data) in str(refused.value) and f"pid {holder.pid}" in str(refused.value)
    assert snapshot(data) == before  # the first stack's passwords and token, untouched
    assert held(data / LOCK)


def test_the_stack_holds_its_data_dir_while_up_and_lets_it_go_when_stopped(
        tmp_path: Path) -> None:
    data = tmp_path / "data"
    stack = Stack(plan_in(data), lambda *_: None)
    stack.claim()
    try:
        assert held(data / LOCK)
        assert (data / LOCK).read_text().strip() == str(os.getpid())
        stack.claim()  # again: it is already ours
        second = Stack(plan_in(data), lambda *_: None)
        with pytest.raises(PlanError, match="in use"):
            second.claim()
    finally:
        stack.stop(grace_s=1.0)
    assert not held(data / LOCK)
    again = Stack(plan_in(data), lambda *_: None)
    again.claim()
    again.stop(grace_s=1.0)


@pytest.mark.parametrize("listening", [True, False])
def test_a_stack_refuses_a_port_in_use_naming_it_before_writing_anything(
        tmp_path: Path, listening: bool) -> None:
    data = tmp_path / "data"
    plan = plan_in(data)
    stack = Stack(plan, lambda *_: None, ready_timeout_s=5.0)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", plan.hub.port))  # bound; a listener or not, it is taken
        if listening:
            taken.listen()
        try:
            with pytest.raises(PlanError) as refused:
                stack.start()
            assert stack.pids == {}
        finally:
            stack.stop(grace_s=1.0)
    said = str(refused.value)
    assert str(plan.hub.port) in said and "hub" in said and "--random-ports" in said
    assert not (data / "zenoh").exists()  # no credential written
    assert not held(data / LOCK)  # and the data dir is free again


def test_a_port_bound_but_not_listening_is_busy() -> None:
    port = free_port()
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", port))
        assert Ports(hub=port).busy(["hub"]) == [f"hub:{port}"]
    assert Ports(hub=port).busy(["hub"]) == []


@pytest.mark.parametrize(("argv", "flag"), [
    (["up", "--random-ports", "--data-dir", "{data}"], "--data-dir"),
    (["demo", "--random-ports", "--out", "{out}"], "--out"),  # its data dir: <out>/data
])
def test_up_on_a_data_dir_in_use_exits_2_at_once_naming_it_and_its_holder(
        tmp_path: Path, holder: subprocess.Popen[str], monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str], argv: list[str], flag: str) -> None:
    data = tmp_path / "data"
    before = first_stack(data)
    argv = [a.format(data=data, out=tmp_path) for a in argv]

    def no_process(self: Child) -> None:
        raise AssertionError(f"aesop up started {self.name} on a data dir in use")

    monkeypatch.setattr(Child, "start", no_process)
    monkeypatch.setattr(up, "install_stop_handlers", lambda stop: None)
    monkeypatch.delenv("AESOP_ADMIN_TOKEN", raising=False)
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert str(data) in err and f"pid {holder.pid}" in err and flag in err
    assert snapshot(data) == before
