"""Eq. 3 at the paper's hardware grid (dt 0.05 s, T 10 s, K 4.3 s: 200 steps).

Feasibility must be decided correctly: states that are feasible by construction
are found feasible (cold and warm), states that are infeasible by construction
are shown infeasible, and a solve stopped at its cap is neither.

"By construction" is an argument on the planning model's limits, checked
independently by the CVXPY/Clarabel reference (an interior-point solve of the
same problem written from the maths). The planned speed limit is 0.87 m/s
(1 m/s less 3 % and the 0.1 m/s margin), the planned acceleration 0.97 m/s^2,
and the regions must be reached by the promise, ``T - R`` = 9 s.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.control.core.controllers import make_controller, mpc_config
from services.control.core.mpc import SolveStatus, promised_step
from services.control.core.scenario import load_scenario, planning_model
from services.control.core.selection import SubsetSelector
from services.sim.plant import make_plant
from shared.messages import Mode
from tools.bench.reference import reference_solve

SCENE = load_scenario("hardware")
MODEL = planning_model(SCENE)
CONFIG = mpc_config(SCENE)
PAIR = (1, 2)
REGIONS = [SCENE.region(i) for i in PAIR]


def at_rest(x: float, y: float = 0.0, z: float = 1.0, vx: float = 0.0) -> np.ndarray:
    """A model state: at (x, y, z), moving at ``vx`` along x, its lag settled."""
    return MODEL.measure(np.array([x, y, z, vx, 0, 0, 0, 0, 0, 0, 0, 0.0]))


def goal() -> np.ndarray:
    return MODEL.rest_state(SCENE.approach)


def reference(state: np.ndarray) -> str:
    return reference_solve(MODEL, CONFIG, REGIONS, state, goal(),
                           region_step=promised_step(CONFIG, 0)).status


def test_the_grid_is_the_papers_hardware_mpc():
    assert (CONFIG.horizon, CONFIG.consensus) == (200, 86)
    assert promised_step(CONFIG, 0) == 200 - CONFIG.reserve_steps


# Both regions lie within 1.6 m (x) and 1.5 m (y) of home, x = -4 m. From rest at x0
# the farther one is at most |x0 + 4| + 0.8 m away along x and 1.5 m along y, and a
# trapezoid at 0.87 m/s with 0.97 m/s^2 ramps covers d metres in d / 0.87 + 0.9 s.
FEASIBLE = {"home": -4.0, "mid-arena": 0.0, "past the middle": 2.0}


@pytest.mark.parametrize("where", FEASIBLE)
def test_states_feasible_by_construction_are_found_feasible_cold_and_warm(where: str):
    x0 = FEASIBLE[where]
    assert (abs(x0 + 4.0) + 0.8) / 0.87 + 0.9 < 9.0  # the construction above
    state = at_rest(x0)
    assert reference(state) == "optimal"
    selector = SubsetSelector(MODEL, CONFIG, REGIONS)
    cold = selector.select(state, goal())
    assert cold.feasible and cold.subset == PAIR, cold.status
    # warm: the same problem after a solve elsewhere (its iterate shifted in)
    selector.select(at_rest(x0 + 0.5), goal())
    warm = selector.select(state, goal())
    assert warm.feasible, warm.status


@pytest.mark.parametrize("where, state", [
    # 8.5 m from the nearer region: 8.5 / 0.87 = 9.8 s > the 9 s promise even at full speed
    ("too far from the regions", at_rest(4.5)),
    # 0.12 m from the fence (4.95 m planned) at 0.87 m/s: braking at 0.97 m/s^2 needs
    # 0.39 m, and the acceleration lag adds more
    ("too fast toward the fence", at_rest(4.83, vx=0.87)),
])
def test_states_infeasible_by_construction_are_shown_infeasible(where: str, state):
    assert reference(state) == "infeasible", where
    plan = SubsetSelector(MODEL, CONFIG, REGIONS).select(state, goal())
    assert not plan.feasible and plan.decided, where
    assert plan.status is SolveStatus.INFEASIBLE, where


def test_a_solve_stopped_at_its_cap_is_undecided_and_the_next_call_resumes():
    """A first solve cut at ten ADMM iterations, no referee: no verdict. Nothing is
    discarded for it, and the same call again goes on from where the last one stopped
    (not from a memo, nor from an iterate shifted as if a tick had passed)."""
    capped = dataclasses.replace(CONFIG, max_iter=200, max_iter_cold=10, referee_max_iter=0)
    selector = SubsetSelector(MODEL, capped, REGIONS)
    state = at_rest(-4.0)
    calls = [selector.select(state, goal()) for _ in range(30)]
    first = calls[0]
    assert not first.feasible and not first.decided
    assert first.status in (SolveStatus.MAX_ITER, SolveStatus.INACCURATE)
    assert all(c.status is not SolveStatus.INFEASIBLE for c in calls)
    settled = next(i for i, c in enumerate(calls) if c.feasible)
    assert 0 < settled < 30
    assert all(c.feasible for c in calls[settled:])  # then the memo answers


def test_the_referee_settles_what_osqp_leaves_at_its_cap():
    refereed = dataclasses.replace(CONFIG, max_iter=1, max_iter_cold=1)
    selector = SubsetSelector(MODEL, refereed, REGIONS)
    feasible = selector.select(at_rest(-4.0), goal())
    assert feasible.feasible and feasible.plan.refereed == 3  # every chain, by PIQP
    infeasible = SubsetSelector(MODEL, refereed, REGIONS).select(at_rest(4.5), goal())
    assert infeasible.status is SolveStatus.INFEASIBLE and infeasible.decided


def test_from_rest_at_the_papers_grid_the_robot_flies():
    """The 200-step regression: from the start at rest a tree is found at once and the
    robot sets off toward the red box (before, no subset was ever found)."""
    controller = make_controller("aesop", SCENE)
    x0 = np.zeros(12)
    x0[:3] = SCENE.start_center
    controller.warm_up(x0)
    plant = make_plant(SCENE, x0)
    statuses = []
    for _ in range(40):  # 2 s
        out = controller.make_step(plant.state, False)
        statuses.append(out.status)
        plant.step(out.u)
    assert all(s is SolveStatus.SOLVED for s in statuses)
    assert out.mode is Mode.NOMINAL and out.active_regions == PAIR
    assert plant.state[3] > 0.5  # m/s toward the red box


def test_a_solve_stopped_by_its_time_limit_is_undecided_too():
    """A warm solve given 1 us: OSQP stops at its time limit, which decides nothing; the
    tick's time is spent, so no referee runs past it either."""
    timed = dataclasses.replace(CONFIG, time_limit_s=1e-6)
    selector = SubsetSelector(MODEL, timed, REGIONS)
    state = at_rest(-4.0)
    assert selector.select(state, goal()).feasible  # the cold solve has no limit
    moved = selector.select(at_rest(-3.9), goal())  # warm, cut at once
    assert not moved.feasible and not moved.decided
    assert moved.status is SolveStatus.TIME_LIMIT


