"""The simulated quadrotor's truth and flight controller (the simulator's physics).

The truth is always the nonlinear 12-state quadrotor of
:mod:`services.control.core.dynamics`, integrated with RK4. What a set-point's command
means depends on the scenario's planning model (:mod:`services.control.core.planning`):

* ``quadrotor``: thrust and torques, applied to the motors
  (:class:`SimulatedQuadrotor`), clipped to what the rotors can produce;
* ``point-mass``: an acceleration command, tracked by the vehicle's own flight
  controller (:class:`FlightController`, a PX4-style cascade run at
  ``hz`` inside each tick) that turns it into thrust and torques
  (:class:`TrackedQuadrotor`). This is how the paper's hardware flew: its MPC
  sent acceleration set-points and "relies on the PX4's internal PID
  controllers to track" them.

Both plants have the same ``step(u, duration) -> x`` shape (``duration`` defaults to
their ``dt``), so whoever drives them does not care which one it is:
:class:`.vehicle.SimVehicle` (the simulator ``aesop serve sim`` runs, and the
benchmarks in process) and the control benchmarks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from services.control.core.dynamics import QuadrotorParams, body_z, simulate_step
from services.control.core.scenario import Scenario


class Plant(Protocol):
    """A simulated vehicle advanced ``dt`` per step under the controller's input."""

    dt: float

    @property
    def state(self) -> np.ndarray: ...

    def step(self, u: np.ndarray, duration: float | None = None) -> np.ndarray: ...


class SimulatedQuadrotor:
    """A quadrotor flying the nonlinear dynamics, advanced ``dt`` seconds per ``step``."""

    def __init__(self, x0: np.ndarray, dt: float, params: QuadrotorParams | None = None,
                 substeps: int = 10) -> None:
        self.params = params or QuadrotorParams()
        self.dt, self.substeps = dt, substeps
        self._lo, self._hi = self.params.input_bounds()
        self._x = np.asarray(x0, dtype=float).copy()
        self.t = 0.0  # s

    @property
    def state(self) -> np.ndarray:
        return self._x.copy()

    def step(self, u: np.ndarray, duration: float | None = None) -> np.ndarray:
        """Hold ``u`` (clipped to the actuator box) for ``duration`` (``dt``); return the
        new state."""
        span = self.dt if duration is None else duration
        u = np.clip(np.asarray(u, dtype=float), self._lo, self._hi)
        substeps = max(1, math.ceil(self.substeps * span / self.dt - 1e-9))
        self._x = simulate_step(self._x, u, span, self.params, substeps)
        self.t += span
        return self.state


@dataclass(frozen=True)
class FlightControllerGains:
    """A PX4-style cascade: acceleration -> attitude -> body rates -> torques."""

    attitude: float = 12.0  # 1/s: body-rate set-point per radian of attitude error
    rate: float = 45.0  # 1/s: angular acceleration per rad/s of rate error
    max_tilt: float = 0.3  # rad, roll and pitch set-points are clipped here
    max_rate: tuple[float, float, float] = (1.2, 1.2, 0.8)  # rad/s, rate set-point limits
    hz: float = 250.0  # inner-loop rate


class FlightController:
    """Thrust and torques that track a world-frame acceleration, yaw held at 0.

    The desired thrust vector ``m (a + g e_z)`` gives the attitude set-point
    (clipped at ``max_tilt``) and the collective thrust (its projection on the
    body z axis); a P attitude loop gives saturated body-rate set-points, and a
    P rate loop with gyroscopic compensation the torques, clipped to the
    rotors' box.
    """

    def __init__(self, params: QuadrotorParams, gains: FlightControllerGains) -> None:
        self.params, self.gains = params, gains
        self._lo, self._hi = params.input_bounds()
        self._inertia = np.asarray(params.inertia)
        self._max_rate = np.asarray(gains.max_rate)

    def command(self, x: np.ndarray, accel: np.ndarray) -> np.ndarray:
        p, g = self.params, self.gains
        ax, ay, az = np.asarray(accel, dtype=float).tolist()
        fx, fy, fz = p.mass * ax, p.mass * ay, p.mass * (az + p.gravity)
        norm = max(math.sqrt(fx * fx + fy * fy + fz * fz), 1e-6)
        phi_d = _clip(math.asin(_clip(-fy / norm, 1.0)), g.max_tilt)
        theta_d = _clip(math.atan2(fx, fz), g.max_tilt)
        phi, theta, psi, wx, wy, wz = np.asarray(x, dtype=float)[6:12].tolist()
        bx, by, bz = body_z(phi, theta, psi).tolist()
        thrust = fx * bx + fy * by + fz * bz
        jx, jy, jz = p.inertia
        rx, ry, rz = (_clip(g.attitude * (phi_d - phi), g.max_rate[0]),
                      _clip(g.attitude * (theta_d - theta), g.max_rate[1]),
                      _clip(g.attitude * (0.0 - psi), g.max_rate[2]))
        hx, hy, hz = jx * wx, jy * wy, jz * wz  # omega x (J omega): gyroscopic compensation
        u = np.array([thrust,
                      jx * g.rate * (rx - wx) + (wy * hz - wz * hy),
                      jy * g.rate * (ry - wy) + (wz * hx - wx * hz),
                      jz * g.rate * (rz - wz) + (wx * hy - wy * hx)])
        return np.minimum(np.maximum(u, self._lo), self._hi)


def _clip(value: float, limit: float) -> float:
    return -limit if value < -limit else limit if value > limit else value


class TrackedQuadrotor:
    """The quadrotor with its flight controller tracking an acceleration command.

    As PX4 does with an acceleration set-point, the flight controller runs no
    position or velocity loop of its own: the MPC closes that loop at the
    control rate. Horizontally the realized acceleration follows the command
    with a first-order lag (about 0.08 s with the default gains and the
    hardware scene's vehicle; the scene's ``acceleration_lag``), vertically at
    once.
    """

    def __init__(self, x0: np.ndarray, dt: float, params: QuadrotorParams | None = None,
                 gains: FlightControllerGains | None = None) -> None:
        self.params = params or QuadrotorParams()
        self.gains = gains or FlightControllerGains()
        self.controller = FlightController(self.params, self.gains)
        self.dt = dt
        self.inner = max(1, math.ceil(dt * self.gains.hz - 1e-9))
        self._x = np.asarray(x0, dtype=float).copy()
        self.t = 0.0

    @property
    def state(self) -> np.ndarray:
        return self._x.copy()

    def step(self, u: np.ndarray, duration: float | None = None) -> np.ndarray:
        """Track the acceleration ``u`` (m/s^2, world frame) for ``duration`` (``dt``)."""
        span = self.dt if duration is None else duration
        inner = self.inner if duration is None else max(1, math.ceil(span * self.gains.hz
                                                                       - 1e-9))
        accel = np.asarray(u, dtype=float)
        x = self._x
        h = span / inner
        for _ in range(inner):
            x = simulate_step(x, self.controller.command(x, accel), h, self.params, 1)
        self._x = x
        self.t += span
        return self.state


def make_plant(scenario: Scenario, x0: np.ndarray) -> Plant:
    """The simulated vehicle at ``x0`` (12-state), driven the way the scenario's model
    commands it."""
    if scenario.model == "point-mass":
        return TrackedQuadrotor(x0, scenario.dt, scenario.vehicle)
    return SimulatedQuadrotor(x0, scenario.dt, scenario.vehicle)
