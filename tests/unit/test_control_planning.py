"""The planning models, the flight controller that tracks the point mass's commands,
the nominal route, and the relaxing promise of the recovery tree."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.linalg import expm

from services.control.core.aesop import Route
from services.control.core.controllers import mpc_config
from services.control.core.dynamics import QuadrotorParams
from services.control.core.mpc import BranchProblem, decouple, promised_step
from services.control.core.planning import point_mass_model
from services.control.core.scenario import load_scenario, planning_model
from services.sim.plant import TrackedQuadrotor
from tools.bench.reference import reference_solve

SCENE = load_scenario("hardware")
LAG = 0.0825


def lagged(dt: float = 0.05):
    return point_mass_model(dt, (-5, -3, 0), (5, 3, 2.5), 1.0, (1.0, 1.0, 1.0), (LAG, LAG, 0.0))


def test_point_mass_splits_into_one_chain_per_axis_with_its_lag_state():
    model = lagged()
    assert model.n == 8 and model.state_names[6:] == ("ax", "ay")
    assert decouple(model.linear.a, model.linear.b) == [((0, 3, 6), (0,)), ((1, 4, 7), (1,)),
                                                        ((2, 5), (2,))]
    lo, hi = model.region_box(SCENE.region(1))
    assert np.all(lo[3:] == 0) and np.all(hi[3:] == 0)  # at rest, lag settled
    assert np.allclose(model.rest_state((1, 2, 3)), [1, 2, 3, 0, 0, 0, 0, 0])


def test_the_lag_state_the_controller_keeps_is_the_models_own():
    """advance() (what the controller does with its commands) equals the model's exact
    discretization of a' = (u - a) / tau under the same commands."""
    model = lagged()
    rng = np.random.default_rng(0)
    x = model.rest_state((0, 0, 1))
    lag = np.zeros(2)
    for _ in range(50):
        u = rng.uniform(-1, 1, 3)
        x = model.linear.a @ x + model.linear.b @ u
        lag = model.advance(lag, u)
        assert np.allclose(x[6:], lag)
    assert np.allclose(model.measure(np.r_[x[:6], np.zeros(6)], lag), x)
    # and the discretization is the continuous lag's
    assert model.lag_decay[0] == pytest.approx(np.exp(-0.05 / LAG))
    assert np.allclose(expm(np.array([[-1 / LAG]]) * 0.05), model.lag_decay[0])


@pytest.mark.parametrize("commands, bound", [
    # smooth commands: the first-order lag fits to a few mm/s
    (lambda k: np.array([0.8 * np.sin(k / 9), 0.5 * np.cos(k / 7), 0.3 * np.sin(k / 5)]), 0.005),
    # jumps of 1.6 m/s^2 (braking hard at the edge of feasibility): the rate limit makes the
    # real response more second-order; still within 2 cm/s
    (lambda k: np.array([0.8 * np.sign(np.sin(k / 9)), 0.5 * np.cos(k / 7), 0.3 * np.sin(k / 5)]),
     0.02),
], ids=["smooth", "jumps"])
def test_the_flight_controller_realizes_the_lag_the_planner_assumes(commands, bound):
    """The hardware scene's vehicle under a stream of acceleration commands: the one-step
    prediction the MPC makes from each measured state (with the lag state it keeps)
    against the vehicle's next velocity; the lag-free model misses by far more."""
    params = QuadrotorParams(inertia=(0.01, 0.01, 0.02))
    plant = TrackedQuadrotor(np.r_[0.0, 0.0, 1.0, np.zeros(9)], 0.05, params)
    model, naive = lagged(), point_mass_model(0.05, (-5, -3, 0), (5, 3, 2.5), 1.0, (1, 1, 1))
    lag = np.zeros(model.n_lag)
    err, naive_err = 0.0, 0.0
    for k in range(80):
        u = commands(k)
        x = model.measure(plant.state, lag)
        predicted = model.linear.a @ x + model.linear.b @ u
        predicted_naive = naive.linear.a @ x[:6] + naive.linear.b @ u
        plant.step(u)
        lag = model.advance(lag, u)
        err = max(err, float(np.max(np.abs(plant.state[3:6] - predicted[3:6]))))
        naive_err = max(naive_err, float(np.max(np.abs(plant.state[3:6] - predicted_naive[3:6]))))
    assert err < bound and naive_err > 2 * err, (err, naive_err)
    assert np.max(np.abs(plant.state[6:8])) < SCENE.limits.tilt
    assert np.max(np.abs(plant.state[9:11])) < SCENE.limits.rates[0]


