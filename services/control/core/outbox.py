"""What one tick says, as pure functions: the request to the reasoner, the controller's
state and plan, and the events of a mode change.

:class:`~services.control.loop.ControlRuntime` owns the time and the counters (the tick's ``t``, the
set-point's ``seq``, the seconds left to the reasoner, a fresh ``request_id``) and hands
them in; everything here is data in, messages out, so the rules can be read and tested
apart from the loop.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from shared.messages import (
    AnomalyVerdict,
    ControlState,
    Event,
    Mode,
    Observation,
    Option,
    PlanSnapshot,
    ReasonerRequest,
    Severity,
)

from .aesop import ControlOutput
from .dynamics import POS
from .mpc import Plan
from .regions import Region
from .verdicts import UNMONITORED, Cause

SOURCE = "control"
SILENT = ("the anomaly detector has gone silent: no verdict answers a recent observation, "
          "so the scene is unmonitored and continuing is not an option")
BLIND = ("the vehicle's state has stopped arriving (or was refused): the robot flies blind on "
         "its last verified recovery branch, so continuing is not an option")


def event(robot: str, kind: str, severity: Severity, message: str,
          **data: str | int | float | bool | None) -> Event:
    """An event of the control loop."""
    return Event(robot=robot, source=SOURCE, kind=kind, severity=severity, message=message,
                 data=data)


def options_for(regions: Sequence[Region], offered: Sequence[int], *,
                continue_: bool = True) -> tuple[Option, ...]:
    """Option 0 (continue, unless ``continue_`` is false) plus one option per offered
    region, for the reasoner."""
    by_index = {r.index: r for r in regions}
    options = [Option(index=0, label="continue", description="keep flying the nominal task")
               ] if continue_ else []
    for index in offered:
        region = by_index[index]
        center = (np.asarray(region.position_lo) + np.asarray(region.position_hi)) / 2
        where = ", ".join(f"{v:.1f}" for v in center)
        what = "land" if region.kind == "landing" else "hover"
        options.append(Option(index=index, label=region.label,
                              description=f"{what} at {region.name} ({where}) m"))
    return tuple(options)


def request(*, robot: str, request_id: str, cause: Cause | None,
            verdict: AnomalyVerdict | None, observation: Observation | None,
            regions: Sequence[Region], offered: Sequence[int],
            deadline_s: float) -> ReasonerRequest:
    """The question to the reasoner for the regions ``offered``.

    When the cause is silence (of the detector, or of the vehicle) the reasoner is told
    so, in place of the scene, and "continue" is not offered: nothing watches the scene.
    Otherwise the observation the verdict judged is asked about, with what the verdict
    found unusual (its detections, its pair)."""
    silent = cause in UNMONITORED
    seq_of_verdict = 0 if verdict is None else verdict.seq
    if silent:
        last = "" if observation is None else f"; the last observation:\n{observation.text}"
        why = SILENT if cause is Cause.SILENCE else BLIND
        seq = seq_of_verdict if observation is None else observation.seq
        observation = Observation(robot=robot, seq=seq, text=why + last)
    elif observation is None:
        text = "the anomaly detector flagged the scene; no observation text was received"
        observation = Observation(robot=robot, seq=seq_of_verdict, text=text)
    named = verdict if verdict is not None and verdict.is_anomaly and not silent else None
    return ReasonerRequest(
        robot=robot, request_id=request_id, observation=observation,
        options=options_for(regions, offered, continue_=not silent), deadline_s=deadline_s,
        unusual=named.detections if named is not None else (),
        unusual_pair=named.pair if named is not None else None,
        drift=verdict.drift if verdict is not None else None)


def points(states: np.ndarray) -> tuple[tuple[float, float, float], ...]:
    """The x, y, z of each row of a ``(T+1, 12)`` trajectory."""
    return tuple((float(x), float(y), float(z)) for x, y, z in np.asarray(states)[:, POS])


def control_state(*, robot: str, t: float, x: np.ndarray, output: ControlOutput,
                  t_anom: float | None, state_age_s: float | None) -> ControlState:
    """The loop's state at tick time ``t``: ``x`` is the newest state planned from (no
    fresh state is not news)."""
    return ControlState(
        robot=robot, t=t, x=tuple(float(v) for v in x), u=tuple(float(v) for v in output.u),
        mode=output.mode.value, t_anom=t_anom, chosen=output.chosen,
        active_regions=tuple(int(i) for i in output.active_regions),
        state_age_s=None if state_age_s is None else round(state_age_s, 6))


def plan_snapshot(robot: str, t: float, plan: Plan | None) -> PlanSnapshot | None:
    """The tick's plan (nominal and recovery branches), for the dashboard."""
    if plan is None:
        return None
    return PlanSnapshot(
        robot=robot, t=t, nominal=() if plan.nominal is None else points(plan.nominal),
        recovery={int(i): points(s) for i, s in plan.recovery.items()},
        consensus_steps=int(plan.consensus), solve_ms=max(0.0, float(plan.solve_ms)),
        status=str(plan.status.value))


def mode_events(robot: str, before: Mode, output: ControlOutput,
                request_id: str | None) -> list[Event]:
    """What the controller said this tick: its notes as they are, or, when the mode
    changed, one ``mode_change`` (``fallback``, an alarm, when the recovery was committed
    without a decision) naming both modes and the request it belongs to."""
    if output.mode is before:
        return [event(robot, "controller", "info", text) for text in output.events]
    fallback = output.mode is Mode.RECOVERING and output.fallback
    severity: Severity = "alarm" if fallback else \
        ("info" if output.mode is Mode.NOMINAL else "warning")
    said = "; ".join(output.events) or f"{before.value} -> {output.mode.value}"
    return [event(robot, "fallback" if fallback else "mode_change", severity, said,
                  **{"from": before.value, "to": output.mode.value, "chosen": output.chosen,
                     "fallback": output.fallback, "request_id": request_id})]
