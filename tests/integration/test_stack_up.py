"""`aesop up` as a real process: every service ready behind one Zenoh hub, and
SIGINT stops them all (no orphan left)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import psutil
import pytest

from tests.zenoh_peers import wait_until

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(300)]

SERVICES = ("fake-llm", "embedding", "reasoner", "control", "dashboard")


def wait_for_urls(proc: subprocess.Popen[str], timeout_s: float = 240.0,
                  names: tuple[str, ...] = SERVICES) -> dict[str, str]:
    assert proc.stdout is not None
    urls: dict[str, str] = {}
    deadline = time.monotonic() + timeout_s
    for line in proc.stdout:
        parts = line.split()
        if len(parts) == 2 and parts[0] in names:
            urls[parts[0]] = parts[1]
        if line.startswith("Ctrl-C stops everything"):
            return urls
        assert time.monotonic() < deadline, "aesop up did not come up in time"
    raise AssertionError(f"aesop up exited early with status {proc.wait()}")


def test_up_serves_every_service_and_sigint_stops_them_all(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items()
           if k not in ("AESOP_ADMIN_TOKEN", "AESOP_REASONER_LLM_BASE_URL")}
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "up", "--random-ports", "--data-dir",
         str(tmp_path / "data")], env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
        stdin=subprocess.DEVNULL, text=True)
    try:
        urls = wait_for_urls(proc)
        assert set(urls) == set(SERVICES)
        for name, url in urls.items():
            assert httpx.get(f"{url}/readyz", timeout=5).status_code == 200, name
        token_file = tmp_path / "data" / "admin-token"
        assert token_file.stat().st_mode & 0o777 == 0o600
        auth = {"Authorization": f"Bearer {token_file.read_text().strip()}"}
        assert httpx.get(f"{urls['control']}/v1/state", timeout=5).status_code == 401
        state = httpx.get(f"{urls['control']}/v1/state", headers=auth, timeout=5).json()
        assert state["scenario"] == "paper-quadrotor-hardware"
        children = psutil.Process(proc.pid).children(recursive=True)
        assert len(children) >= 1 + len(SERVICES)  # the hub too
        pids = [c.pid for c in children]
        # those that must act on time run ahead of the rest, where the machine allows it
        nice = {_role(c.cmdline()): c.nice() for c in children}
        inherited = os.getpriority(os.PRIO_PROCESS, 0)
        favoured = -10 if _may_raise_priority() else inherited
        assert {nice["hub"], nice["control"], nice["sim"]} == {favoured}, nice
        assert nice["embedding"] == nice["dashboard"] == inherited, nice

        proc.send_signal(signal.SIGINT)
        assert proc.wait(60) == 0
        _, alive = psutil.wait_procs(children, timeout=10)
        assert alive == [], f"orphans: {alive}"
        for pid in pids:  # each child led its own process group: nothing is left in it
            with pytest.raises(ProcessLookupError):
                os.killpg(pid, 0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _role(cmdline: list[str]) -> str:
    if "tools.stack.router" in cmdline:
        return "hub"
    return cmdline[cmdline.index("serve") + 1] if "serve" in cmdline else " ".join(cmdline)


def _may_raise_priority() -> bool:
    probe = "import os; os.setpriority(os.PRIO_PROCESS, 0, -10)"
    return subprocess.run([sys.executable, "-c", probe], capture_output=True).returncode == 0


def test_up_rejects_a_missing_scenario_file(tmp_path: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "tools.cli", "up", "--random-ports",
                        "--scenario", str(tmp_path / "nope.yaml")],
                       capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert r.returncode == 2
    assert "--scenario" in r.stderr and "nope.yaml" in r.stderr


def test_a_second_up_on_the_data_dir_in_use_is_refused_and_the_first_serves_on(
        tmp_path: Path) -> None:
    """Issue 44: a second ``aesop up`` on a running stack's data dir exits 2 at once, naming
    the data dir and the first one's pid, and leaves its passwords and token as they were
    (it used to rewrite them and start most of a stack: the first's ``aesop watch`` line
    stopped working, and after its hub restarted no service could log in)."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("AESOP_ADMIN_TOKEN", "AESOP_REASONER_LLM_BASE_URL")}
    data = tmp_path / "data"
    argv = [sys.executable, "-m", "tools.cli", "up", "--random-ports", "--no-dashboard",
            "--data-dir", str(data)]
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            stdin=subprocess.DEVNULL, text=True)
    second: subprocess.Popen[str] | None = None
    try:
        urls = wait_for_urls(proc, names=("fake-llm", "embedding", "reasoner", "control"))
        kept = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in data.rglob("*")
                if p.is_file() and (p.parent.name == "zenoh" or p.name == "admin-token")}
        assert data / "zenoh" / "monitor.password" in kept and data / "admin-token" in kept
        second = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
        try:
            _, err = second.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            second.send_signal(signal.SIGINT)
            second.wait(90)
            raise AssertionError("the second aesop up went on starting a stack") from None
        assert second.returncode == 2, err
        assert str(data) in err and f"pid {proc.pid}" in err, err
        assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in kept} == kept
        for name, url in urls.items():
            assert httpx.get(f"{url}/readyz", timeout=5).status_code == 200, name
        proc.send_signal(signal.SIGINT)
        assert proc.wait(60) == 0
    finally:  # SIGINT first: a killed aesop up would leave its children behind
        for p in (second, proc):
            if p is not None and p.poll() is None:
                interrupt(p)


