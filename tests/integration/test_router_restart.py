"""The Zenoh router dies mid-flight and comes back (issue 14). ``aesop up``'s supervisor
starts the hub again on its port; every service is a client that reconnects by itself;
the control loop takes the silence as an anomaly meanwhile; no service exits; the
dashboard shows the services gone, then back; the flight still ends in a region."""

from __future__ import annotations

import os
import re
import signal
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest

from shared.process import file_sink
from tools.demo.flights import fly_scenarios
from tools.stack.up import Ports, Stack, StackOptions, plan_stack

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(420)]

TOKEN = "restart-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SERVICES = ("embedding", "reasoner", "control", "dashboard")


def wait_for(cond: object, what: str, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():  # type: ignore[operator]
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def test_the_router_restarts_mid_flight_and_the_stack_carries_on(tmp_path: Path) -> None:
    environ = {k: v for k, v in os.environ.items() if k != "AESOP_ADMIN_TOKEN"}
    plan = plan_stack(StackOptions(data_dir=tmp_path / "data", ports=Ports.free()), environ,
                      TOKEN)
    stack = Stack(plan, file_sink(tmp_path / "logs"), restart_delay_s=2.0)
    control, dashboard = plan.url("control"), plan.url("dashboard")
    http = httpx.Client(headers=AUTH, timeout=10)

    def alive() -> dict[str, bool]:
        return http.get(f"{dashboard}/v1/snapshot").json()["services"]

    died: list[str | None] = []
    try:
        stack.start()
        watcher = threading.Thread(target=lambda: died.append(stack.watch()), daemon=True)
        watcher.start()
        pids = {c.name: c.pid for c in stack.children}
        with ThreadPoolExecutor(1) as pool:
            flight = pool.submit(fly_scenarios, plan, ["1-nominal"])
            wait_for(lambda: http.get(f"{control}/v1/state").json()["mode"] == "nominal",
                     "the flight to start")
            time.sleep(1.0)
            hub_pid = stack.hub.proc.pid  # type: ignore[union-attr]
            os.killpg(hub_pid, signal.SIGKILL)  # the router dies without a word
            states, seen = [], []  # control and the dashboard while the hub is down (2 s)
            while stack.hub_restarts == 0 or stack.hub.exited() is not None \
                    or not stack.hub.is_ready():
                states.append(http.get(f"{control}/v1/state").json())
                seen.append(alive())
                time.sleep(0.05)
            assert stack.hub_restarts == 1
            others = [s for s in SERVICES if s != "dashboard"]
            assert any(not any(v.get(s, False) for s in others) for v in seen), seen
            wait_for(lambda: all(alive().get(s, False) for s in SERVICES if s != "dashboard"),
                     "the dashboard to show every service back", 60)
            result, _ = flight.result(timeout=300)
        row = result["scenarios"][0]
        assert row["ended_in"] in {"red-box", "blue-box", "holding-zone"}, row
        assert row["constraint_violations"] == 0
        silent = [st for st in states if st["verdict_stale"]]
        assert silent, states  # the silence was seen ...
        assert {st["mode"] for st in silent} - {"nominal"}, silent  # ... as an anomaly
        metrics = http.get(f"{control}/metrics").text
        alarms = re.search(r"^aesop_control_stale_verdict_alarms_total (\S+)$", metrics, re.M)
        # a silent spell at least: the verdicts may come back and pause once more while the
        # detector's and control's sessions find the new hub one after the other (a CI run
        # on a loaded machine counted more than one)
        assert alarms is not None and float(alarms.group(1)) >= 1.0, alarms
        assert "aesop_control_tick_errors_total 0.0" in metrics
        assert died == [] and all(c.exited() is None for c in stack.children)
        assert {c.name: c.pid for c in stack.children} == pids  # nobody restarted
        assert stack.hub.proc.pid != hub_pid  # type: ignore[union-attr]
    finally:
        stack.stopping.set()
        stack.stop()
        http.close()
