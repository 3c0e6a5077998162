"""A flight scenario: limits, goal, start box and recovery regions, from YAML or JSON.

The bundled ``scenarios/paper.yaml`` is the paper's quadrotor simulation
(appendix "Additional Results: Quadrotor Simulation"): start near
(10, 2, 2) m, two grassy fields near x = 8 m, a rooftop and a parking lot near
x = 3 m, |v| <= 1.5 m/s per axis, T = 4 s, dt = 0.1 s, K = 1.5 s.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .dynamics import N_STATE, POS, RATE, VEL
from .regions import Region, check_regions


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message names the field."""


@dataclass(frozen=True)
class Limits:
    """The state constraint set ``X`` as a box (the input box comes from the vehicle)."""

    velocity: float = 1.5  # m/s per axis (the paper)
    tilt: float = 0.35  # rad, roll and pitch
    rates: tuple[float, float, float] = (1.5, 1.5, 1.0)  # rad/s
    position_lo: tuple[float, float, float] = (-3.0, -4.0, 0.0)  # m; z >= 0 is the ground
    position_hi: tuple[float, float, float] = (14.0, 8.0, 6.0)  # m

    def __post_init__(self) -> None:
        if self.velocity <= 0 or self.tilt <= 0 or min(self.rates) <= 0:
            raise ScenarioError("limits: velocity, tilt and rates must be positive")
        if np.any(np.asarray(self.position_lo) >= np.asarray(self.position_hi)):
            raise ScenarioError("limits: position_lo must be below position_hi")

    def box(self, shrink: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """``(x_lo, x_hi)``; ``shrink`` tightens velocity, tilt and rates by that fraction."""
        scale = 1.0 - shrink
        hi = np.full(N_STATE, np.inf)
        hi[POS] = self.position_hi
        hi[VEL] = self.velocity * scale
        hi[6:8] = self.tilt * scale
        hi[8] = np.pi
        hi[RATE] = np.asarray(self.rates) * scale
        lo = -hi
        lo[POS] = self.position_lo
        return lo, hi


@dataclass(frozen=True)
class Scenario:
    name: str
    goal: tuple[float, float, float]  # m, where the nominal task hovers
    start_center: tuple[float, float, float]  # m
    start_half_width: float  # m; starts are uniform in the cube, at rest
    regions: tuple[Region, ...]
    limits: Limits = field(default_factory=Limits)
    dt: float = 0.1  # s
    horizon_s: float = 4.0  # T
    consensus_s: float = 1.5  # K

    def __post_init__(self) -> None:
        check = ScenarioError
        if self.dt <= 0:
            raise check("dt must be positive")
        if not self.consensus_s < self.horizon_s:
            raise check("consensus_s (K) must be shorter than horizon_s (T)")
        try:
            check_regions(self.regions)
        except ValueError as exc:
            raise check(f"regions: {exc}") from None

    @property
    def horizon(self) -> int:
        """T in steps."""
        return int(round(self.horizon_s / self.dt))

    @property
    def consensus(self) -> int:
        """K in steps."""
        return int(round(self.consensus_s / self.dt))

    @property
    def goal_state(self) -> np.ndarray:
        out = np.zeros(N_STATE)
        out[POS] = self.goal
        return out

    def region(self, index: int) -> Region:
        for region in self.regions:
            if region.index == index:
                return region
        raise KeyError(index)

    def with_regions(self, regions: tuple[Region, ...]) -> Scenario:
        return Scenario(self.name, self.goal, self.start_center, self.start_half_width,
                        regions, self.limits, self.dt, self.horizon_s, self.consensus_s)

    def sample_start(self, rng: np.random.Generator) -> np.ndarray:
        x = np.zeros(N_STATE)
        x[POS] = np.asarray(self.start_center) + rng.uniform(
            -self.start_half_width, self.start_half_width, size=3)
        return x


def regions_from_list(items: Any) -> tuple[Region, ...]:
    """Regions from a list of mappings; errors name the entry and the field."""
    if not isinstance(items, list) or not items:
        raise ScenarioError("regions: expected a non-empty list")
    out = []
    for i, item in enumerate(items):
        if not isinstance(item, dict):
            raise ScenarioError(f"regions[{i}]: expected a mapping")
        try:
            out.append(Region(
                index=int(item.get("index", i + 1)), name=str(item["name"]),
                label=str(item.get("label", item["name"])), kind=item.get("kind", "landing"),
                position_lo=tuple(float(v) for v in item["position_lo"]),
                position_hi=tuple(float(v) for v in item["position_hi"])))
        except KeyError as exc:
            raise ScenarioError(f"regions[{i}].{exc.args[0]}: required") from None
        except (TypeError, ValueError) as exc:
            raise ScenarioError(f"regions[{i}]: {exc}") from None
    regions = tuple(out)
    try:
        check_regions(regions)
    except ValueError as exc:
        raise ScenarioError(f"regions: {exc}") from None
    return regions


def scenario_from_dict(data: Any) -> Scenario:
    if not isinstance(data, dict):
        raise ScenarioError("scenario: expected a mapping at the top level")
    try:
        limits = Limits(**{k: tuple(v) if isinstance(v, list) else v
                           for k, v in (data.get("limits") or {}).items()})
        start = data["start"]
        return Scenario(
            name=str(data.get("name", "scenario")),
            goal=tuple(float(v) for v in data["goal"]),
            start_center=tuple(float(v) for v in start["center"]),
            start_half_width=float(start.get("half_width", 0.0)),
            regions=regions_from_list(data.get("regions")),
            limits=limits,
            dt=float(data.get("dt", 0.1)),
            horizon_s=float(data.get("horizon_s", 4.0)),
            consensus_s=float(data.get("consensus_s", 1.5)),
        )
    except KeyError as exc:
        raise ScenarioError(f"{exc.args[0]}: required") from None
    except TypeError as exc:
        raise ScenarioError(f"scenario: {exc}") from None


def load_scenario(path: Path | str | None = None) -> Scenario:
    """Load a YAML or JSON scenario; ``None`` gives the bundled paper scenario."""
    if path is None:
        text = resources.files(__package__).joinpath("scenarios/paper.yaml").read_text()
        return scenario_from_dict(yaml.safe_load(text))
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ScenarioError(f"{path}: {exc.strerror}") from None
    try:
        data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        raise ScenarioError(f"{path}: not valid {path.suffix.lstrip('.') or 'YAML'}: {exc}") \
            from None
    return scenario_from_dict(data)