def test_up_serves_the_local_model_and_starts_it_again_when_it_dies(tmp_path: Path) -> None:
    """``aesop up --llm local``: llama.cpp's server with the bundled SmolLM2 in place of the
    fake LLM, the reasoner answered by the model; the server killed is started again."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("AESOP_ADMIN_TOKEN", "AESOP_REASONER_LLM_BASE_URL")}
    said = tmp_path / "up.log"
    with open(said, "w") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "tools.cli", "up", "--random-ports", "--no-dashboard",
             "--llm", "local", "--data-dir", str(tmp_path / "data")], env=env,
            stdout=subprocess.PIPE, stderr=log, stdin=subprocess.DEVNULL, text=True)
    try:
        urls = wait_for_urls(proc, names=("llm", "embedding", "reasoner", "control"))
        assert "fake-llm" not in urls and "llm" in urls
        token = (tmp_path / "data" / "admin-token").read_text().strip()
        auth = {"Authorization": f"Bearer {token}"}
        assert reason(urls["reasoner"], auth)["source"] == "llm"

        def server() -> list[psutil.Process]:
            return [c for c in psutil.Process(proc.pid).children(recursive=True)
                    if "llama_cpp.server" in " ".join(c.cmdline())]

        [first] = server()
        first.kill()
        first.wait(30)

        def answered_again() -> bool:
            assert proc.poll() is None, "aesop up stopped when its LLM server died"
            return bool(server()) and reason(urls["reasoner"], auth)["source"] == "llm"

        wait_until(answered_again, "the LLM server started again", 120.0)
        assert server()[0].pid != first.pid
        proc.send_signal(signal.SIGINT)
        assert proc.wait(60) == 0
        assert "llm exited with status" in said.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def reason(url: str, auth: dict[str, str]) -> dict[str, object]:
    body = {"observation": {"seq": 1, "task": "land the quadrotor on the red box",
                            "text": "another quadrotor is parked on the red box\n"
                                    "a blue box on the ground"},
            "options": [{"index": 0, "label": "continue"},
                        {"index": 1, "label": "alternative landing site"},
                        {"index": 2, "label": "holding zone"}],
            "deadline_s": 60.0}
    r = httpx.post(f"{url}/v1/reason", json=body, headers=auth, timeout=90)
    assert r.status_code == 200, r.text
    answer: dict[str, object] = r.json()
    return answer


def test_the_fly_line_aesop_up_prints_flies_2a_to_the_blue_box(tmp_path: Path) -> None:
    """Issue 44: after `aesop up`, nothing flew and nothing said how; its banner now says
    the `aesop demo --attach` that flies the hardware scenarios against it, as a newcomer
    would copy it (the cache built over REST, the flight judged on the vehicle's truth)."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("AESOP_") or k == "AESOP_LOG_LEVEL"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "up", "--random-ports", "--data-dir",
         str(tmp_path / "data")], env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
        stdin=subprocess.DEVNULL, text=True)
    try:
        assert proc.stdout is not None
        fly = None
        for line in proc.stdout:
            if "aesop demo --attach" in line:  # the command, on a line of its own
                fly = line.split()
            if line.startswith("Ctrl-C stops everything"):
                break
        assert fly is not None and fly[:3] == ["aesop", "demo", "--attach"], fly
        done = subprocess.run([sys.executable, "-m", "tools.cli", *fly[1:], "--scenario-name",
                               "2a", "--json", "--out", str(tmp_path / "report")], env=env,
                              capture_output=True, text=True, timeout=240)
        assert done.returncode == 0, done.stderr[-3000:]
        (row,) = json.loads(done.stdout.splitlines()[-1])["scenarios"]
        assert row["ended_in"] == "blue-box" and row["constraint_violations"] == 0, row
    finally:
        interrupt(proc)


def interrupt(proc: subprocess.Popen[str]) -> None:
    """Stop an ``aesop up`` as Ctrl-C does (it stops its children), killing it after 60 s."""
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(60)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
