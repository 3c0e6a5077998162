"""Eq. 3 on OSQP and Algorithm 1's transitions, on a small, quick geometry.

The vehicle has the paper's inertia, which makes it slow to tilt: regions a
few tens of centimetres away and a 3 s horizon keep every solve small.
"""

import numpy as np
import pytest

from services.control.core.aesop import AESOP, NAIVE, Controller, Route
from services.control.core.dynamics import QuadrotorParams, simulate_step
from services.control.core.mpc import BranchProblem, MPCConfig
from services.control.core.planning import quadrotor_model
from services.control.core.regions import Region
from services.control.core.scenario import Limits
from shared.messages import Mode

PARAMS = QuadrotorParams()
MODEL = quadrotor_model(PARAMS, 0.1, Limits().box())
U_BOUNDS = PARAMS.input_bounds()
CONFIG = MPCConfig(horizon=30, consensus=8)
REGIONS = (
    Region(1, "hold", "holding zone", "hover", (0.3, -0.8, 0.8), (1.3, -0.3, 1.2)),
    Region(2, "roof", "rooftop", "landing", (0.3, 0.3, 0.0), (1.3, 0.8, 0.2)),
    Region(3, "lot", "parking lot", "landing", (-0.8, -0.5, 0.0), (-0.3, 0.5, 0.2)),
)
FAR = Region(4, "far", "alternative landing site", "landing", (9.0, 6.0, 0.0), (10.0, 7.0, 0.2))
OUTSIDE = Region(5, "out", "holding zone", "hover", (0.0, 9.0, 1.0), (1.0, 10.0, 2.0))


def state(pos=(0.0, 0.0, 1.0), vel=(0.0, 0.0, 0.0)) -> np.ndarray:
    x = np.zeros(12)
    x[:3], x[3:6] = pos, vel
    return x


GOAL = state((3.0, 0.0, 1.0))
TOL = 5e-3  # OSQP's eps is 1e-3: equalities and bounds hold to a few thousandths


def test_tree_plan_keeps_dynamics_consensus_bounds_and_regions():
    problem = BranchProblem(MODEL, CONFIG, 2)
    x0 = state(vel=(0.2, 0.0, 0.0))
    plan = problem.solve(x0, GOAL, [REGIONS[0], REGIONS[2]])
    assert plan.feasible, plan.status
    branches = [(plan.nominal, plan.inputs)] + [
        (plan.recovery[i], plan.recovery_inputs[i]) for i in (1, 3)]
    for states, inputs in branches:
        assert np.allclose(states[0], x0, atol=TOL)
        du = inputs - MODEL.linear.u_hover
        predicted = states[:-1] @ MODEL.linear.a.T + du @ MODEL.linear.b.T
        assert np.allclose(predicted, states[1:], atol=TOL)
        assert np.all(states[1:] <= problem.x_hi + TOL) and np.all(states[1:] >= problem.x_lo - TOL)
        assert np.all(inputs <= U_BOUNDS[1] + TOL) and np.all(inputs >= U_BOUNDS[0] - TOL)
    # every branch shares the first input; the recovery branches share their first K
    assert np.allclose(plan.recovery_inputs[1][0], plan.inputs[0], atol=TOL)
    assert np.allclose(plan.recovery_inputs[1][:8], plan.recovery_inputs[3][:8], atol=TOL)
    assert not np.allclose(plan.recovery_inputs[1][8:], plan.recovery_inputs[3][8:], atol=TOL)
    for index in (1, 3):
        end = plan.recovery[index][-1]
        region = REGIONS[index - 1]
        assert np.all(end >= region.lo - TOL) and np.all(end <= region.hi + TOL)
    assert plan.cost > 0 and plan.iterations > 0