def test_route_descends_only_from_the_waypoint_at_rest():
    model = planning_model(SCENE)
    route = Route([model.rest_state(SCENE.approach), model.rest_state(SCENE.goal)])
    far = model.rest_state((0.0, 0.0, 1.0))
    assert np.allclose(route.target(far, model)[:3], SCENE.approach)
    over_fast = model.rest_state(SCENE.approach)
    over_fast[3] = 0.5  # passing through at 0.5 m/s
    assert np.allclose(route.target(over_fast, model)[:3], SCENE.approach)
    arrived = model.rest_state(SCENE.approach)
    assert np.allclose(route.target(arrived, model)[:3], SCENE.goal)
    assert np.allclose(route.target(far, model)[:3], SCENE.goal)  # and stays on the goal


def test_the_promise_relaxes_from_t_minus_r_to_algorithm_1s_deadline_at_k():
    config = mpc_config(SCENE)
    t, k_max, r = config.horizon, config.consensus, config.reserve_steps
    steps = [promised_step(config, k) for k in range(k_max + 1)]
    assert steps[0] == t - r and steps[-1] == t - k_max
    assert all(t - r - k <= s <= t - k for k, s in enumerate(steps))  # inside Theorem 1's
    assert all(0 <= a - b <= 1 for a, b in zip(steps, steps[1:], strict=False))
    assert promised_step(dataclasses.replace(config, reserve_steps=0), 7) == t - 7


def test_relax_floor_keeps_a_state_the_lag_carries_over_its_cap_feasible():
    """Just under the planned 0.87 m/s with the realized acceleration still pushing
    (-0.43 m/s^2): no command keeps the next step under the cap, so the problem is
    infeasible in the strict sense (the interior-point reference); OSQP's eps-accurate
    answer had called it solved in one tick and PIQP infeasible in the next. Found in a
    flight; the floor widens the first steps by what the lag can carry."""
    model = planning_model(SCENE)
    config = mpc_config(SCENE)
    state = np.array([1.159, 0.019, 0.095, -0.868, 0.123, -0.016, -0.428, 0.887])
    region = [SCENE.region(1)]
    goal = model.rest_state(SCENE.goal)
    strict = dataclasses.replace(config, relax_floor=0.0)
    no_deadline = config.horizon  # the region only from the last step: the limits decide
    assert reference_solve(model, strict, region, state, goal, consensus=0,
                           region_step=no_deadline, nominal=False).status == "infeasible"
    assert reference_solve(model, config, region, state, goal, consensus=0,
                           region_step=no_deadline, nominal=False).status == "optimal"
    plan = BranchProblem(model, config, 1, nominal=False).solve(state, goal, region, 0,
                                                                no_deadline)
    assert plan.feasible


def _lag_gaps(model, plan) -> np.ndarray:
    """Per branch and step, |u_k - a_k|: how far each command jumps from the acceleration
    the vehicle realizes at that step (the lag states of the planned trajectory)."""
    branches = [(plan.nominal, plan.inputs)] + [(plan.recovery[i], plan.recovery_inputs[i])
                                                for i in plan.recovery]
    lag = list(model.lag_inputs)
    return np.array([np.abs(u[:, lag] - x[:-1, 6:]) for x, u in branches])


def test_a_plan_steps_its_command_no_faster_than_the_vehicle_may_tilt():
    """A horizontal acceleration a is a tilt of about a/g, realized with the lag tau:
    a command u tilts the vehicle at about (u - a)/(g tau) rad/s. Flying toward the red
    box at 0.6 m/s and still accelerating, with the goal behind: the plan reverses, and
    must not jump its command more than g x the body-rate limit x tau from the realized
    acceleration (1.2 m/s^2 in the hardware scene; a jump of 1.9 m/s^2 tilted a vehicle
    that realizes the lag faithfully at 1.9 rad/s against the scene's 1.5: issue 46)."""
    model, config = planning_model(SCENE), mpc_config(SCENE)
    regions = list(SCENE.regions)
    state = np.array([0.0, 0.0, 1.2, 0.6, -0.6, 0.0, 0.9, -0.9])
    goal = model.rest_state((-4.0, 0.0, 1.2))
    plan = BranchProblem(model, config, len(regions)).solve(state, goal, regions)
    assert plan.feasible
    gaps = _lag_gaps(model, plan)
    g = SCENE.vehicle.gravity
    bound = g * np.array([SCENE.limits.rates[1], SCENE.limits.rates[0]]) * LAG
    assert np.all(gaps <= bound * (1 - config.shrink - config.jerk_margin) + 2 * config.eps_abs)
    assert gaps[0, 0].max() > 0.9 * (bound * (1 - config.shrink - config.jerk_margin)).min()
