"""K for a demo flown with a real model: measured on the served model, kept if the scene can.

The paper chose K from its model's measured latencies (appendix "Choosing K"): the 95 %
quantile of 500 queries. With ``aesop demo --llm local`` the stack serves a model whose
latency nobody has measured on this machine, so the demo measures it first, with the
reasoner's own calibration job (``POST /v1/latency/calibrate``: the served model asked the
question of scenario 2a, the prompt the demo's flights will send) under the load of the
running stack. :func:`choose_k` turns that job's report into the K the flights use:

* the 95 % empirical quantile of the answers' latencies (``k_s``, the paper's rule),
  rounded up to a tick; the distribution-free upper bound on the true quantile at 95 %
  confidence (``k_upper_s``; with :data:`QUERIES` queries, the slowest answer) is reported
  beside it (one slow answer in 60 decides it: 10.7 s on a first run, p95 4.1 s);
* kept only if the scene can keep it: K below T and the tree of recovery plans feasible
  at the start (a probe of the controller, :func:`tree_at_start`); the MPC cannot promise
  every recovery after a longer wait. Otherwise the scene's own K is flown and the report
  says why (the decisions that come later than it become the control loop's fallback).

:func:`measure_k` is the whole measurement, shared by ``aesop demo --llm local`` (which
then starts its control loop again with the K chosen) and ``aesop demo --attach
--measure-k`` (whose stack's loop is not its own to restart: it flies the K that loop has,
:func:`control_k`, and says how to fly the one chosen). :func:`scene_with_k` writes the
scene with that K for a control loop to load; :func:`k_record` is what the report keeps.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import shlex
import threading
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from services.control.core.controllers import make_controller
from services.control.core.dynamics import rest_at
from services.control.core.scenario import Scenario, ScenarioError, load_scenario
from services.reasoner.client import ReasonerClient
from services.reasoner.latency import min_samples
from shared.client import ServiceError
from tools import progress

QUANTILE = CONFIDENCE = 0.95  # the paper's quantile; the bound's confidence
QUERIES = min_samples(QUANTILE, CONFIDENCE) + 1  # 60: the bound is the slowest answer
WARMUP = 2
SCENE_FILE = "scene-with-k.yaml"  # in aesop demo --attach's --out
SCENE_OVERRIDE = "deploy/compose.scene.yml"  # mounts $AESOP_SCENE_FILE as control's scene
LOAD_FLIGHTS = 20  # nominal flights at most while the model is timed (about 30 s each)
LOAD_SCENARIO = "1-nominal"

# flies the named demo scenarios (none: only builds the detector's cache) until the event
# is set (None: all of them); the flights' result (``scenarios``: a row per flight)
Fly = Callable[[Sequence[str], threading.Event | None], Mapping[str, Any]]


@dataclass(frozen=True)
class KChoice:
    """The K the demo flies and where it came from."""

    k_s: float  # flown
    scene_k_s: float  # the scene's own
    measured_k_s: float | None  # the calibration's bound, rounded up to a tick
    report: Mapping[str, Any]  # the calibration job's result (latencies in s)
    why: str  # one sentence for the report

    @property
    def calibrated(self) -> bool:
        return self.measured_k_s is not None and self.k_s == self.measured_k_s


def tree_at_start(scenario: Scenario) -> str | None:
    """Why the scene's MPC cannot fly its tree from the start at its K (None: it can)."""
    try:
        controller = make_controller("aesop", scenario)
    except ValueError as exc:  # e.g. the tree's reserve does not fit in T - K
        return f"the scene's MPC refuses it ({exc})"
    out = controller.make_step(rest_at(scenario.start_center), False)
    if not out.active_regions:
        return ("no tree of recovery plans is feasible from the start: the robot could not "
                "promise every recovery after waiting that long")
    return None


def choose_k(scenario: Scenario, report: Mapping[str, Any]) -> KChoice:
    """The K to fly from a calibration ``report`` (module docstring)."""
    bound = report.get("k_s")
    scene_k = scenario.consensus_s
    if bound is None or not math.isfinite(bound):
        why = report.get("error", "too many failed queries")
        return KChoice(scene_k, scene_k, None, report, f"the calibration gave no bound ({why}):"
                       f" flying the scene's K = {scene_k:g} s")
    ticks = max(1, math.ceil(bound / scenario.dt - 1e-9))
    measured = round(ticks * scenario.dt, 6)
    if measured >= scenario.horizon_s:
        why = f"K = {measured:g} s is not below T = {scenario.horizon_s:g} s"
    else:
        try:
            why = tree_at_start(dataclasses.replace(scenario, consensus_s=measured)) or ""
        except ScenarioError as exc:
            why = str(exc)
    if why:
        return KChoice(scene_k, scene_k, measured, report,
                       f"measured K = {measured:g} s cannot be flown ({why}): flying the "
                       f"scene's K = {scene_k:g} s; answers later than that end as the "
                       "control loop's fallback")
    return KChoice(measured, scene_k, measured, report,
                   f"K = {measured:g} s: the {QUANTILE:.0%} quantile of {report['n']} answers' "
                   f"latencies (the scene's own: {scene_k:g} s)")