def test_shrunk_horizon_pins_the_region_earlier():
    problem = BranchProblem(MODEL, CONFIG, 1, nominal=False)
    plan = problem.solve(state(), GOAL, [REGIONS[0]], 0, region_step=20)
    assert plan.feasible and plan.region_step == 20
    region = REGIONS[0]
    tail = plan.recovery[1][20:]
    assert np.all(tail >= region.lo - TOL) and np.all(tail <= region.hi + TOL)


def test_hard_problem_reports_an_unreachable_region_and_soft_returns_the_least_violating_plan():
    hard = BranchProblem(MODEL, CONFIG, 1, nominal=False)
    assert not hard.solve(state(), GOAL, [FAR]).feasible
    assert hard.solve(state(), GOAL, [OUTSIDE]).status.value == "infeasible"  # beyond the fence
    soft = BranchProblem(MODEL, CONFIG, 1, nominal=False, soft=True)
    plan = soft.solve(state(), GOAL, [FAR])
    assert plan.status.value == "solved" and not plan.feasible
    assert plan.slack > 1.0
    end = plan.recovery[4][-1]
    assert end[0] > 0.5 and end[1] > 0.5  # it heads for the region as far as it can


def fly(controller, script, ticks):
    """Run ``controller`` on the nonlinear model; ``script(t)`` gives (anomaly, decision)."""
    x, outputs = state(), []
    for t in range(ticks):
        anomaly, decision = script(t)
        out = controller.make_step(x, anomaly, decision)
        outputs.append(out)
        x = simulate_step(x, out.u, MODEL.dt, PARAMS)
    return x, outputs


def aesop(**kwargs) -> Controller:
    return Controller(MODEL, CONFIG, REGIONS, Route([GOAL]), policy=AESOP, **kwargs)


def test_decision_zero_returns_to_nominal():
    _, outs = fly(aesop(), lambda t: (t == 2, 0 if t == 5 else None), 8)
    assert [o.mode for o in outs[:2]] == [Mode.NOMINAL] * 2
    assert outs[2].request and outs[2].mode is Mode.PENDING
    assert [o.mode for o in outs[3:5]] == [Mode.PENDING] * 2
    assert outs[5].mode is Mode.NOMINAL and "continue" in outs[5].events[0]
    assert outs[5].t_anom is None


def test_decision_y_recovers_to_y():
    controller = aesop()
    x, outs, offered = state(), [], ()
    for t in range(12):
        out = controller.make_step(x, t == 2, offered[-1] if t == 5 else None)
        offered = out.request or offered
        outs.append(out)
        x = simulate_step(x, out.u, MODEL.dt, PARAMS)
    chosen = offered[-1]
    assert outs[5].mode is Mode.RECOVERING and outs[5].chosen == chosen
    assert not outs[-1].fallback and outs[-1].active_regions == (chosen,)


def test_no_decision_by_k_commits_the_fallback():
    _, outs = fly(aesop(), lambda t: (t == 1, None), 1 + CONFIG.consensus + 2)
    pending = [o for o in outs if o.mode is Mode.PENDING]
    assert len(pending) == CONFIG.consensus  # the detection tick and k = 1..K-1
    committed = outs[1 + CONFIG.consensus]
    assert committed.mode is Mode.RECOVERING and committed.fallback
    assert committed.chosen in outs[1].request
    assert any("fallback" in e for e in committed.events)


def test_fixed_fallback_and_a_decision_not_offered():
    _, outs = fly(aesop(fallback=3), lambda t: (t == 0, 99 if t == 2 else None),
                  CONFIG.consensus + 2)
    assert any("not offered" in e for e in outs[2].events)
    last = outs[-1]
    if 3 in outs[0].request:
        assert last.chosen == 3
    else:
        assert last.chosen == outs[0].request[0]


def test_bad_fallback_is_refused():
    with pytest.raises(ValueError, match="fallback"):
        aesop(fallback=9)


