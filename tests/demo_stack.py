"""The demo's stack on free ports, as `aesop demo --random-ports` plans it (a Zenoh
router, the fake LLM, the vector cache, the reasoner, the control loop and the
dashboard, as processes), for the tests that fly the demo's scenarios."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from services.control.scenario import load_scenario
from shared.process import file_sink
from tools.stack.up import Ports, Stack, StackOptions, StackPlan, hardware_scenario, plan_stack


@contextlib.contextmanager
def demo_stack(tmp_path: Path, token: str) -> Iterator[StackPlan]:
    """Up with its data in ``tmp_path/data`` and logs in ``tmp_path/logs``; stopped
    whatever happens. The control loop runs at the scene's rate unless
    ``AESOP_CONTROL_RATE_HZ`` says otherwise."""
    path = hardware_scenario()
    scene = load_scenario(path)
    rate = None if os.environ.get("AESOP_CONTROL_RATE_HZ") else 1.0 / scene.dt
    options = StackOptions(data_dir=tmp_path / "data", ports=Ports.free(), scenario=path,
                           rate_hz=rate)
    environ = {k: v for k, v in os.environ.items() if k != "AESOP_ADMIN_TOKEN"}
    plan = plan_stack(options, environ, token)
    running = Stack(plan, file_sink(tmp_path / "logs"))
    try:
        running.start()
        yield plan
    finally:
        running.stop()
