"""Issue 44, item 4: any dead service stopped the whole stack, the control loop included,
even the read-only dashboard. `aesop up` now restarts each child as compose's restart
policy or systemd's ``Restart=`` would, with a delay that doubles while it keeps dying, and
stops the stack only when one child exits too often. Real child processes (small Python
scripts standing in for the services), the stack's own watch loop."""

from __future__ import annotations

import sys
import threading
from pathlib import Path

from shared.process import Child, ChildSpec
from tools.stack import up
from tools.stack.up import Ports, Stack, StackOptions, plan_stack

# exits with status 3 the first time (no marker yet), then runs until stopped
ONCE = """
import pathlib, sys, time
marker = pathlib.Path(sys.argv[1])
if not marker.exists():
    marker.write_text("died once")
    sys.exit(3)
time.sleep(600)
"""
ALWAYS = "import sys; sys.exit(3)"
RUNS = "import time; time.sleep(600)"


def stack_of(tmp: Path, children: dict[str, tuple[str, ...]]) -> tuple[Stack, list[str]]:
    options = StackOptions(data_dir=tmp / "data", ports=Ports(1, 2, 3, 4, 5, 6, 7),
                           rate_hz=5.0, python="py")
    said: list[str] = []
    stack = Stack(plan_stack(options, {}, "t" * 24), lambda name, line: said.append(line),
                  restart_delay_s=0.05)
    stack.hub = Child(ChildSpec("hub", (sys.executable, "-c", RUNS), 1, {}), stack.sink)
    stack.children = [Child(ChildSpec(name, (sys.executable, "-c", *argv), 2, {}), stack.sink)
                      for name, argv in children.items()]
    for child in [stack.hub, *stack.children]:
        child.start()
    return stack, said


def test_a_service_that_dies_is_started_again_and_the_rest_go_on(tmp_path: Path) -> None:
    stack, said = stack_of(tmp_path, {"dashboard": (ONCE, str(tmp_path / "marker")),
                                      "control": (RUNS,)})
    control = stack.children[1].pid
    died: list[str | None] = []
    watcher = threading.Thread(target=lambda: died.append(stack.watch()), daemon=True)
    watcher.start()
    try:
        for _ in range(100):  # until the dashboard was started again and runs
            if stack.restarts.get("dashboard") and stack.children[0].exited() is None:
                break
            watcher.join(0.1)
        assert stack.restarts == {"dashboard": 1}, (stack.restarts, said)
        assert stack.children[0].exited() is None  # running again
        assert stack.children[1].pid == control and stack.children[1].exited() is None
        assert any("dashboard exited with status 3: starting it again" in s for s in said)
    finally:
        stack.stopping.set()
        watcher.join(5)
        for child in [stack.hub, *stack.children]:
            child.signal(9)
    assert died == [None]  # stopped by the stop event, not by a death


def test_a_service_that_keeps_dying_stops_the_stack_naming_it(tmp_path: Path) -> None:
    stack, said = stack_of(tmp_path, {"control": (ALWAYS,), "embedding": (RUNS,)})
    try:
        died = stack.watch()
    finally:
        for child in [stack.hub, *stack.children]:
            child.signal(9)
    assert died is not None and died.startswith("control exited with status 3"), died
    assert stack.restarts["control"] == up.MAX_RESTARTS
    assert f"{up.MAX_RESTARTS + 1} times" in died
