"""Planning models: what the MPC of eq. 3 plans with, in its own coordinates.

The plant is always the 12-state quadrotor of :mod:`.dynamics` (its state is
what the robot measures and what flights are judged on). The MPC plans with
one of two linear models of it:

* the hover model (:func:`quadrotor_model`), the paper's simulation: the
  12-state hover linearization, inputs thrust and body torques. The MPC
  commands the motors.
* the point mass (:func:`point_mass_model`), the paper's hardware: "a simple
  kinematic model ... [that] uses acceleration commands as its inputs", with
  the vehicle's own flight controller tracking them
  (:class:`.plant.FlightController`). State ``(p, v)`` plus, per axis whose
  flight controller lags, the realized acceleration ``a`` with
  ``a' = (u - a) / tau``; input ``u``, the commanded acceleration (m/s^2).
  The controller knows ``a`` without measuring it: it is its own past
  commands filtered by the lag (:meth:`PlanningModel.advance`). Without the
  lag the plan is always a little ahead of the vehicle, and a plan at the
  edge of feasibility (where AESOP flies) turns infeasible on the next tick.

A model gives the MPC its linear dynamics, the true state and input boxes in
its coordinates, its state layout (which limits are symmetric and tightened,
which coordinate a region leaves free) and the maps from the plant's state:
:meth:`PlanningModel.measure` (12-state truth, plus the lag states, to model
state) and the rest states at a position (goals and the centres of regions).

Why two: at the paper's hardware grid (dt 0.05 s, T 10 s, 200 steps) the
hover model's x/pitch and y/roll chains are fourth-order integrator chains
whose ADMM iterations run into the tens of thousands (measured, see
docs/control.md); the point mass converges in tens.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .dynamics import N_STATE, LinearModel, QuadrotorParams, discretize_zoh
from .regions import Region

MODEL_NAMES = ("quadrotor", "point-mass")


@dataclass(frozen=True)
class PlanningModel:
    """A linear model with its boxes and layout (see the module docstring).

    ``x_lo``/``x_hi`` and ``u_lo``/``u_hi`` are the true limits; the MPC
    tightens them (:func:`.mpc.tightened_states`). ``symmetric`` are the
    coordinates whose limits are ``+-limit`` and shrink by a fraction;
    ``velocity`` get the extra velocity margin; ``free`` are left to the state
    limits inside a recovery region (yaw); every other non-position coordinate
    is pinned to zero there (at rest, level). The last ``len(lag_decay)``
    coordinates are lag states that :meth:`advance` keeps from the commands;
    ``lag_gap`` bounds how far a command may jump from its lag state (``|u - a|``,
    the realized jerk times the lag: see :func:`point_mass_model`).
    """

    name: str
    linear: LinearModel
    x_lo: np.ndarray
    x_hi: np.ndarray
    u_lo: np.ndarray  # absolute input bounds [N, N m] or [m/s^2]
    u_hi: np.ndarray
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    # the kind of each coordinate, which picks its weight (:class:`.mpc.Weights`)
    state_groups: tuple[str, ...]
    input_groups: tuple[str, ...]
    position: tuple[int, int, int] = (0, 1, 2)
    velocity: tuple[int, int, int] = (3, 4, 5)
    symmetric: tuple[int, ...] = (3, 4, 5)
    free: tuple[int, ...] = ()
    lag_inputs: tuple[int, ...] = ()  # the input each lag state follows
    lag_decay: tuple[float, ...] = ()  # exp(-dt / tau) per lag state
    lag_gap: tuple[float, ...] = ()  # largest |u - a| per lag state (inf: none), true limit

    @property
    def n(self) -> int:
        return self.linear.n

    @property
    def m(self) -> int:
        return self.linear.m

    @property
    def dt(self) -> float:
        return self.linear.dt

    @property
    def n_lag(self) -> int:
        return len(self.lag_decay)

    def measure(self, x: np.ndarray, lag: np.ndarray | None = None) -> np.ndarray:
        """The model state of a measured 12-state ``x`` and the lag states ``lag``."""
        x = np.asarray(x, dtype=float)
        if self.n == N_STATE:
            return x.copy()
        lag = np.zeros(self.n_lag) if lag is None else np.asarray(lag, dtype=float)
        return np.concatenate([x[:6], lag])

    def advance(self, lag: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The lag states one step on, with ``u`` held (exact for the first-order lag)."""
        decay = np.asarray(self.lag_decay)
        lagged: np.ndarray = (decay * lag
                              + (1.0 - decay) * np.asarray(u, dtype=float)[list(self.lag_inputs)])
        return lagged

    def within_reach(self, lag: np.ndarray, rows: np.ndarray, share: float) -> np.ndarray:
        """``rows`` (inputs of consecutive steps, the first meeting the lag states ``lag``)
        with each lagged input moved to within ``share`` of its ``lag_gap`` of the lag state
        it meets, the lag advanced by each row as moved. The MPC plans every input so
        (:func:`.mpc.tightened_lag_gaps`): this bounds what a plan did not make for the
        vehicle's state, such as a kept plan's branch flown blind after late ticks."""
        out = np.array(rows, dtype=float, ndmin=2)
        # each lag state follows its own input alone (:meth:`advance`): a channel at a time,
        # in floats (this runs every tick, on a few rows)
        for a, channel, decay, gap in zip(np.asarray(lag, dtype=float).tolist(),
                                          self.lag_inputs, self.lag_decay, self.lag_gap,
                                          strict=True):
            column, width = out[:, channel], share * gap
            for i, u in enumerate(column.tolist()):
                column[i] = u = min(max(u, a - width), a + width)
                a = decay * a + (1.0 - decay) * u
        return out

    def advance_by(self, lag: np.ndarray, u: np.ndarray, duration: float) -> np.ndarray:
        """The lag states ``duration`` seconds on with ``u`` held (:meth:`advance` for dt)."""
        decay = np.asarray(self.lag_decay) ** (duration / self.dt)
        lagged: np.ndarray = (decay * lag
                              + (1.0 - decay) * np.asarray(u, dtype=float)[list(self.lag_inputs)])
        return lagged

    def predict(self, x: np.ndarray, lag: np.ndarray, inputs: Sequence[np.ndarray],
                first_s: float) -> np.ndarray:
        """The 12-state ``x`` (with the model's ``lag`` states at its time) carried forward
        under ``inputs`` (absolute, in the model's units): the first held ``first_s``
        seconds, each later one ``dt``. The coordinates the model has are predicted
        (position and velocity for the point mass, all twelve for the hover model); the
        rest of ``x`` is kept."""
        z = self.measure(x, lag)
        hover = self.linear.u_hover
        for i, u in enumerate(inputs):
            a, b = self.linear.over(first_s if i == 0 else self.dt)
            z = a @ z + b @ (np.asarray(u, dtype=float) - hover)
        out = np.asarray(x, dtype=float).copy()
        if self.n == N_STATE:
            return z
        out[:6] = z[:6]
        return out

    def rest_state(self, position: np.ndarray | tuple[float, ...]) -> np.ndarray:
        """At rest (and level) at ``position`` (m)."""
        out = np.zeros(self.n)
        out[list(self.position)] = position
        return out

    def region_box(self, region: Region) -> tuple[np.ndarray, np.ndarray]:
        """``X_R^i`` in model coordinates: the position box, ``free`` coordinates
        unbounded, everything else at zero (rest states are equilibria)."""
        lo, hi = np.zeros(self.n), np.zeros(self.n)
        lo[list(self.position)] = region.position_lo
        hi[list(self.position)] = region.position_hi
        lo[list(self.free)] = -np.inf
        hi[list(self.free)] = np.inf
        return lo, hi

    def region_center(self, region: Region) -> np.ndarray:
        return self.rest_state((np.asarray(region.position_lo)
                                + np.asarray(region.position_hi)) / 2)


