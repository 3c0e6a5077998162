"""The quadrotor model, regions and scenario files (pure logic, no solver)."""

import json

import numpy as np
import pytest

from services.control.core.dynamics import (
    LinearModel,
    QuadrotorParams,
    continuous_dynamics,
    discretize_zoh,
    linearize_hover,
    rotor_thrusts,
    simulate_step,
)
from services.control.core.regions import Region, Tolerance
from services.control.core.scenario import Limits, ScenarioError, bundled_path, load_scenario

PARAMS = QuadrotorParams()


def hover_state(pos=(1.0, -2.0, 3.0)) -> np.ndarray:
    x = np.zeros(12)
    x[:3] = pos
    return x


def test_hover_is_an_equilibrium_of_the_nonlinear_model():
    x = hover_state()
    assert np.allclose(continuous_dynamics(x, PARAMS.hover_input, PARAMS), 0.0)
    assert np.allclose(simulate_step(x, PARAMS.hover_input, 0.1, PARAMS), x)


def test_linearization_matches_finite_differences():
    a, b = linearize_hover(PARAMS)
    x0, u0 = hover_state((0.0, 0.0, 0.0)), PARAMS.hover_input
    h = 1e-6
    a_fd = np.column_stack([
        (continuous_dynamics(x0 + h * e, u0, PARAMS) - continuous_dynamics(x0 - h * e, u0, PARAMS))
        / (2 * h) for e in np.eye(12)])
    b_fd = np.column_stack([
        (continuous_dynamics(x0, u0 + h * e, PARAMS) - continuous_dynamics(x0, u0 - h * e, PARAMS))
        / (2 * h) for e in np.eye(4)])
    assert np.allclose(a, a_fd, atol=1e-6)
    assert np.allclose(b, b_fd, atol=1e-6)
    assert a[3, 7] == pytest.approx(9.81) and a[4, 6] == pytest.approx(-9.81)


def test_zero_order_hold_matches_fine_integration_of_the_linear_model():
    a, b = linearize_hover(PARAMS)
    ad, bd = discretize_zoh(a, b, 0.1)
    x = np.linspace(-0.2, 0.2, 12)
    du = np.array([0.5, 0.1, -0.1, 0.01])
    fine = x.copy()
    for _ in range(10000):
        fine = fine + 1e-5 * (a @ fine + b @ du)
    assert np.allclose(ad @ x + bd @ du, fine, atol=1e-5)


def test_nonlinear_and_linear_models_agree_near_hover():
    model = LinearModel.hover(PARAMS)
    x = hover_state()
    x[3:6] = [0.3, -0.2, 0.1]
    du = np.array([0.2, 0.01, -0.02, 0.0])
    truth = simulate_step(x, model.u_hover + du, model.dt, PARAMS)
    assert np.allclose(model.a @ x + model.b @ du, truth, atol=2e-3)


def test_every_corner_of_the_input_box_is_flyable():
    lo, hi = PARAMS.input_bounds()
    for corner in np.array(np.meshgrid(*zip(lo, hi, strict=True))).T.reshape(-1, 4):
        thrusts = rotor_thrusts(corner, PARAMS)
        assert np.all(thrusts >= -1e-9) and np.all(thrusts <= PARAMS.rotor_max + 1e-9)
    assert rotor_thrusts(PARAMS.hover_input, PARAMS) == pytest.approx([PARAMS.mass * 9.81 / 4] * 4)


def test_region_is_a_set_of_rest_states_and_its_polytope_agrees():
    region = Region(1, "pad", "rooftop", "landing", (0.0, 0.0, 1.0), (1.0, 1.0, 1.2))
    at_rest = hover_state((0.5, 0.5, 1.1))
    h, hvec = region.polytope
    assert region.contains(at_rest)
    assert np.all(h @ at_rest <= hvec)
    moving = at_rest.copy()
    moving[3] = 0.05
    assert not region.contains(moving)
    assert region.contains(moving, Tolerance())
    assert not np.all(h @ moving <= hvec)
    assert np.allclose(region.center[:3], [0.5, 0.5, 1.1])


def test_bundled_scenario_is_the_papers_setup():
    scenario = load_scenario()
    assert (scenario.horizon, scenario.consensus, scenario.dt) == (40, 15, 0.1)
    assert scenario.limits.velocity == 1.5
    labels = [r.label for r in scenario.regions]
    assert labels == ["grassy field", "grassy field", "rooftop", "parking lot"]
    assert all(abs(scenario.region(i).center[0] - 8.0) < 0.5 for i in (1, 2))
    assert all(abs(scenario.region(i).center[0] - 3.0) < 0.5 for i in (3, 4))
    x = scenario.sample_start(np.random.default_rng(0))
    assert np.all(np.abs(x[:3] - np.array([10.0, 2.0, 2.0])) <= 1.0) and not x[3:].any()


