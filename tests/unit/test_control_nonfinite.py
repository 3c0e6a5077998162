"""A non-finite number never reaches the plant.

A NaN or inf in the measured state (a failed estimator) or in the solver's output
(numerical trouble): the step flies the last verified plan's recovery branch, or
hovers if there is none, raises an alarm, and the loop keeps ticking. Before, a
NaN state turned the initial-state rows into +-inf bounds and OSQP said "solved".
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from services.control.core.aesop import AESOP, Controller, Route
from services.control.core.dynamics import QuadrotorParams, simulate_step
from services.control.core.mpc import BranchProblem, MPCConfig, SolveStatus
from services.control.core.planning import quadrotor_model
from services.control.core.regions import Region
from services.control.core.scenario import Limits
from services.control.core.selection import Selection, SubsetSelector
from shared.messages import Mode

PARAMS = QuadrotorParams()
MODEL = quadrotor_model(PARAMS, 0.1, Limits().box())
CONFIG = MPCConfig(horizon=30, consensus=8)
REGIONS = (
    Region(1, "hold", "holding zone", "hover", (0.3, -0.8, 0.8), (1.3, -0.3, 1.2)),
    Region(2, "roof", "rooftop", "landing", (0.3, 0.3, 0.0), (1.3, 0.8, 0.2)),
)
GOAL = MODEL.rest_state((3.0, 0.0, 1.0))
START = MODEL.rest_state((0.0, 0.0, 1.0))


class PoisonedSelector(SubsetSelector):
    """A real selector whose answers, once ``poisoned``, carry a NaN first input: the
    solver's output gone bad."""

    poisoned = False

    def select(self, x0, goal) -> Selection:
        selection = super().select(x0, goal)
        if not self.poisoned or selection.plan is None:
            return selection
        bad = replace(selection.plan, u0=np.full(MODEL.m, np.nan))
        return replace(selection, plan=bad)

    def solve(self, subset, x0, goal, consensus=None, region_step=None):
        plan = super().solve(subset, x0, goal, consensus, region_step)
        return replace(plan, u0=np.full(MODEL.m, np.nan)) if self.poisoned else plan


def controller() -> tuple[Controller, PoisonedSelector]:
    selector = PoisonedSelector(MODEL, CONFIG, REGIONS)
    return Controller(MODEL, CONFIG, REGIONS, Route([GOAL]), policy=AESOP,
                      selector=selector), selector


def fly(ctrl: Controller, ticks: int, x: np.ndarray, anomaly_at: int | None = None,
        decision_at: int | None = None) -> np.ndarray:
    offered = ()
    for t in range(ticks):
        out = ctrl.make_step(x, t == anomaly_at, offered[0] if t == decision_at else None)
        offered = out.request or offered
        x = simulate_step(x, out.u, MODEL.dt, PARAMS)
    return x


def bad_state(x: np.ndarray, where: str) -> np.ndarray:
    x = x.copy()
    index, value = {"position NaN": (0, np.nan), "velocity inf": (4, np.inf),
                    "attitude -inf": (7, -np.inf)}[where]
    x[index] = value
    return x


MODES = {"before any plan": (0, None, None), "nominal": (5, None, None),
         "pending": (5, 2, None), "recovering": (6, 2, 4)}


@pytest.mark.parametrize("where", ["position NaN", "velocity inf", "attitude -inf"])
@pytest.mark.parametrize("mode", MODES)
def test_a_non_finite_state_is_never_solved_or_flown(where: str, mode: str):
    ctrl, _ = controller()
    ticks, anomaly_at, decision_at = MODES[mode]
    x = fly(ctrl, ticks, START, anomaly_at, decision_at)
    before = ctrl.mode
    out = ctrl.make_step(bad_state(x, where), False)
    assert np.all(np.isfinite(out.u)) and out.plan is None
    assert out.status is SolveStatus.FAILED and out.alarms and "non-finite state" in out.alarms[0]
    assert out.mode is before  # nothing else changes
    if before is Mode.RECOVERING:  # still flying toward the one region chosen
        assert out.active_regions == (out.chosen,)
    if ticks == 0:
        assert np.allclose(out.u, MODEL.linear.u_hover)  # nothing to fly but hover
    again = ctrl.make_step(x, False)  # the estimator recovers: the loop goes on
    assert again.status is not SolveStatus.FAILED and not again.alarms


@pytest.mark.parametrize("mode", ["nominal", "pending"])
def test_a_non_finite_solver_output_is_never_flown(mode: str):
    ctrl, selector = controller()
    ticks, anomaly_at, _ = MODES[mode]
    x = fly(ctrl, ticks, START, anomaly_at)
    kept = ctrl.kept.inputs.copy()
    selector.poisoned = True
    out = ctrl.make_step(x, False)
    assert np.all(np.isfinite(out.u)) and out.plan is None and out.alarms
    assert out.status is SolveStatus.FAILED
    assert np.allclose(out.u[1:], kept[1][1:])  # the kept recovery branch's next input
    assert out.mode is (Mode.NOMINAL if mode == "nominal" else Mode.PENDING)


def test_the_fallback_at_k_still_comes_while_the_state_is_lost():
    ctrl, _ = controller()
    x = fly(ctrl, 3, START, anomaly_at=2)
    lost = bad_state(x, "position NaN")
    outs = [ctrl.make_step(lost, False) for _ in range(CONFIG.consensus)]
    assert outs[-1].mode is Mode.RECOVERING and outs[-1].fallback
    assert all(np.all(np.isfinite(o.u)) for o in outs)


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_eq3_refuses_a_non_finite_state_instead_of_solving_with_infinite_bounds(value):
    problem = BranchProblem(MODEL, CONFIG, 2)
    x0 = START.copy()
    x0[2] = value
    plan = problem.solve(x0, GOAL, list(REGIONS))
    assert plan.status is SolveStatus.FAILED and not plan.feasible and plan.iterations == 0