def quadrotor_model(params: QuadrotorParams, dt: float, x_bounds: tuple[np.ndarray, np.ndarray]
                    ) -> PlanningModel:
    """The paper's simulation model: the 12-state hover linearization (ZOH at ``dt``).

    ``x_bounds`` is the 12-state box of the scenario's limits.
    """
    u_lo, u_hi = params.input_bounds()
    return PlanningModel(
        name="quadrotor", linear=LinearModel.hover(params, dt),
        x_lo=np.asarray(x_bounds[0], dtype=float), x_hi=np.asarray(x_bounds[1], dtype=float),
        u_lo=u_lo, u_hi=u_hi,
        state_names=("px", "py", "pz", "vx", "vy", "vz", "phi", "theta", "psi", "p", "q", "r"),
        input_names=("F", "tau_x", "tau_y", "tau_z"),
        state_groups=("position",) * 3 + ("velocity",) * 3 + ("attitude",) * 3 + ("rate",) * 3,
        input_groups=("thrust", "torque", "torque", "torque"),
        symmetric=(3, 4, 5, 6, 7, 9, 10, 11), free=(8,))


def point_mass_model(dt: float, position_lo: tuple[float, float, float],
                     position_hi: tuple[float, float, float], velocity: float,
                     acceleration: tuple[float, float, float],
                     lag: tuple[float, float, float] = (0.0, 0.0, 0.0),
                     jerk: tuple[float, float, float] = (np.inf, np.inf, np.inf)
                     ) -> PlanningModel:
    """The paper's hardware model: ``p'' = a`` per axis, ZOH at ``dt``.

    Limits: the position fence, ``|v| <= velocity`` and ``|u_i| <= acceleration[i]``
    (m, m/s, m/s^2). ``lag[i] > 0`` (s) adds the realized acceleration of axis ``i``
    as a state with ``a' = (u - a) / lag[i]``; the velocity then integrates ``a``.
    ``jerk[i]`` (m/s^3) bounds that realized jerk where it starts, ``|u - a| / lag[i]``:
    a multirotor realizes a horizontal acceleration ``a`` by tilting about ``a / g``, so
    its tilt rate is the jerk over ``g``, and the body-rate limit bounds the jerk
    (:func:`.scenario.planning_model`). A command that jumps further from the realized
    acceleration asks a vehicle that honours the lag to tilt faster than it may.
    """
    axes = [i for i in range(3) if lag[i] > 0]
    n = 6 + len(axes)
    a = np.zeros((n, n))
    b = np.zeros((n, 3))
    a[0:3, 3:6] = np.eye(3)
    for axis in range(3):
        if axis in axes:
            j = 6 + axes.index(axis)
            a[3 + axis, j] = 1.0
            a[j, j] = -1.0 / lag[axis]
            b[j, axis] = 1.0 / lag[axis]
        else:
            b[3 + axis, axis] = 1.0
    ad, bd = discretize_zoh(a, b, dt)
    ad[np.abs(ad) < 1e-14] = 0.0  # keep the axes' chains apart (decouple reads sparsity)
    bd[np.abs(bd) < 1e-14] = 0.0
    accel = np.asarray(acceleration, dtype=float)
    x_lo = np.concatenate([np.asarray(position_lo, dtype=float), np.full(3, -velocity),
                           np.full(len(axes), -np.inf)])
    x_hi = np.concatenate([np.asarray(position_hi, dtype=float), np.full(3, velocity),
                           np.full(len(axes), np.inf)])
    names = ("px", "py", "pz", "vx", "vy", "vz") + tuple(f"a{'xyz'[i]}" for i in axes)
    return PlanningModel(
        name="point-mass", linear=LinearModel(a=ad, b=bd, dt=dt, u_hover=np.zeros(3), ac=a,
                                              bc=b),
        x_lo=x_lo, x_hi=x_hi, u_lo=-accel, u_hi=accel,
        state_names=names, input_names=("ax", "ay", "az"),
        state_groups=("position",) * 3 + ("velocity",) * 3 + ("lag",) * len(axes),
        input_groups=("acceleration",) * 3,
        lag_inputs=tuple(axes), lag_decay=tuple(float(np.exp(-dt / lag[i])) for i in axes),
        lag_gap=tuple(float(jerk[i] * lag[i]) for i in axes))
