"""A flight scenario: limits, goal, start box and recovery regions, from YAML or JSON.

Two ship with the package and load by name (:data:`BUNDLED`):

* ``paper`` (``scenarios/paper.yaml``), the paper's quadrotor simulation
  (appendix "Additional Results: Quadrotor Simulation"): start near
  (10, 2, 2) m, two grassy fields near x = 8 m, a rooftop and a parking lot
  near x = 3 m, |v| <= 1.5 m/s per axis, T = 4 s, dt = 0.1 s, K = 1.5 s, the
  12-state hover model commanding the motors;
* ``hardware`` (``scenarios/hardware.yaml``), the paper's hardware scene at
  its MPC's grid (dt 0.05 s, T 10 s, K 4.3 s), planned with the point-mass
  model whose accelerations the vehicle's flight controller tracks.

Besides limits and regions a scenario names its planning ``model``
(:mod:`.planning`), its ``vehicle`` (:class:`.dynamics.QuadrotorParams`), an
``approach_height`` (the nominal task flies to a waypoint that far above the
goal, then descends) and ``mpc`` overrides of :class:`.mpc.MPCConfig` fields.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields, replace
from importlib import resources
from pathlib import Path
from typing import Any, cast

import numpy as np
import yaml

from .dynamics import N_STATE, POS, RATE, VEL, QuadrotorParams
from .planning import MODEL_NAMES, PlanningModel, point_mass_model, quadrotor_model
from .regions import Region, check_regions

BUNDLED = ("paper", "hardware")  # scenario names that load the packaged files
# MPCConfig fields counted in steps of dt (so they scale when the grid changes)
STEP_FIELDS = ("relax_steps", "min_region_step", "late_region_steps", "reserve_steps")
# MPCConfig fields a scenario may set (numbers only; the rest belongs to the code)
MPC_FIELDS = ("velocity_margin", "position_margin", "shrink", "input_margin", "jerk_margin",
              "relax_steps",
              "recovery_tracking", "relax_lag", "relax_floor", "referee_max_iter",
              "reserve_steps",
              "min_region_step", "late_region_steps", "recovery_weight", "max_iter",
              "max_iter_cold", "time_limit_s", "workers", "eps_abs", "eps_rel")


class ScenarioError(ValueError):
    """A scenario (or a list of regions) that cannot be used. ``field`` names where
    (``regions[1].name``, ``limits``, or the file); the message starts with it."""

    def __init__(self, field: str, problem: str) -> None:
        super().__init__(f"{field}: {problem}")
        self.field = field


@dataclass(frozen=True)
class Limits:
    """The state constraint set ``X`` as a box (the input box comes from the vehicle)."""

    velocity: float = 1.5  # m/s per axis (the paper)
    tilt: float = 0.35  # rad, roll and pitch
    rates: tuple[float, float, float] = (1.5, 1.5, 1.0)  # rad/s
    position_lo: tuple[float, float, float] = (-3.0, -4.0, 0.0)  # m; z >= 0 is the ground
    position_hi: tuple[float, float, float] = (14.0, 8.0, 6.0)  # m
    # m/s^2 per axis: the accelerations the point-mass planner may command
    acceleration: tuple[float, float, float] = (2.0, 2.0, 2.0)

    def __post_init__(self) -> None:
        if self.velocity <= 0 or self.tilt <= 0 or min(self.rates) <= 0:
            raise ScenarioError("limits", "velocity, tilt and rates must be positive")
        if len(self.acceleration) != 3 or min(self.acceleration) <= 0:
            raise ScenarioError("limits.acceleration", "expected 3 positive numbers (m/s^2)")
        if np.any(np.asarray(self.position_lo) >= np.asarray(self.position_hi)):
            raise ScenarioError("limits", "position_lo must be below position_hi")

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
    model: str = "quadrotor"  # what the MPC plans with: "quadrotor" or "point-mass" (models.py)
    # s per axis: how far the vehicle's flight controller lags an acceleration command
    # (point-mass planning only; 0: none)
    acceleration_lag: tuple[float, float, float] = (0.0, 0.0, 0.0)
    vehicle: QuadrotorParams = field(default_factory=QuadrotorParams)
    approach_height: float = 0.0  # m: fly to this far above the goal first, then descend
    # s: when the closed-loop ablation's consequential anomalies come (uniform), the paper's
    # 1..4 s by default
    anomaly_window: tuple[float, float] = (1.0, 4.0)
    mpc: tuple[tuple[str, float], ...] = ()  # MPCConfig overrides, (field, value)

    def __post_init__(self) -> None:
        check = ScenarioError
        for name, point in (("goal", self.goal), ("start.center", self.start_center)):
            if len(point) != 3:
                raise check(name, f"expected 3 numbers (m), got {len(point)}")
        if not self.dt > 0:
            raise check("dt", "must be positive")
        if not self.consensus_s < self.horizon_s:
            raise check("consensus_s", "K must be shorter than horizon_s (T)")
        if self.model not in MODEL_NAMES:
            raise check("model", f"expected one of {', '.join(MODEL_NAMES)}")
        if len(self.acceleration_lag) != 3 or not all(0.0 <= v <= 2.0
                                                        for v in self.acceleration_lag):
            raise check("acceleration_lag", "expected 3 numbers in 0..2 s")
        lo, hi = self.anomaly_window
        if not 0.0 <= lo <= hi:
            raise check("anomaly_window", "expected [from, to] s with 0 <= from <= to")
        if not 0.0 <= self.approach_height <= 10.0:
            raise check("approach_height", "expected 0..10 m")
        unknown = [k for k, _ in self.mpc if k not in MPC_FIELDS]
        if unknown:
            raise check(f"mpc.{unknown[0]}", f"unknown; one of {', '.join(MPC_FIELDS)}")
        try:
            check_regions(self.regions)
        except ValueError as exc:
            raise check("regions", str(exc)) from None

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
        return replace(self, regions=regions)

    def regridded(self, horizon: int) -> Scenario:
        """The same scene planned over ``horizon`` steps of T: ``dt = T / horizon``, with K
        and T kept in seconds and the step-valued ``mpc`` settings kept in seconds too
        (for ``aesop bench mpc --horizons``)."""
        if horizon < 2:
            raise ScenarioError("horizon", "need at least 2 steps")
        dt = self.horizon_s / horizon
        scale = self.dt / dt
        mpc = tuple((k, max(1, round(v * scale)) if k in STEP_FIELDS else v)
                    for k, v in self.mpc)
        return replace(self, dt=dt, mpc=mpc)

    @property
    def approach(self) -> tuple[float, float, float]:
        """The waypoint the nominal task flies to before it descends onto the goal (m)."""
        x, y, z = self.goal
        return (x, y, z + self.approach_height)

    def sample_start(self, rng: np.random.Generator) -> np.ndarray:
        x = np.zeros(N_STATE)
        x[POS] = np.asarray(self.start_center) + rng.uniform(
            -self.start_half_width, self.start_half_width, size=3)
        return x


def regions_from_list(items: Any) -> tuple[Region, ...]:
    """Regions from a list of mappings; errors name the entry and the field."""
    if not isinstance(items, list) or not items:
        raise ScenarioError("regions", "expected a non-empty list")
    out = []
    for i, item in enumerate(items):
        if not isinstance(item, dict):
            raise ScenarioError(f"regions[{i}]", "expected a mapping")
        try:
            out.append(Region(
                index=int(item.get("index", i + 1)), name=str(item["name"]),
                label=str(item.get("label", item["name"])), kind=item.get("kind", "landing"),
                position_lo=_vec3(item["position_lo"]),
                position_hi=_vec3(item["position_hi"])))
        except KeyError as exc:
            raise ScenarioError(f"regions[{i}].{exc.args[0]}", "required") from None
        except (TypeError, ValueError) as exc:
            raise ScenarioError(f"regions[{i}]", str(exc)) from None
    regions = tuple(out)
    try:
        check_regions(regions)
    except ValueError as exc:
        raise ScenarioError("regions", str(exc)) from None
    return regions


def scenario_from_dict(data: Any) -> Scenario:
    if not isinstance(data, dict):
        raise ScenarioError("scenario", "expected a mapping at the top level")
    try:
        given: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v
                                 for k, v in _mapping(data, "limits").items()}
        limits = Limits(**given)
        start = data["start"]
        return Scenario(
            name=str(data.get("name", "scenario")),
            goal=_vec3(data["goal"]),
            start_center=_vec3(start["center"]),
            start_half_width=float(start.get("half_width", 0.0)),
            regions=regions_from_list(data.get("regions")),
            limits=limits,
            dt=float(data.get("dt", 0.1)),
            horizon_s=float(data.get("horizon_s", 4.0)),
            consensus_s=float(data.get("consensus_s", 1.5)),
            model=str(data.get("model", "quadrotor")),
            acceleration_lag=_vec3(data.get("acceleration_lag", (0, 0, 0))),
            vehicle=_vehicle(_mapping(data, "vehicle")),
            approach_height=float(data.get("approach_height", 0.0)),
            # two numbers: Scenario unpacks them as (from, to)
            anomaly_window=cast(tuple[float, float],
                                tuple(float(v) for v in data.get("anomaly_window", (1.0, 4.0)))),
            mpc=_mpc_overrides(_mapping(data, "mpc")),
        )
    except KeyError as exc:
        raise ScenarioError(str(exc.args[0]), "required") from None
    except (TypeError, ValueError) as exc:
        if isinstance(exc, ScenarioError):
            raise
        raise ScenarioError("scenario", str(exc)) from None


def _vec3(values: Any) -> tuple[float, float, float]:
    """Numbers from a list in the file; Region and Scenario check that there are 3."""
    return cast(tuple[float, float, float], tuple(float(v) for v in values))


def _mapping(data: dict[str, Any], key: str) -> dict[str, Any]:
    value = data.get(key) or {}
    if not isinstance(value, dict):
        raise ScenarioError(key, "expected a mapping")
    return value


def _vehicle(data: dict[str, Any]) -> QuadrotorParams:
    """``vehicle:`` fields of :class:`QuadrotorParams` (mass, arm, inertia, rotor_max, ...)."""
    known = {f.name for f in fields(QuadrotorParams)}
    for key in data:
        if key not in known:
            raise ScenarioError(f"vehicle.{key}", f"unknown; one of {', '.join(sorted(known))}")
    try:
        given: dict[str, Any] = {k: tuple(float(x) for x in v) if isinstance(v, list)
                                 else float(v) for k, v in data.items()}
        return QuadrotorParams(**given)
    except (TypeError, ValueError) as exc:
        raise ScenarioError("vehicle", str(exc)) from None


def _mpc_overrides(data: dict[str, Any]) -> tuple[tuple[str, float], ...]:
    out = []
    for key, value in data.items():
        if key not in MPC_FIELDS:
            raise ScenarioError(f"mpc.{key}", f"unknown; one of {', '.join(MPC_FIELDS)}")
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ScenarioError(f"mpc.{key}", "expected a number")
        out.append((key, value))
    return tuple(sorted(out))


def bundled_path(name: str) -> Path:
    """The packaged file of a bundled scenario (``paper`` or ``hardware``)."""
    if name not in BUNDLED:
        raise ScenarioError("scenario", f"no bundled scenario {name!r} (bundled: "
                            f"{', '.join(BUNDLED)})")
    return Path(str(resources.files("services.control").joinpath(f"scenarios/{name}.yaml")))


def resolve_scenario(name_or_path: Path | str | None) -> Path:
    """The file behind a bundled name, a path, or ``None`` (the paper scenario)."""
    if name_or_path is None:
        return bundled_path("paper")
    if str(name_or_path) in BUNDLED:
        return bundled_path(str(name_or_path))
    return Path(name_or_path)


def load_scenario(name_or_path: Path | str | None = None) -> Scenario:
    """Load a YAML or JSON scenario by bundled name or path; ``None`` gives ``paper``."""
    path = resolve_scenario(name_or_path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ScenarioError(str(path), str(exc.strerror)) from None
    try:
        data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        raise ScenarioError(str(path), f"not valid {path.suffix.lstrip('.') or 'YAML'}: {exc}") \
            from None
    return scenario_from_dict(data)


def planning_model(scenario: Scenario) -> PlanningModel:
    """The linear model the scenario's MPC plans with (:mod:`.planning`)."""
    if scenario.model == "point-mass":
        lim, g = scenario.limits, scenario.vehicle.gravity
        # x is flown by pitching, y by rolling (rates: roll, pitch, yaw); z by thrust alone
        jerk = (g * lim.rates[1], g * lim.rates[0], np.inf)
        return point_mass_model(scenario.dt, lim.position_lo, lim.position_hi, lim.velocity,
                                lim.acceleration, scenario.acceleration_lag, jerk)
    return quadrotor_model(scenario.vehicle, scenario.dt, scenario.limits.box())
