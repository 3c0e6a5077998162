"""The simulated quadrotor plant and a controller factory for a scenario.

The plant is the nonlinear model of :mod:`.dynamics` integrated with RK4
sub-steps: the truth the MPC's linear model only approximates. Inputs are
clipped to what the rotors can produce, as real motors would.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from .aesop import AesopController, FallbackSafeController, NaiveController, _Controller
from .dynamics import LinearModel, QuadrotorParams, simulate_step
from .mpc import MPCConfig
from .scenario import Scenario

Method = Literal["naive", "fsmpc", "aesop"]
METHODS: tuple[Method, ...] = ("naive", "fsmpc", "aesop")


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

    def step(self, u: np.ndarray) -> np.ndarray:
        """Hold ``u`` (clipped to the actuator box) for ``dt``; return the new state."""
        u = np.clip(np.asarray(u, dtype=float), self._lo, self._hi)
        self._x = simulate_step(self._x, u, self.dt, self.params, self.substeps)
        self.t += self.dt
        return self.state


def mpc_config(scenario: Scenario, **overrides) -> MPCConfig:
    """The MPC settings a scenario implies (T and K in steps)."""
    return MPCConfig(horizon=scenario.horizon, consensus=scenario.consensus, **overrides)


def make_controller(method: Method, scenario: Scenario, params: QuadrotorParams | None = None,
                    config: MPCConfig | None = None, fallback: str | int = "cheapest"
                    ) -> _Controller:
    """A fresh controller of ``method`` for ``scenario`` on its hover model."""
    params = params or QuadrotorParams()
    model = LinearModel.hover(params, scenario.dt)
    config = config or mpc_config(scenario)
    args = (model, scenario.limits.box(), params.input_bounds(), config, scenario.regions,
            scenario.goal_state)
    if method == "aesop":
        return AesopController(*args, fallback=fallback)
    if method == "fsmpc":
        return FallbackSafeController(*args)
    if method == "naive":
        return NaiveController(*args)
    raise ValueError(f"unknown method {method!r}: use one of {', '.join(METHODS)}")
