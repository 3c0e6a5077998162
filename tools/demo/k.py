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

:func:`scene_with_k` writes the scene with that K for the control loop to load.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from services.control.controllers import make_controller
from services.control.loop import rest_at
from services.control.scenario import Scenario, ScenarioError, load_scenario
from services.reasoner.client import ReasonerClient
from services.reasoner.latency import min_samples

QUANTILE = CONFIDENCE = 0.95  # the paper's quantile; the bound's confidence
QUERIES = min_samples(QUANTILE, CONFIDENCE) + 1  # 60: the bound is the slowest answer
WARMUP = 2


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
