"""The paper's 12-state quadrotor: nonlinear truth and its hover linearization.

State ``x`` (shape ``(12,)``), SI units::

    0:3   px, py, pz      position in the world frame, z up       [m]
    3:6   vx, vy, vz      velocity in the world frame             [m/s]
    6:9   phi, theta, psi roll, pitch, yaw (Z-Y-X Euler angles)   [rad]
    9:12  p, q, r         body angular rates                      [rad/s]

Input ``u`` (shape ``(4,)``): collective thrust ``F`` [N] and body torques
``tau_x, tau_y, tau_z`` [N m]. A "+" rotor layout with arm length ``l`` maps
them to four rotor thrusts (:func:`rotor_thrusts`); the input box the MPC uses
(:meth:`QuadrotorParams.input_bounds`) is chosen inside the set of inputs the
rotors can produce, so a plan within it is always flyable.

The simulator integrates :func:`continuous_dynamics` with RK4 sub-steps
(:func:`simulate_step`); the MPC uses :func:`linearize_hover` discretized with
a zero-order hold (:func:`discretize_zoh`) at ``dt = 0.1 s``. The MPC works in
input deviations ``du = u - u_hover``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

N_STATE = 12
N_INPUT = 4
POS = slice(0, 3)
VEL = slice(3, 6)
ATT = slice(6, 9)
RATE = slice(9, 12)
STATE_NAMES = ("px", "py", "pz", "vx", "vy", "vz", "phi", "theta", "psi", "p", "q", "r")
INPUT_NAMES = ("F", "tau_x", "tau_y", "tau_z")


@dataclass(frozen=True)
class QuadrotorParams:
    """Physical parameters (the paper's simulation appendix where it gives them)."""

    mass: float = 1.0  # kg
    arm: float = 0.25  # m, rotor centre to body centre
    inertia: tuple[float, float, float] = (0.45, 0.45, 0.7)  # kg m^2, diagonal J
    gravity: float = 9.81  # m/s^2
    yaw_coefficient: float = 0.02  # m, rotor drag torque per unit thrust
    rotor_max: float = 4.905  # N per rotor (thrust-to-weight 2)

    def __post_init__(self) -> None:
        if self.mass <= 0 or self.arm <= 0 or min(self.inertia) <= 0:
            raise ValueError("mass, arm and inertia must be positive")
        if 4 * self.rotor_max <= self.mass * self.gravity:
            raise ValueError("rotor_max cannot lift the vehicle")

    @property
    def hover_input(self) -> np.ndarray:
        """``u`` that holds a level hover: ``[m g, 0, 0, 0]``."""
        return np.array([self.mass * self.gravity, 0.0, 0.0, 0.0])

    def input_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """A box on ``u`` inside the rotors' reach.

        Each rotor gives ``F/4 +- tau_xy / (2 l) +- tau_z / (4 c)``. Keeping
        ``F`` within ``hover +- margin`` leaves a per-rotor budget ``b`` on both
        sides; 80 % of it goes to roll/pitch torque and 20 % to yaw.
        """
        hover_rotor = self.mass * self.gravity / 4
        budget = min(hover_rotor, self.rotor_max - hover_rotor) / 2
        thrust_lo = 4 * (hover_rotor - budget)
        thrust_hi = 4 * (hover_rotor + budget)
        tau_xy = 0.8 * budget * 2 * self.arm
        tau_z = 0.2 * budget * 4 * self.yaw_coefficient
        return (np.array([thrust_lo, -tau_xy, -tau_xy, -tau_z]),
                np.array([thrust_hi, tau_xy, tau_xy, tau_z]))


def rotor_thrusts(u: np.ndarray, params: QuadrotorParams) -> np.ndarray:
    """Rotor thrusts [N] (front, left, back, right) that produce ``u``."""
    thrust, tau_x, tau_y, tau_z = u
    base = thrust / 4
    roll = tau_x / (2 * params.arm)
    pitch = tau_y / (2 * params.arm)
    yaw = tau_z / (4 * params.yaw_coefficient)
    return np.array([base - pitch + yaw, base + roll - yaw, base + pitch + yaw, base - roll - yaw])


def rotation(phi: float, theta: float, psi: float) -> np.ndarray:
    """Body-to-world rotation ``Rz(psi) Ry(theta) Rx(phi)``."""
    cf, sf = np.cos(phi), np.sin(phi)
    ct, st = np.cos(theta), np.sin(theta)
    cp, sp = np.cos(psi), np.sin(psi)
    return np.array([
        [cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf],
        [sp * ct, sp * st * sf + cp * cf, sp * st * cf - cp * sf],
        [-st, ct * sf, ct * cf],
    ])


def body_z(phi: float, theta: float, psi: float) -> np.ndarray:
    """The body z axis in the world frame, the third column of :func:`rotation`."""
    cf, sf = np.cos(phi), np.sin(phi)
    ct, st = np.cos(theta), np.sin(theta)
    cp, sp = np.cos(psi), np.sin(psi)
    return np.array([cp * st * cf + sp * sf, sp * st * cf - cp * sf, ct * cf])


def continuous_dynamics(x: np.ndarray, u: np.ndarray, params: QuadrotorParams) -> np.ndarray:
    """``dx/dt`` of the rigid-body quadrotor (Newton-Euler, Z-Y-X Euler angles).

    Written on plain floats: the simulator integrates it hundreds of times per simulated
    second, and numpy's per-call overhead on 3-vectors was most of its cost."""
    _, _, _, vx, vy, vz, phi, theta, psi, p, q, r = np.asarray(x, dtype=float).tolist()
    thrust, tau_x, tau_y, tau_z = np.asarray(u, dtype=float).tolist()
    cf, sf = math.cos(phi), math.sin(phi)
    ct, st = math.cos(theta), math.sin(theta)
    cp, sp = math.cos(psi), math.sin(psi)
    tt = st / ct
    f = thrust / params.mass  # along the body z axis (the third column of rotation())
    jx, jy, jz = params.inertia
    hx, hy, hz = jx * p, jy * q, jz * r  # J omega; omega x (J omega) below
    return np.array([
        vx, vy, vz,
        (cp * st * cf + sp * sf) * f, (sp * st * cf - cp * sf) * f, ct * cf * f - params.gravity,
        p + sf * tt * q + cf * tt * r, cf * q - sf * r, (sf * q + cf * r) / ct,
        (tau_x - (q * hz - r * hy)) / jx, (tau_y - (r * hx - p * hz)) / jy,
        (tau_z - (p * hy - q * hx)) / jz,
    ])


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` for 3-vectors (``np.cross`` costs ~50 us a call; this a few)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def simulate_step(x: np.ndarray, u: np.ndarray, dt: float, params: QuadrotorParams,
                  substeps: int = 10) -> np.ndarray:
    """Advance the nonlinear model ``dt`` seconds with ``u`` held (RK4, ``substeps``)."""
    h = dt / substeps
    for _ in range(substeps):
        k1 = continuous_dynamics(x, u, params)
        k2 = continuous_dynamics(x + h / 2 * k1, u, params)
        k3 = continuous_dynamics(x + h / 2 * k2, u, params)
        k4 = continuous_dynamics(x + h * k3, u, params)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def linearize_hover(params: QuadrotorParams) -> tuple[np.ndarray, np.ndarray]:
    """Continuous Jacobians ``(A, B)`` at a level hover with ``psi = 0``.

    Any position is a hover; the model is translation-invariant. Small tilts
    tip the thrust vector: ``dvx/dt = g theta``, ``dvy/dt = -g phi``.
    """
    a = np.zeros((N_STATE, N_STATE))
    b = np.zeros((N_STATE, N_INPUT))
    a[POS, VEL] = np.eye(3)
    a[3, 7] = params.gravity
    a[4, 6] = -params.gravity
    a[ATT, RATE] = np.eye(3)
    b[5, 0] = 1.0 / params.mass
    b[9:12, 1:4] = np.diag(1.0 / np.asarray(params.inertia))
    return a, b


def discretize_zoh(a: np.ndarray, b: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretization via the augmented matrix exponential."""
    n, m = b.shape
    block = np.zeros((n + m, n + m))
    block[:n, :n] = a
    block[:n, n:] = b
    phi = expm(block * dt)
    return phi[:n, :n], phi[:n, n:]


@dataclass(frozen=True)
class LinearModel:
    """``x[k+1] = A x[k] + B du[k]`` with ``du = u - u_hover`` (hover at any position),
    the zero-order hold at ``dt`` of ``x' = Ac x + Bc du`` (:meth:`over` holds ``du`` for
    any other duration)."""

    a: np.ndarray
    b: np.ndarray
    dt: float  # s
    u_hover: np.ndarray
    ac: np.ndarray
    bc: np.ndarray

    @classmethod
    def hover(cls, params: QuadrotorParams, dt: float = 0.1) -> LinearModel:
        ac, bc = linearize_hover(params)
        a, b = discretize_zoh(ac, bc, dt)
        return cls(a=a, b=b, dt=dt, u_hover=params.hover_input, ac=ac, bc=bc)

    def over(self, duration: float) -> tuple[np.ndarray, np.ndarray]:
        """``(A, B)`` of the zero-order hold for ``duration`` seconds (``dt``: ``a``, ``b``)."""
        if abs(duration - self.dt) <= 1e-12:
            return self.a, self.b
        return discretize_zoh(self.ac, self.bc, duration)

    @property
    def n(self) -> int:
        return int(self.a.shape[0])

    @property
    def m(self) -> int:
        return int(self.b.shape[1])


def rest_at(position: Sequence[float]) -> np.ndarray:
    """The 12-state at rest at ``position`` (m)."""
    x = np.zeros(N_STATE)
    x[POS] = np.asarray(position, dtype=float)
    return x