def test_naive_flies_on_while_waiting_and_plans_the_recovery_afterwards():
    naive = Controller(MODEL, CONFIG, REGIONS, Route([GOAL]), policy=NAIVE)
    _, outs = fly(naive, lambda t: (t == 1, 2 if t == 4 else None), 8)
    assert outs[1].request == (1, 2, 3)
    assert all(o.active_regions == () for o in outs[:4])  # it keeps no recovery plan
    assert outs[4].mode is Mode.RECOVERING and outs[4].chosen == 2


def test_region_step_past_the_horizon_drops_the_region_but_keeps_the_limits():
    problem = BranchProblem(MODEL, CONFIG, 1, nominal=False)
    plan = problem.solve(state(), GOAL, [FAR], 0, region_step=CONFIG.horizon + 1)
    assert plan.feasible and plan.region_step == CONFIG.horizon + 1
    path = plan.recovery[4]
    assert not FAR.contains(path[-1])  # out of reach in 3 s ...
    assert path[-1][0] > 0.5 and path[-1][1] > 0.5  # ... but it heads there
    assert np.all(path[1:] <= problem.x_hi + TOL) and np.all(path[1:] >= problem.x_lo - TOL)


def test_velocity_margin_tightens_the_planned_velocity_limits():
    loose = BranchProblem(MODEL, MPCConfig(horizon=30, consensus=8,
                                                               velocity_margin=0.0), 0)
    tight = BranchProblem(MODEL, MPCConfig(horizon=30, consensus=8,
                                                               velocity_margin=0.3), 0)
    assert np.allclose(tight.x_hi[3:6], loose.x_hi[3:6] - 0.3)
    assert np.allclose(tight.x_lo[3:6], loose.x_lo[3:6] + 0.3)
    assert np.allclose(tight.x_hi[:3], loose.x_hi[:3])  # positions untouched
    far = state((0.0, 0.0, 1.0))
    plan = tight.solve(far, state((20.0, 0.0, 1.0)), [])
    assert plan.feasible
    assert np.max(np.abs(plan.nominal[:, 3:6])) <= tight.x_hi[3] + TOL


def test_recovery_whose_region_is_out_of_reach_by_its_step_is_planned_to_reach_it_later():
    """The nonlinear plant left the robot 0.3 m/s off rest inside its region after
    ``T``: Algorithm 1's ``s = max(min_region_step, T - k)`` is 5 steps, too few for
    the slow attitude chain to kill that velocity, so the deadline moves back."""
    controller = aesop()
    chosen = controller.make_step(state(), True).request[-1]  # t = 0: the anomaly
    controller.t = CONFIG.horizon + 5  # the decision comes long after it
    region = {r.index: r for r in REGIONS}[chosen]
    x = state(region.center[:3], vel=(0.3, 0.0, 0.0))
    hard = controller.problems.recovery(False)
    assert not hard.solve(x, GOAL, [region], 0, CONFIG.min_region_step).feasible
    out = controller.make_step(x, False, chosen)
    assert out.mode is Mode.RECOVERING and out.status.value == "solved"
    assert out.plan is not None and out.plan.region_step > CONFIG.min_region_step
    assert any("out of reach by step 5" in e for e in out.events)


@pytest.mark.parametrize("kind", ["aesop", "naive"])
def test_warm_up_leaves_the_first_tick_nothing_to_solve(kind: str):
    controller = aesop() if kind == "aesop" else Controller(
        MODEL, CONFIG, REGIONS, Route([GOAL]), policy=NAIVE)
    x0 = state()
    controller.warm_up(x0)
    assert controller.t == 0 and controller.mode is Mode.NOMINAL
    first = controller.make_step(x0, False)
    assert first.plan is not None and first.plan.iterations == 0  # answered by the memo
    cold = aesop() if kind == "aesop" else Controller(
        MODEL, CONFIG, REGIONS, Route([GOAL]), policy=NAIVE)
    same = cold.make_step(x0, False)
    assert same.plan.iterations > 0
    np.testing.assert_allclose(first.u, same.u, atol=1e-9)
