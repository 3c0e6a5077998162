"""The closed-loop simulator: flights on the nonlinear plant, how they are judged,
and a golden regression of one AESOP flight (paper scenario, seed 0, case 4)."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from services.control.core.dynamics import QuadrotorParams
from services.control.core.scenario import load_scenario, planning_model
from services.sim.judge import count_violations, over_limits
from tools.bench.sim import Case, Flight, fly, judge, sample_cases

SCENARIO = load_scenario()
CASES = sample_cases(SCENARIO, 10, 0)
GOLDEN = Path(__file__).parent.parent / "data" / "golden_aesop_case4.npz"


def test_cases_follow_the_papers_distribution():
    cases = sample_cases(SCENARIO, 200, 3)
    starts = np.array([c.x0[:3] for c in cases])
    assert np.all(np.abs(starts - SCENARIO.start_center) <= SCENARIO.start_half_width)
    assert all(1.0 <= c.anomaly_s <= 4.0 for c in cases)
    assert all(0 < c.latency_s <= SCENARIO.consensus_s for c in cases)
    assert all(np.all(c.x0[3:] == 0) for c in cases)  # at rest
    assert sample_cases(SCENARIO, 5, 3)[4].anomaly_s == cases[4].anomaly_s  # seeded


def test_aesop_flight_reaches_the_chosen_region_without_violations():
    flight = fly("aesop", SCENARIO, CASES[4])
    outcome = judge(flight, SCENARIO)
    assert flight.chosen is not None and flight.decision_s is not None
    assert outcome.success, outcome
    assert outcome.violations == 0 and outcome.ended_in == flight.chosen
    assert "anomaly_pending" in flight.modes and flight.modes[-1] == "recovering"


def test_naive_mpc_fails_where_aesop_succeeds():
    """Case 1: the naive controller plans no recovery while it waits, and its
    post-hoc plan toward the region it is sent to comes too late."""
    naive = judge(fly("naive", SCENARIO, CASES[1]), SCENARIO)
    aesop = judge(fly("aesop", SCENARIO, CASES[1]), SCENARIO)
    assert aesop.success
    assert not naive.success and naive.ended_in != naive.chosen


def test_judge_counts_state_and_input_violations():
    params = QuadrotorParams()
    region = SCENARIO.region(1)
    rest = np.zeros(12)
    rest[:3] = region.center[:3]
    states = np.tile(rest, (4, 1))
    inputs = np.tile(params.hover_input, (3, 1))
    case = Case(0, rest, 1.0, 0.5, 0.0)
    ok = Flight("aesop", case, states, inputs, ["recovering"] * 3, t_anom_s=0.0, chosen=1)
    assert judge(ok, SCENARIO).success
    fast = states.copy()
    fast[2, 3] = SCENARIO.limits.velocity + 0.2  # m/s over the limit at one tick
    pushed = inputs.copy()
    pushed[0, 1] = params.input_bounds()[1][1] + 0.01  # a torque beyond the rotors
    bad = Flight("aesop", case, fast, pushed, ["recovering"] * 3, t_anom_s=0.0, chosen=1)
    assert bad.violations(SCENARIO) == 2
    assert not judge(bad, SCENARIO).success
    elsewhere = Flight("aesop", case, states, inputs, ["recovering"] * 3, t_anom_s=0.0, chosen=2)
    assert judge(elsewhere, SCENARIO).ended_in == 1
    assert not judge(elsewhere, SCENARIO).success


# OpenBLAS picks its kernels by CPU at load time, and an AVX-512 machine's kernels sum in
# another order: the flight then drifts by centimetres from the one the golden file holds
# (10 mm and 0.06 of one input on an AMD EPYC here). The golden flight runs in a process
# pinned to the kernels it was written with (Haswell: any x86-64 with AVX2), so it is the
# same flight to the last digits on every such machine.
GOLDEN_FLIGHT = """
import sys
import numpy as np
from services.control.core.scenario import load_scenario
from tools.bench.sim import fly, sample_cases
scenario = load_scenario()
flight = fly("aesop", scenario, sample_cases(scenario, 10, 0)[4])
np.savez(sys.argv[1], chosen=flight.chosen, t_anom_s=flight.t_anom_s, states=flight.states,
         inputs=flight.inputs)
"""


def test_golden_closed_loop_run(tmp_path: Path) -> None:
    """The same seeded flight (case 4) as when the golden file was written."""
    out = tmp_path / "flight.npz"
    subprocess.run([sys.executable, "-c", GOLDEN_FLIGHT, str(out)], check=True, timeout=120,
                   env={**os.environ, "OPENBLAS_CORETYPE": "Haswell"})
    golden, flight = np.load(GOLDEN), np.load(out)
    assert int(flight["chosen"]) == int(golden["chosen"])
    assert float(flight["t_anom_s"]) == pytest.approx(float(golden["t_anom_s"]))
    np.testing.assert_allclose(flight["states"], golden["states"], atol=1e-6)
    np.testing.assert_allclose(flight["inputs"], golden["inputs"], atol=1e-6)


@pytest.mark.parametrize("name", ["paper", "hardware"])
def test_count_violations_judges_the_truth_and_the_models_inputs(name: str) -> None:
    """States against the scene's limits on the 12-state truth; inputs against the box of
    the scene's planning model (motor commands for the hover model, accelerations for the
    point mass)."""
    scene = load_scenario(name)
    model = planning_model(scene)
    rest = np.zeros(12)
    rest[:3] = np.asarray(scene.start_center)
    inside = [rest] * 3
    hover = [model.linear.u_hover] * 3
    assert count_violations(inside, hover, scene) == 0
    fast = rest.copy()
    fast[3] = scene.limits.velocity + 0.5
    outside = rest.copy()
    outside[0] = scene.limits.position_hi[0] + 0.5  # beyond the fence
    assert count_violations([rest, fast, outside], hover, scene) == 2
    pushed = np.array(hover)
    pushed[1] = model.u_hi + 0.01
    assert count_violations(inside, pushed, scene) == 1
    lost = rest.copy()
    lost[2] = np.nan  # a non-finite state counts too
    assert count_violations([lost], [], scene) == 1
    # which limits, by how much: what a team needs to tune its vehicle
    spun = rest.copy()
    spun[10] = -(scene.limits.rates[1] + 0.7)  # pitch rate
    assert over_limits(inside, hover, scene) == {}
    got = over_limits([rest, fast, outside, spun, spun], pushed, scene)
    assert got == {"position": (1, pytest.approx(0.5)), "velocity": (1, pytest.approx(0.5)),
                   "rate": (2, pytest.approx(0.7)), "input": (1, pytest.approx(0.01))}
    assert over_limits([lost], [], scene) == {"position": (1, np.inf)}
