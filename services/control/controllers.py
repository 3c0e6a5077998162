"""The controllers a scenario implies: Algorithm 1 (AESOP) and the paper's two baselines.

Every method speaks the :class:`Controller` protocol, which is all the control
loop and the closed-loop benchmark rely on.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Literal, Protocol, Self

import numpy as np

from shared.messages import Mode

from .aesop import (
    AesopController,
    ControlOutput,
    FallbackSafeController,
    NaiveController,
    Route,
    _Controller,
)
from .mpc import MPCConfig
from .planning import PlanningModel
from .scenario import Scenario, planning_model

Method = Literal["naive", "fsmpc", "aesop"]
METHODS: tuple[Method, ...] = ("naive", "fsmpc", "aesop")


class Controller(Protocol):
    """One step of a recovery-aware MPC per tick (Algorithm 1's loop body)."""

    model: PlanningModel
    goal: np.ndarray  # this step's nominal target (model state)
    measured: np.ndarray  # the model state of the last step

    @property
    def mode(self) -> Mode: ...

    @property
    def lag(self) -> np.ndarray: ...

    @property
    def state(self) -> np.ndarray: ...

    def warm_up(self, x: np.ndarray) -> None: ...

    def make_step(self, x: np.ndarray | None, anomaly: bool, decision: int | None = None,
                  age: float = 0.0) -> ControlOutput: ...

    def carry_on(self, other: Self) -> None: ...


_INT_FIELDS = {f.name for f in fields(MPCConfig) if f.type in ("int", int)}


def mpc_config(scenario: Scenario, **overrides) -> MPCConfig:
    """The MPC settings a scenario implies: T and K in steps, its ``mpc`` overrides, then
    ``overrides``."""
    merged = {**dict(scenario.mpc), **overrides}
    merged = {k: int(v) if k in _INT_FIELDS else v for k, v in merged.items()}
    return MPCConfig(horizon=scenario.horizon, consensus=scenario.consensus, **merged)


def make_controller(method: Method, scenario: Scenario, config: MPCConfig | None = None,
                    fallback: str | int = "cheapest") -> _Controller:
    """A fresh controller of ``method`` for ``scenario`` on its planning model."""
    model = planning_model(scenario)
    config = config or mpc_config(scenario)
    args = (model, config, scenario.regions, route(scenario, model))
    if method == "aesop":
        return AesopController(*args, fallback=fallback)
    if method == "fsmpc":
        return FallbackSafeController(*args)
    if method == "naive":
        return NaiveController(*args)
    raise ValueError(f"unknown method {method!r}: use one of {', '.join(METHODS)}")


def route(scenario: Scenario, model: PlanningModel) -> Route:
    """The nominal task of a scenario: its approach waypoint (if any), then its goal."""
    stops = [scenario.goal] if scenario.approach_height <= 0 else [scenario.approach,
                                                                    scenario.goal]
    return Route(tuple(model.rest_state(p) for p in stops))