def test_a_realized_acceleration_the_vehicle_reports_replaces_the_predicted_lag_state():
    """Issue 46: the loop's lag states are predicted from the commands it sent; a vehicle
    that reports the acceleration it realizes has the loop plan from that instead (clipped
    to the inputs a command may take), so each command stays within the lag gap of what
    the vehicle does. Without a report, or with a non-finite one, the prediction stands."""
    controller = make_controller("aesop", SCENE)
    x0 = np.zeros(12)
    x0[:3] = SCENE.start_center
    controller.warm_up(x0)
    controller.make_step(x0, False)
    predicted = controller.lag.copy()
    first = MODEL.n - MODEL.n_lag
    realized = np.array([-0.8, 0.3, 0.0])
    axes = list(MODEL.lag_inputs)
    out = controller.make_step(x0, False, realized=realized)
    assert controller.measured[first:] == pytest.approx(realized[axes])
    gap = np.asarray(MODEL.lag_gap)
    assert np.all(np.abs(out.u[axes] - realized[axes]) <= gap + 1e-6)
    assert not np.allclose(controller.measured[first:], predicted)
    controller.make_step(x0, False, realized=np.array([50.0, -50.0, 0.0]))
    assert controller.measured[first:] == pytest.approx(np.asarray(MODEL.u_hi)[axes[0]]
                                                        * np.array([1.0, -1.0]))
    kept = controller.lag.copy()
    controller.make_step(x0, False, realized=np.array([np.nan, 0.0, 0.0]))
    assert controller.measured[first:] == pytest.approx(kept)
