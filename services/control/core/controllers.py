"""The controllers a scenario implies: Algorithm 1 (AESOP) and the paper's two baselines.

The three are one :class:`~.aesop.Controller` configured by a :class:`~.aesop.Policy`;
it is all the control loop and the closed-loop benchmark rely on.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any, Literal

from .aesop import POLICIES, Controller, Route

__all__ = ["Controller", "Method", "make_controller", "mpc_config"]
from .mpc import MPCConfig
from .planning import PlanningModel
from .scenario import Scenario, planning_model

Method = Literal["naive", "fsmpc", "aesop"]
METHODS: tuple[Method, ...] = ("naive", "fsmpc", "aesop")


_INT_FIELDS = {f.name for f in fields(MPCConfig) if f.type in ("int", int)}


def mpc_config(scenario: Scenario, **overrides: Any) -> MPCConfig:
    """The MPC settings a scenario implies: T and K in steps, its ``mpc`` overrides, then
    ``overrides``."""
    merged = {**dict(scenario.mpc), **overrides}
    merged = {k: int(v) if k in _INT_FIELDS else v for k, v in merged.items()}
    return MPCConfig(horizon=scenario.horizon, consensus=scenario.consensus, **merged)


def make_controller(method: Method, scenario: Scenario, config: MPCConfig | None = None,
                    fallback: str | int = "cheapest") -> Controller:
    """A fresh controller of ``method`` (its :class:`~.aesop.Policy`) for ``scenario`` on
    its planning model."""
    if method not in POLICIES:
        raise ValueError(f"unknown method {method!r}: use one of {', '.join(METHODS)}")
    model = planning_model(scenario)
    config = config or mpc_config(scenario)
    return Controller(model, config, scenario.regions, route(scenario, model),
                      policy=POLICIES[method], fallback=fallback)


def route(scenario: Scenario, model: PlanningModel) -> Route:
    """The nominal task of a scenario: its approach waypoint (if any), then its goal."""
    stops = [scenario.goal] if scenario.approach_height <= 0 else [scenario.approach,
                                                                    scenario.goal]
    return Route(tuple(model.rest_state(p) for p in stops))
