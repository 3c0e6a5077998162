"""The demo's stack on free ports, as `aesop demo --random-ports` plans it (a Zenoh
router, the fake LLM or a served local model, the vector cache, the reasoner, the control
loop, the simulated vehicle and the dashboard, as processes), for the tests that fly the
demo's scenarios."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.control.core.scenario import load_scenario
from shared.process import file_sink
from shared.settings import BusSettings, read_settings
from tools.local_llm import LocalModel
from tools.stack.up import (
    Ports,
    Stack,
    StackOptions,
    StackPlan,
    child_names,
    fleet,
    hardware_scenario,
    loop_rate,
    plan_stack,
)


@dataclass(frozen=True)
class Running:
    """A stack that is up, with what it was planned from."""

    stack: Stack
    plan: StackPlan
    options: StackOptions
    environ: Mapping[str, str]


@contextlib.contextmanager
def running_stack(tmp_path: Path, token: str, *, local_model: LocalModel | None = None,
                  environ: Mapping[str, str] | None = None,
                  ros2: Path | None = None, robots: int = 1, replicas: int = 1,
                  data_dir: Path | None = None, **role: Any) -> Iterator[Running]:
    """Up with its data in ``tmp_path/data`` (or ``data_dir``) and logs in
    ``tmp_path/logs`` (``environ``: variables over this process's); stopped whatever
    happens. The control loop runs at the scene's rate unless ``AESOP_CONTROL_RATE_HZ``
    says otherwise; ``ros2``: the bridge with this config instead of the simulated
    vehicle; ``robots``, ``replicas``: a fleet (a ``data_dir`` PostgreSQL's user can
    reach, with replicas); ``role``: what ``aesop up --role`` gives (``role``, ``tls``,
    ``server``, ``linked``, ``listen``)."""
    path = hardware_scenario()
    scene = load_scenario(path)
    env = {k: v for k, v in {**os.environ, **(environ or {})}.items()
           if k != "AESOP_ADMIN_TOKEN"}
    rate = None if env.get("AESOP_CONTROL_RATE_HZ") else loop_rate(1.0 / scene.dt, robots)
    names = child_names(fleet(read_settings(BusSettings, env).robot, robots), replicas)
    options = StackOptions(data_dir=data_dir or tmp_path / "data",
                           ports=Ports.free([n for kind in names.values() for n in kind[1:]]),
                           scenario=path, rate_hz=rate, local_model=local_model, ros2=ros2,
                           robots=robots, replicas=replicas, **role)
    plan = plan_stack(options, env, token)
    running = Stack(plan, file_sink(tmp_path / "logs"))
    try:
        running.start()
        yield Running(running, plan, options, env)
    finally:
        running.stop()


@contextlib.contextmanager
def demo_stack(tmp_path: Path, token: str) -> Iterator[StackPlan]:
    """:func:`running_stack` with the fake LLM; its plan."""
    with running_stack(tmp_path, token) as up:
        yield up.plan
