"""``aesop demo --attach --measure-k`` (issue 42, item 4) against a stack of ``aesop up``'s
as processes: K is measured on the model the stack's reasoner asks, exactly as ``aesop demo
--llm local`` measures it (the reasoner's calibration job while the robot flies the
nominal scenario), but the stack's control loop is not the demo's to restart: the flight
has the K that loop flies (its scene's, control reporting no K), the scene with the K
chosen is written to the report's folder, and the command to fly it is said. Started again
on that file, as ``aesop up --scenario FILE`` would start it, the loop's K is read back.

The model is the fake LLM answering in 0.3 s (60 answers in a minute, not the real model's
several: the real model's run is in docs/demo.md), so the K chosen (about 0.35 s) is not
the scene's 4.3 s.
"""

from __future__ import annotations

import asyncio
import json
import os
import secrets
import shlex
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from services.control.client import ControlClient
from services.control.core.scenario import load_scenario
from tests.demo_stack import running_stack
from tools.demo.k import QUERIES, SCENE_FILE, control_k, how_to_fly
from tools.stack.up import fly_command, hardware_scenario, plan_stack

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(420)]

TOKEN = secrets.token_urlsafe(24)
SCENE = load_scenario(hardware_scenario())


async def flown_scene(url: str) -> str:
    async with ControlClient(url, token=TOKEN) as control:
        return (await control.state()).scenario


def test_k_is_measured_on_an_attached_stack_and_the_loops_own_k_is_flown(
        tmp_path: Path) -> None:
    fast = {"AESOP_FAKE_LLM_FIXED_S": "0.3"}
    out = tmp_path / "report"
    with running_stack(tmp_path, TOKEN, environ=fast) as up:
        fly, reasoner = fly_command(up.plan), up.plan.url("reasoner")
        assert fly is not None and reasoner is not None
        env = {k: v for k, v in os.environ.items() if not k.startswith("AESOP_")}
        wrong = subprocess.run(  # no reasoner there: said before anything is built
            [sys.executable, "-m", "tools.cli", *shlex.split(fly)[1:], "--measure-k",
             "--reasoner-url", f"{up.plan.url('embedding')}/nothing", "--out", str(out)],
            env={**env, "AESOP_ADMIN_TOKEN": TOKEN}, capture_output=True, text=True,
            timeout=60, stdin=subprocess.DEVNULL)
        assert wrong.returncode == 2 and "--reasoner-url" in wrong.stderr, wrong.stderr
        assert "building" not in wrong.stderr and not out.exists()
        done = subprocess.run(
            [sys.executable, "-m", "tools.cli", *shlex.split(fly)[1:], "--measure-k",
             "--reasoner-url", reasoner, "--scenario-name", "2a", "--json", "--out", str(out)],
            env={**env, "AESOP_ADMIN_TOKEN": TOKEN}, capture_output=True, text=True,
            timeout=360, stdin=subprocess.DEVNULL)
        assert done.returncode == 0, done.stderr[-3000:]
        assert "timing the model" in done.stderr
        printed = json.loads(done.stdout.splitlines()[-1])
        k, (row,) = printed["k"], printed["scenarios"]
        said = json.dumps(printed, default=str)
        # measured and chosen as --llm local chooses: the 95 % quantile, kept by the scene
        assert k["calibration"]["n"] == QUERIES and 0.3 <= k["measured_s"] <= 1.5, said
        assert k["chosen_s"] == k["measured_s"] and "quantile" in k["why"]
        # flown: the loop's own K, the scene's (control names its scene, not its K)
        assert k["flown_s"] == SCENE.consensus_s and "not its K" in k["control"], said
        assert "fallback" in k["later"]
        assert row["outcome"] == "ok" and row["constraint_violations"] == 0, said
        assert row["decision_latency_ms"] <= SCENE.consensus_s * 1000.0 + 50.0
        # the scene with the K chosen, and how to fly it on aesop up (--data-dir: not compose)
        scene = Path(k["scene_file"])
        assert scene == out / SCENE_FILE and load_scenario(scene).consensus_s == k["chosen_s"]
        assert k["to_fly_chosen"] == list(how_to_fly(scene, compose=False))
        assert k["to_fly_chosen"][1] == f"aesop up --scenario {scene}"
        assert json.loads((out / "result.json").read_text())["k"] == k
        assert "The model's decisions" in (out / "index.html").read_text()
        # the loop started again on that file (as aesop up --scenario FILE starts it): its K
        again = plan_stack(replace(up.options, scenario=scene), up.environ, TOKEN,
                           passwords=lambda _: dict(up.plan.passwords))
        up.stack.replace(next(s for s in again.services if s.name == "control"))
        url = up.plan.url("control")
        assert url is not None
        assert control_k(asyncio.run(flown_scene(url)), SCENE)[0] == k["chosen_s"]
