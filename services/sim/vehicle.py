"""The simulated vehicle behind the vehicle contract (pure: time comes in as arguments).

:class:`SimVehicle` is what ``aesop serve sim`` runs in real time and what the
closed-loop benchmarks run in process, so both fly the same vehicle:

* the truth (:mod:`.plant`: the 12-state quadrotor, with its PX4-style flight
  controller when the scene's model commands accelerations), integrated in steps of
  at most the flight controller's period;
* the set-point it follows: the newest valid one (a command of the kind the scene's
  model sends), applied from the moment it arrives, then the plan's commands it carries
  ``ahead``, each from its own instant (a late or missed tick does not stretch one
  command). Past the set-point's ``valid_until`` on the vehicle's clock, or before any, it
  *holds* on its own: a
  position loop around the flight controller brings it to rest where it was
  (:func:`hold_gains`), as PX4 drops out of offboard mode into a hold;
* the states it reports (:class:`Reporting`): at ``rate_hz``, each published
  ``delay_s`` after the instant it is valid for, with Gaussian noise, lost at
  random with ``drop_rate``, stamped on a clock ``clock_offset_s`` off the true one;
  and the faults a test or an operator injects (:class:`Faults`): a drop-out, a
  vehicle that stops reporting, set-points lost, an estimate that jumps.

Clock: ``now`` is the vehicle's true wall time in seconds (any origin); its clock
reads ``now + clock_offset_s``. The truth advances ``time_scale`` simulated seconds per
second of ``now`` (1: real time).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from services.control.core.dynamics import N_STATE, QuadrotorParams
from services.control.core.scenario import Scenario
from shared.frames import quaternion_from_euler
from shared.messages import VehicleSetpoint, VehicleState
from shared.stats import spread

from .plant import FlightController, FlightControllerGains, Plant, make_plant

# The hold's position and velocity gains (1/s^2, 1/s) and its acceleration per axis (m/s^2):
# vertically brisk (thrust acts at once); horizontally brisk for an airframe that tilts
# fast, gentle for one that does not (the paper's simulated quadrotor, 0.45 kg m^2 against
# a torque box of 0.49 N m, diverges under the brisk ones: its attitude loop saturates).
BRISK_HOLD = (2.0, 2.5, 2.0)
GENTLE_HOLD = (0.5, 1.2, 0.5)
BRISK_TILT_RAD_S2 = 10.0  # the angular acceleration the torque box gives, at least
# simulated s over which a hold eases from the last acceleration command into its own (a
# step would be a step in attitude: docs/architecture.md 3a, "Holding")
HOLD_EASE_S = 0.2


def hold_gains(params: QuadrotorParams) -> np.ndarray:
    """``(kp, kd, accel)`` of the vehicle's own hold per axis (rows x, y, z): the
    horizontal ones by how fast its airframe tilts."""
    torque = params.input_bounds()[1][1]
    tilt = torque / max(params.inertia[0], params.inertia[1])
    across = BRISK_HOLD if tilt >= BRISK_TILT_RAD_S2 else GENTLE_HOLD
    return np.array([across, across, BRISK_HOLD])


@dataclass(frozen=True)
class Reporting:
    """How the vehicle reports its state."""

    rate_hz: float = 100.0
    delay_s: float = 0.0  # from the instant a state is valid to its publication
    position_noise_m: float = 0.0  # standard deviation per axis
    velocity_noise_m_s: float = 0.0
    drop_rate: float = 0.0  # fraction of states lost at random
    clock_offset_s: float = 0.0  # the vehicle's clock minus the true time

    def __post_init__(self) -> None:
        if not (0 < self.rate_hz <= 10_000 and self.delay_s >= 0 and self.position_noise_m >= 0
                and self.velocity_noise_m_s >= 0 and 0 <= self.drop_rate < 1
                and math.isfinite(self.clock_offset_s)):
            raise ValueError(f"reporting out of range: {self}")


@dataclass
class Faults:
    """Faults injected from now on (times on ``now``'s clock; None: not active)."""

    silent_until: float | None = None  # no state is reported before this (a drop-out)
    stopped: bool = False  # no state is reported again (the vehicle stopped talking)
    deaf_until: float | None = None  # set-points arriving before this are lost
    jump: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m, added to reported positions
    jump_until: float | None = None  # ... for states valid before this

    def silent(self, t: float) -> bool:
        return self.stopped or (self.silent_until is not None and t < self.silent_until)


@dataclass(frozen=True)
class Report:
    """A state and when it is published (``now``'s clock)."""

    at: float
    state: VehicleState


@dataclass
class SetpointAges:
    """The age of each set-point when it arrived: the vehicle's clock minus its ``t``; and
    the set-points refused, by reason."""

    window: int = 2000
    ages_s: deque[float] = field(default_factory=deque)
    received: int = 0
    refused: int = 0
    # "kind" (a command this vehicle does not take), "older" (than the one it follows),
    # "future" (for an instant past MAX_AHEAD_S of its clock), "validity" (past MAX_VALID_S),
    # "before_reset" (planned from a state before the vehicle's last reset: another flight's)
    refusals: dict[str, int] = field(default_factory=dict)

    def refuse(self, reason: str) -> None:
        self.refused += 1
        self.refusals[reason] = self.refusals.get(reason, 0) + 1

    def record(self, age: float) -> None:
        self.received += 1
        self.ages_s.append(age)
        while len(self.ages_s) > self.window:
            self.ages_s.popleft()

    def summary(self) -> dict[str, float | int | None]:
        return {"received": self.received, "refused": self.refused,
                **{f"refused_{reason}": n for reason, n in sorted(self.refusals.items())},
                **spread((age * 1000.0 for age in self.ages_s), "age")}


MAX_AHEAD_S = 1.0  # a set-point is for now: one for an instant further ahead is refused
MAX_VALID_S = 10.0  # a loop's set-point is valid for a few ticks; one valid longer is refused


def refusal(sp: VehicleSetpoint, followed: VehicleSetpoint | None, clock: float,
            accelerations: bool, reset_at: float = -math.inf) -> str | None:
    """Why a vehicle whose clock reads ``clock`` and that follows ``followed`` does not
    take ``sp`` (None: it does). It must be of the kind the vehicle takes, newer than the one
    it follows (a higher ``seq``, or a later ``t``: a restarted loop counts again), planned
    from a state of this flight (``state_stamp`` after the vehicle's last reset, ``reset_at``,
    its clock: one planned from before belongs to another flight, from where the vehicle was,
    even when a loop flying blind on that state sends it for an instant of now), and
    bounded: for an instant
    at most :data:`MAX_AHEAD_S` past the vehicle's clock, valid for at most
    :data:`MAX_VALID_S`, so that no one set-point, forged or broken, can lock out the loop's
    next ones by a far-future ``t`` or be flown for ever."""
    if (sp.acceleration is not None) != accelerations:
        return "kind"
    if sp.state_stamp < reset_at:  # and so its t, which is later
        return "before_reset"
    if sp.t > clock + MAX_AHEAD_S:
        return "future"
    if not 0.0 <= sp.valid_until - sp.t <= MAX_VALID_S:
        return "validity"
    if followed is not None and not (sp.seq > followed.seq or sp.t > followed.t):
        return "older"
    return None


class SimVehicle:
    """The simulated vehicle (module docstring), created at rest at ``x0`` at time ``now``."""

    def __init__(self, scenario: Scenario, x0: np.ndarray, reporting: Reporting, *,
                 now: float, time_scale: float = 1.0, robot: str = "robot0",
                 frame: str = "world", seed: int = 0) -> None:
        if not time_scale > 0:
            raise ValueError("time_scale must be positive")
        self.scenario, self.reporting, self.time_scale = scenario, reporting, time_scale
        self.robot, self.frame = robot, frame
        self.accelerations = scenario.model == "point-mass"  # else thrust and torques
        self._fc = FlightController(scenario.vehicle, FlightControllerGains())
        self._hold = hold_gains(scenario.vehicle)
        self._step_s = 1.0 / FlightControllerGains().hz
        self._rng = np.random.default_rng(seed)
        self.faults = Faults()
        self.ages = SetpointAges()
        self._reports: deque[Report] = deque()
        self.reset(x0, now)

    # ----------------------------------------------------------------- state

    def reset(self, x0: np.ndarray, now: float) -> None:
        """At rest at ``x0`` (12-state) from ``now``: no set-point, holding there."""
        self.plant: Plant = make_plant(self.scenario, np.asarray(x0, dtype=float))
        self.now = now
        self._reset_clock = self.clock(now)  # one planned from a state before: refused
        self.seq = getattr(self, "seq", -1) + 1  # the count goes on across resets
        self._next_report = now
        self._reports.clear()
        self._setpoint: VehicleSetpoint | None = None
        self._hold_at: np.ndarray | None = np.asarray(x0, dtype=float)[0:3].copy()
        self._hold_from: np.ndarray | None = None  # the command a hold eases from
        self._hold_since = now
        self.applied = np.zeros(3 if self.accelerations else 4)  # the last command flown

    @property
    def truth(self) -> np.ndarray:
        return self.plant.state

    def clock(self, now: float) -> float:
        """What the vehicle's clock reads at ``now``."""
        return now + self.reporting.clock_offset_s

    @property
    def holding(self) -> bool:
        """Not following a set-point (none yet, or the last one expired)."""
        return self._hold_at is not None

    @property
    def setpoint(self) -> VehicleSetpoint | None:
        return self._setpoint

    # ----------------------------------------------------------------- inputs

    def receive(self, sp: VehicleSetpoint, now: float) -> bool:
        """A set-point arrived at ``now``; False when it is not taken (lost to a fault, of
        the wrong kind, or not newer than the one followed)."""
        self._integrate(now)
        if self.faults.deaf_until is not None and now < self.faults.deaf_until:
            return False
        reason = refusal(sp, self._setpoint, self.clock(now), self.accelerations,
                         self._reset_clock)
        if reason is not None:
            self.ages.refuse(reason)
            return False
        self.ages.record(self.clock(now) - sp.t)
        self._setpoint = sp
        if self.clock(now) <= sp.valid_until:
            self._hold_at = None
        return True

    # ----------------------------------------------------------------- time

    def advance(self, now: float) -> list[Report]:
        """Integrate the truth to ``now``; the states whose publication time has come."""
        self._integrate(now)
        out = []
        while self._reports and self._reports[0].at <= now + 1e-12:
            out.append(self._reports.popleft())
        return out

    def next_event(self) -> float:
        """When something is next due on ``now``'s clock: a state to measure or to publish."""
        due = self._next_report
        if self._reports:
            due = min(due, self._reports[0].at)
        return due

    def _integrate(self, now: float) -> None:
        while self.now < now - 1e-12:
            until = min(now, self._next_report, self.now + self._step_s, self._next_switch())
            if until <= self.now:  # a switch that rounds onto now (epoch clocks): step on
                until = min(now, self.now + self._step_s)
            self._step(until - self.now)
            self.now = until
            if self.now >= self._next_report - 1e-12:
                self._measure(self._next_report)
                self._next_report += 1.0 / self.reporting.rate_hz
        if abs(self.now - self._next_report) <= 1e-12:  # exactly on a report instant
            self._measure(self._next_report)
            self._next_report += 1.0 / self.reporting.rate_hz

    def _step(self, span: float) -> None:
        x = self.plant.state
        sp = self._setpoint
        if sp is not None and self._hold_at is None and self.clock(self.now) > sp.valid_until:
            self._hold_at = x[0:3].copy()  # expired: hold where it is now,
            self._hold_from = self.applied.copy() if self.accelerations else None
            self._hold_since = self.now  # easing in from the last command
        h = span * self.time_scale
        if self._hold_at is not None or sp is None:
            accel = self._hold_accel(x)
            if self._hold_from is not None:
                ease = min(1.0, (self.now - self._hold_since) * self.time_scale / HOLD_EASE_S)
                accel = (1.0 - ease) * self._hold_from + ease * accel
            u = accel if self.accelerations else self._fc.command(x, accel)
        else:
            u = np.asarray(sp.command_at(self.clock(self.now)), dtype=float)
        self.applied = u
        self.plant.step(u, h)

    def _next_switch(self) -> float:
        """When the set-point followed next moves on to a command ahead (``now``'s clock)."""
        sp = self._setpoint
        if sp is None or self._hold_at is not None:
            return math.inf
        at = sp.switches_after(self.clock(self.now))
        return math.inf if at is None else at - self.reporting.clock_offset_s

    def _hold_accel(self, x: np.ndarray) -> np.ndarray:
        target = self._hold_at if self._hold_at is not None else x[0:3]
        kp, kd, most = self._hold.T
        return np.clip(kp * (target - x[0:3]) - kd * x[3:6], -most, most)

    def _measure(self, t: float) -> None:
        """The state valid at ``t``, queued for publication ``delay_s`` later (or lost)."""
        self.seq += 1
        rep, faults = self.reporting, self.faults
        if faults.silent(t) or (rep.drop_rate > 0 and self._rng.uniform() < rep.drop_rate):
            return
        x = self.plant.state
        position = x[0:3] + self._rng.normal(0.0, rep.position_noise_m, 3) \
            if rep.position_noise_m > 0 else x[0:3].copy()
        velocity = x[3:6] + self._rng.normal(0.0, rep.velocity_noise_m_s, 3) \
            if rep.velocity_noise_m_s > 0 else x[3:6].copy()
        if faults.jump_until is not None and t < faults.jump_until:
            position = position + np.asarray(faults.jump)
        self._reports.append(Report(t + rep.delay_s, state_message(
            x, position, velocity, seq=self.seq, stamp=self.clock(t), robot=self.robot,
            frame=self.frame)))

    # ----------------------------------------------------------------- faults

    def with_reporting(self, **changes: float) -> None:
        """Change how states are reported from now on (``Reporting``'s fields)."""
        self.reporting = replace(self.reporting, **changes)


def state_message(x: np.ndarray, position: np.ndarray, velocity: np.ndarray, *, seq: int,
                  stamp: float, robot: str, frame: str) -> VehicleState:
    """The contract's state message of the 12-state ``x`` (attitude and rates from it)."""
    assert len(x) == N_STATE
    return VehicleState(robot=robot, seq=seq, stamp=stamp, frame=frame,
                        position=tuple(float(v) for v in position),
                        velocity=tuple(float(v) for v in velocity),
                        attitude=quaternion_from_euler(*(float(v) for v in x[6:9])),
                        body_rates=tuple(float(v) for v in x[9:12]))