def test_bundled_hardware_scene_is_the_papers_hardware_mpc_grid():
    """dt 0.05 s, T 10 s, K 4.3 s (the paper's hardware MPC), planned as a point mass;
    both names and paths load."""
    scene = load_scenario("hardware")
    assert (scene.horizon, scene.consensus) == (200, 86)
    assert scene.dt == pytest.approx(0.05) and scene.model == "point-mass"
    assert scene.limits.velocity == 1.0
    assert scene.approach == pytest.approx((scene.goal[0], scene.goal[1], scene.goal[2] + 0.3))
    assert [r.label for r in scene.regions] == ["alternative landing site", "holding zone"]
    assert load_scenario("paper") == load_scenario()
    assert load_scenario(bundled_path("hardware")) == scene


def test_regridding_keeps_seconds():
    scene = load_scenario("hardware")
    coarse = scene.regridded(40)
    assert coarse.dt == pytest.approx(0.25) and coarse.horizon == 40
    assert coarse.consensus == round(4.3 / 0.25)
    steps, coarse_steps = dict(scene.mpc), dict(coarse.mpc)
    assert coarse_steps["reserve_steps"] == steps["reserve_steps"] // 5  # 1 s either way
    assert coarse_steps["relax_floor"] == steps["relax_floor"]  # not a step count


def test_limits_tighten_only_the_symmetric_bounds():
    lo, hi = Limits().box(shrink=0.1)
    assert hi[3] == pytest.approx(1.35) and lo[3] == pytest.approx(-1.35)
    assert lo[2] == 0.0 and hi[0] == 14.0


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d.pop("goal"), "goal"),
    (lambda d: d["regions"][0].pop("position_hi"), "regions[0].position_hi"),
    (lambda d: d["regions"][1].update(index=7), "regions"),
    (lambda d: d.update(consensus_s=5.0), "consensus_s"),
    (lambda d: d["regions"][0].update(position_lo=[9, 9, 9]), "regions[0]"),
    (lambda d: d.update(model="helicopter"), "model"),
    (lambda d: d.update(mpc={"velocity_margin": 0.1, "eps_prim": 1}), "mpc.eps_prim"),
    (lambda d: d.update(mpc={"velocity_margin": "fast"}), "mpc.velocity_margin"),
    (lambda d: d.update(mpc=[1, 2]), "mpc"),
    (lambda d: d.update(vehicle={"inertia": [0.01, 0.01, 0.02], "wings": 2}), "vehicle.wings"),
    (lambda d: d.update(vehicle={"mass": -1}), "vehicle"),
    (lambda d: d.update(acceleration_lag=[0.1, 0.1]), "acceleration_lag"),
    (lambda d: d.update(anomaly_window=[5, 1]), "anomaly_window"),
    (lambda d: d.update(approach_height=-1), "approach_height"),
    (lambda d: d.update(goal=[0, 1]), "goal"),  # was a numpy broadcast error in flight
    (lambda d: d["start"].update(center=[0, 1, 1, 1]), "start.center"),
    (lambda d: d.update(limits={"acceleration": [1, 0, 1]}), "limits.acceleration"),
])
def test_bad_scenario_files_name_the_field(tmp_path, mutate, field):
    data = {"goal": [0, 0, 1], "start": {"center": [1, 1, 1]}, "regions": [
        {"name": "a", "position_lo": [0, 0, 0], "position_hi": [1, 1, 0.2]},
        {"name": "b", "position_lo": [2, 0, 0], "position_hi": [3, 1, 0.2]}]}
    mutate(data)
    path = tmp_path / "s.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ScenarioError, match=field.replace("[", r"\[").replace("]", r"\]")):
        load_scenario(path)


def test_missing_or_garbled_scenario_file(tmp_path):
    with pytest.raises(ScenarioError, match="No such file"):
        load_scenario(tmp_path / "absent.yaml")
    with pytest.raises(ScenarioError, match="no bundled scenario 'moon'"):
        bundled_path("moon")
    bad = tmp_path / "bad.yaml"
    bad.write_text("goal: [1, 2\n")
    with pytest.raises(ScenarioError, match="not valid yaml"):
        load_scenario(bad)
