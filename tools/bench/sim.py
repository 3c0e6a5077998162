"""The paper's closed-loop quadrotor ablation: naive MPC, FS-MPC and AESOP.

A case is a start state at rest, the time of a consequential anomaly and a
scripted reasoner (its latency, at most ``K``, and a seeded choice among the
regions it was offered at detection time). A flight runs one method on the
nonlinear plant until :data:`SETTLE_S` after ``t_anom + T``: Theorem 1
promises the region by ``t_anom + T`` for the linear model; on the nonlinear
plant the robot arrives up to about 1.5 s later (a recovery whose region is
out of reach by its step is planned to reach it later, see
``aesop._Controller._late``), and a landing is judged once it has settled.
``Outcome.time_to_region_s`` says when it arrived. Success: the flight
ends inside the chosen region and never left the state or input limits on
the way, both judged on the nonlinear truth (:mod:`services.sim.judge`).

The vehicle is the simulator's own (:class:`services.sim.vehicle.SimVehicle`), in
process: it reports its state as configured (:class:`~services.sim.vehicle.Reporting`:
rate, delay, noise, drop-outs) and follows the set-points; the loop reads the states
through the control service's :class:`~services.control.contract.StateInput` (with
the vehicle's clock known exactly, as a clock query on loopback nearly gives it), so
a late state is carried forward as the service carries it. Time is simulated: a
set-point reaches the vehicle at the instant of its tick.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from services.control.contract import ClockMap, StateInput, setpoint
from services.control.core.controllers import METHODS, Method, make_controller
from services.control.core.mpc import MPCConfig
from services.control.core.scenario import Scenario
from services.control.settings import VehicleLink
from services.sim.judge import LIMIT_TOLERANCE, TOLERANCE, LimitTolerance, count_violations
from services.sim.vehicle import Reporting, SimVehicle
from shared.bus import Received
from shared.messages import Mode

SETTLE_S = 3.0  # s after t_anom + T at which a flight ends and is judged




@dataclass(frozen=True)
class Case:
    """One scenario of the ablation."""

    index: int
    x0: np.ndarray
    anomaly_s: float  # when the detector flags the consequential anomaly
    latency_s: float  # how long the scripted reasoner takes (<= K)
    pick: float  # in [0, 1): which offered region the reasoner picks
    continue_: bool = False  # the inconsequential case: the reasoner says y = 0

    def choose(self, options: Sequence[int]) -> int:
        return 0 if self.continue_ else options[int(self.pick * len(options))]


def sample_cases(scenario: Scenario, n: int, seed: int) -> list[Case]:
    """The paper's distribution: start uniform around the centre, anomaly uniform in the
    scene's ``anomaly_window`` (the paper's [1 s, 4 s] by default)."""
    rng = np.random.default_rng(seed)
    return [Case(i, scenario.sample_start(rng), float(rng.uniform(*scenario.anomaly_window)),
                 float(rng.uniform(0.2, 1.0) * scenario.consensus_s), float(rng.uniform()))
            for i in range(n)]


@dataclass
class Flight:
    method: str
    case: Case
    states: np.ndarray  # (N+1, 12)
    inputs: np.ndarray  # (N, 4) as requested by the controller
    modes: list[str]
    t_anom_s: float | None = None
    decision_s: float | None = None
    chosen: int | None = None
    fallback: bool = False
    events: list[str] = field(default_factory=list)
    solve_ms: list[float] = field(default_factory=list)

    def violations(self, scenario: Scenario, tol: LimitTolerance = LIMIT_TOLERANCE) -> int:
        """Ticks at which the plant's state or the controller's input exceeded its limit
        beyond ``tol`` (states on the 12-state truth, inputs in the model's units)."""
        return count_violations(self.states[1:], self.inputs, scenario, tol)

    def in_region(self, scenario: Scenario) -> np.ndarray:
        """Per tick, whether the state is inside the chosen region (with TOLERANCE)."""
        if not self.chosen:
            return np.zeros(len(self.states), dtype=bool)
        region = scenario.region(self.chosen)
        return np.array([region.contains(x, TOLERANCE) for x in self.states])

    def time_to_region_s(self, scenario: Scenario) -> float | None:
        """From the anomaly until the flight enters the chosen region for good."""
        inside = self.in_region(scenario)
        if not inside[-1] or self.t_anom_s is None:
            return None
        last_out = np.flatnonzero(~inside)
        first = int(last_out[-1]) + 1 if last_out.size else 0
        return first * scenario.dt - self.t_anom_s

    def mean_speed(self) -> float:
        return float(np.mean(np.linalg.norm(self.states[:, 3:6], axis=1)))


LINK = VehicleLink.model_fields
STALE_TICKS: float = LINK["state_stale_ticks"].default  # as the control service's defaults
SETPOINT_TICKS: float = LINK["setpoint_valid_ticks"].default


def vehicle_loop(scenario: Scenario, x0: np.ndarray, reporting: Reporting
                 ) -> tuple[SimVehicle, StateInput]:
    """The simulated vehicle at ``x0`` and the loop's view of it, on one exact clock."""
    vehicle = SimVehicle(scenario, x0, reporting, now=0.0)
    clock = ClockMap(sync_max_age_s=math.inf)
    clock.sample(0.0, 0.0, vehicle.clock(0.0))  # a clock query with no round trip
    view = StateInput(limit_s=STALE_TICKS * scenario.dt, clock=clock)
    return vehicle, view


def fly(method: Method, scenario: Scenario, case: Case, config: MPCConfig | None = None,
        duration_s: float | None = None, reporting: Reporting | None = None) -> Flight:
    """One closed-loop flight of ``method`` on the simulated vehicle (reporting its state
    as ``reporting`` says: by default at 100 Hz, without delay or noise)."""
    controller = make_controller(method, scenario, config)
    vehicle, view = vehicle_loop(scenario, case.x0, reporting or Reporting())
    dt = scenario.dt
    anomaly_tick = int(round(case.anomaly_s / dt))
    latency_ticks = max(1, math.ceil(case.latency_s / dt - 1e-9))
    end_s = duration_s or case.anomaly_s + scenario.horizon_s + SETTLE_S
    steps = int(round(end_s / dt))
    states, inputs = [], []
    modes: list[str] = []
    flight = Flight(method, case, np.empty(0), np.empty(0), modes)
    answer: int | None = None
    answer_tick: int | None = None
    for tick in range(steps):
        now = tick * dt
        for report in vehicle.advance(now):
            view.offer(Received("sim", report.state, report.at))
        states.append(vehicle.truth)
        reading = view.read(now)
        decision = answer if answer_tick is not None and tick == answer_tick else None
        x = reading.x if reading.fresh else None
        out = controller.make_step(x, tick == anomaly_tick, decision,
                                   (reading.age or 0.0) if x is not None else 0.0)
        sent = setpoint(robot="bench", seq=tick, output=out, model=controller.model,
                        reading=reading, valid_s=SETPOINT_TICKS * dt, mode=out.mode,
                        period_s=dt, ahead=round(SETPOINT_TICKS) - 1)
        if sent is not None:
            vehicle.receive(sent, now)
        if out.request is not None and answer_tick is None:
            answer, answer_tick = case.choose(out.request), tick + latency_ticks
            flight.t_anom_s = tick * dt
            if not case.continue_:
                flight.chosen = answer
        if decision is not None:
            flight.decision_s = tick * dt
        if out.fallback and not flight.fallback:
            flight.fallback, flight.chosen = True, out.chosen
        flight.events += [f"{tick * dt:.1f}s {e}" for e in out.events]
        if out.plan is not None:
            flight.solve_ms.append(out.plan.solve_ms)
        inputs.append(out.u)
        modes.append(str(out.mode))
        if out.mode is Mode.RECOVERING and flight.chosen is None:
            flight.chosen = out.chosen
    vehicle.advance(steps * dt)
    states.append(vehicle.truth)
    flight.states, flight.inputs = np.array(states), np.array(inputs)
    return flight


@dataclass(frozen=True)
class Outcome:
    method: str
    case: int
    success: bool
    violations: int
    ended_in: int | None
    chosen: int | None
    time_to_region_s: float | None
    mean_speed_m_s: float
    fallback: bool


def judge(flight: Flight, scenario: Scenario) -> Outcome:
    violations = flight.violations(scenario)
    final = flight.states[-1]
    ended_in = next((r.index for r in scenario.regions if r.contains(final, TOLERANCE)), None)
    success = flight.chosen is not None and ended_in == flight.chosen and violations == 0
    return Outcome(flight.method, flight.case.index, success, violations, ended_in, flight.chosen,
                   flight.time_to_region_s(scenario), flight.mean_speed(), flight.fallback)


def run_case(args: tuple[Method, Scenario, Case, Reporting | None]) -> Outcome:
    method, scenario, case, reporting = args
    return judge(fly(method, scenario, case, reporting=reporting), scenario)


def summarize(outcomes: Sequence[Outcome]) -> dict:
    """The ablation row of one method."""
    times = [o.time_to_region_s for o in outcomes if o.success and o.time_to_region_s is not None]
    n = max(len(outcomes), 1)
    return {
        "success_rate": sum(o.success for o in outcomes) / n,
        "constraint_violations": sum(o.violations > 0 for o in outcomes),
        "violation_ticks": sum(o.violations for o in outcomes),
        "ended_in_chosen": sum(o.ended_in is not None and o.ended_in == o.chosen
                               for o in outcomes) / n,
        "mean_time_to_region_s": float(np.mean(times)) if times else None,
        "mean_speed_m_s": float(np.mean([o.mean_speed_m_s for o in outcomes])) if outcomes
        else None,
        "fallbacks": sum(o.fallback for o in outcomes),
    }


def time_lost(scenario: Scenario, case: Case, reach_m: float = 0.2,
              duration_s: float | None = None, reporting: Reporting | None = None) -> dict:
    """The inconsequential case: AESOP slows for the K window, resumes after ``y = 0``.

    Time to come within ``reach_m`` of the goal with the anomaly, against the
    same start with no anomaly (``anomaly_s`` beyond the flight).
    """
    goal = np.asarray(scenario.goal)
    duration_s = duration_s or max(16.0, 4 * scenario.horizon_s)

    def arrival(flight: Flight) -> float | None:
        near = np.flatnonzero(np.linalg.norm(flight.states[:, :3] - goal, axis=1) <= reach_m)
        return float(near[0] * scenario.dt) if near.size else None

    quiet = Case(case.index, case.x0, duration_s + 1.0, case.latency_s, case.pick)
    noisy = Case(case.index, case.x0, case.anomaly_s, case.latency_s, case.pick, continue_=True)
    base = arrival(fly("aesop", scenario, quiet, duration_s=duration_s, reporting=reporting))
    with_anomaly = arrival(fly("aesop", scenario, noisy, duration_s=duration_s,
                               reporting=reporting))
    lost = None if base is None or with_anomaly is None else with_anomaly - base
    return {"arrival_s": with_anomaly, "arrival_no_anomaly_s": base, "time_lost_s": lost}


__all__ = ["METHODS", "SETTLE_S", "Case", "Flight", "Outcome", "fly",
           "judge", "run_case", "sample_cases", "summarize", "time_lost"]