def scene_with_k(source: Path, k_s: float, out: Path) -> Path:
    """``source``'s scene with ``consensus_s = k_s``, written to ``out`` (checked by
    loading it)."""
    data = yaml.safe_load(source.read_text(encoding="utf-8"))
    data["consensus_s"] = k_s
    data["name"] = f"{data.get('name', source.stem)}-k{k_s:g}"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    load_scenario(out)
    return out


async def calibrate(url: str, token: str, *, n: int = QUERIES,
                    say: Any = None) -> dict[str, Any]:
    """The reasoner's latency calibration job on its primary backend, asked scenario 2a's
    question; the job's report."""
    from tools.bench.templates import hardware_cases  # the bench's cases: the demo's prompt

    case = hardware_cases(60.0)[0]
    async with ReasonerClient(url, token=token, timeout_s=60) as client:
        job = await client.calibrate_latency(
            n=n, warmup=WARMUP, quantile=QUANTILE, confidence=CONFIDENCE, timeout_s=60.0,
            observation=case.request.observation, options=case.request.options)
        done = await client.wait_for_job(job.job, progress=say, poll_s=1.0)
    assert done.result is not None
    return dict(done.result)


def time_the_model(url: str, token: str) -> dict[str, Any]:
    """The calibration job's report (or why it failed)."""
    try:
        report = asyncio.run(calibrate(url, token, say=lambda job: progress.count(
            job.done, job.total, "answers")))
    except ServiceError as exc:  # every query failed: the job says why
        report = {"error": str(exc)}
    return report


def measure_k(scenario: Scenario, reasoner_url: str, token: str, fly: Fly) -> KChoice:
    """The served model timed by the reasoner at ``reasoner_url`` (:func:`calibrate`) while
    the robot flies the nominal scenario again and again (``fly``), the detector's cache
    built before, and the K chosen from it (:func:`choose_k`). The model shares the cores
    with the control loop and the detector, as it will in the scenarios: timed on an idle
    stack, SmolLM2's 95 % quantile was 2.6 s and every answer in flight came later; timed
    while the cache was built, a few took 20 s."""
    fly([], None)  # the cache, built first
    progress.step(f"timing the model: {QUERIES} answers to scenario 2a's question while the "
                  "robot flies the nominal scenario (a few minutes)")
    done = threading.Event()
    with ThreadPoolExecutor(1) as pool:
        flying = pool.submit(fly, [LOAD_SCENARIO] * LOAD_FLIGHTS, done)
        try:
            report = time_the_model(reasoner_url, token)
        finally:
            done.set()
        flown = len(flying.result()["scenarios"])
    progress.say(f"  timed during {flown} nominal flights")
    choice = choose_k(scenario, report)
    progress.say(choice.why)
    return choice


def k_record(choice: KChoice) -> dict[str, Any]:
    """What the report and result.json keep of a K measured and chosen (``flown_s``: the
    K the flights had, the one chosen unless the caller says otherwise)."""
    return {"flown_s": choice.k_s, "chosen_s": choice.k_s, "scene_s": choice.scene_k_s,
            "measured_s": choice.measured_k_s, "why": choice.why,
            "calibration": dict(choice.report)}


def control_k(flown: str, scenario: Scenario) -> tuple[float, str]:
    """The K a control loop flies whose ``GET /v1/state`` names the scene ``flown``, and
    how that is known: control reports its scene's name, not its K. ``scenario``'s name is
    ``scenario``'s K; the name :func:`scene_with_k` gives (``<name>-k<K>``) carries the K
    it wrote; any other scene's K is not known, and ``scenario``'s is assumed."""
    if flown == scenario.name:
        return scenario.consensus_s, (
            f"control flies the scene {flown!r} (its GET /v1/state names the scene, not its "
            f"K): K = {scenario.consensus_s:g} s, the scene's")
    prefix = f"{scenario.name}-k"
    try:
        k_s = float(flown.removeprefix(prefix)) if flown.startswith(prefix) else math.nan
    except ValueError:
        k_s = math.nan
    if math.isfinite(k_s) and 0.0 < k_s < scenario.horizon_s:
        return k_s, (f"control flies {flown!r}, the scene written with K = {k_s:g} s (its "
                     "GET /v1/state names the scene, not its K)")
    return scenario.consensus_s, (
        f"control flies a scene of its own, {flown!r}, and does not report its K: taken as "
        f"{scenario.name}'s K = {scenario.consensus_s:g} s")


def how_to_fly(path: Path, compose: bool) -> tuple[str, str]:
    """What to do to fly the scene at ``path`` (its K) on a stack this demo did not start:
    ``aesop up``'s ``--scenario``, or compose's scene override (``compose``). A sentence,
    and the command (one line, to copy)."""
    if not compose:
        return ("stop aesop up (Ctrl-C) and start it again on that scene, with the options "
                "it ran with (e.g. --llm local):",
                f"aesop up --scenario {shlex.quote(str(path))}")
    return (f"start control again on that scene: {SCENE_OVERRIDE} mounts it (from the "
            "repository's root; the files the stack came up with, then the override, e.g. "
            "with deploy/compose.smollm2.yml; deploy/README.md):",
            f"AESOP_SCENE_FILE={shlex.quote(str(path))} docker compose -f docker-compose.yml "
            f"-f deploy/compose.smollm2.yml -f {SCENE_OVERRIDE} up -d control")
