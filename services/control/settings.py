"""Settings of the control-loop service (``AESOP_CONTROL_*``, and the shared ``AESOP_*``)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import SettingsConfigDict

from shared.settings import Group, ServiceSettings


class VehicleLink(Group):
    """How states from the vehicle are trusted and set-points sent back
    (``AESOP_CONTROL_VEHICLE``; docs/architecture.md, "The vehicle contract")."""

    state_stale_ticks: float = Field(
        default=3.0, gt=0.0, le=100.0,
        description="a state that arrived more than this many ticks ago is stale: an "
                    "anomaly, flown blind on the recovery branch")
    setpoint_valid_ticks: float = Field(
        default=16.0, gt=0.0, le=100.0,
        description="a set-point's `valid_until` past its `t` (the plan carried `ahead` that "
                    "far, at most 16 commands; then the vehicle holds): 0.8 s at 20 Hz, so a "
                    "loop late by several ticks on a busy robot computer leaves the vehicle "
                    "flying the plan, not holding; PX4 leaves offboard after `COM_OF_LOSS_T`, "
                    "1 s by default")
    frame: str = Field(default="world", min_length=1, max_length=64,
                       description="the frame a state must name")
    state_jump_m: float = Field(
        default=0.5, gt=0.0,
        description="a state this far (m), plus `5 t^2 / 2` over the stamps' span but never "
                    "more than passed on this host, from where the last accepted one was "
                    "heading is a jump: refused until it has held `state_reset_s`")
    state_reset_s: float = Field(
        default=0.5, ge=0.0,
        description="refused states, a jump or a run outside the window, that hold together "
                    "this long (s) are the new truth: no single state locks the real ones "
                    "out")
    state_window_s: float = Field(
        default=0.5, gt=0.0, le=10.0,
        description="at most 10: s a state may be stamped ahead of the vehicle's clock as "
                    "mapped at its arrival")
    state_max_delay_s: float = Field(
        default=30.0, gt=0.0,
        description="s a state may have been valid before it arrived; a clock answer that "
                    "puts the states taken outside these two is another time base, refused")
    state_max_speed: float = Field(default=20.0, gt=0.0,
                                   description="m/s: a faster state is refused")
    clock_sync_s: float = Field(
        default=1.0, ge=0.0,
        description="s between queries of the vehicle's clock, "
                    "`aesop/{robot}/vehicle/clock`; 0: never ask, arrivals only")


class ControlTuning(Group):
    """The solver and the tick thread (``AESOP_CONTROL_TUNING``)."""

    mpc_max_iter: int | None = Field(
        default=None, ge=1, description="OSQP's iteration cap of a warm solve; none: the "
                                        "scene's")
    mpc_max_iter_cold: int | None = Field(
        default=None, ge=1, description="OSQP's iteration cap of a cold solve; none: the "
                                        "scene's")
    stats_window: int = Field(default=1000, ge=10,
                              description="ticks behind the jitter percentiles")
    switch_interval_s: float = Field(
        default=0.0002, gt=0.0, le=0.01,
        description="`sys.setswitchinterval` while the tick thread runs: how soon (s) Python "
                    "hands the GIL to it once it wakes")


class ControlSettings(ServiceSettings):
    model_config = SettingsConfigDict(env_prefix="AESOP_CONTROL_", extra="ignore",
                                      validate_by_name=True)

    port: int = Field(default=8003, ge=0, le=65535, description="HTTP port")
    rate_hz: float | None = Field(
        default=None, gt=0.0, le=1000.0,
        description="ticks per wall-clock second, at most 1000 (none: the scene's own, 1/dt: "
                    "its plant advances dt a tick)")
    scenario: Path | None = Field(
        default=None,
        description="`paper`, `hardware`, or a YAML/JSON file (none: `paper`)")
    method: Literal["aesop", "fsmpc", "naive"] = Field(
        default="aesop", description="`aesop`, `fsmpc` or `naive`")
    fallback: Literal["cheapest", "first"] | int = Field(
        default="cheapest",
        description="the recovery committed at k = K without a decision: `cheapest`, "
                    "`first`, or a region index >= 1")
    verdict_stale_s: float = Field(
        default=0.5, gt=0.0,
        description="a verdict older than this (s), or none at all, means the detector is "
                    "silent: an anomaly (fail-safe)")
    decision_margin_s: float = Field(
        default=0.02, ge=0.0,
        description="time (s) kept back from the request's deadline for the trip back over "
                    "Zenoh")
    vehicle: VehicleLink = Field(
        default=VehicleLink(),
        description="the vehicle contract (section 3a): how states from the vehicle are "
                    "trusted and set-points sent back")
    tuning: ControlTuning = Field(default=ControlTuning(),
                                  description="the solver and the tick thread")

    @field_validator("scenario", "rate_hz", mode="before")
    @classmethod
    def _empty_is_none(cls, v: object) -> object:
        return None if v == "" else v

    @field_validator("fallback", mode="before")
    @classmethod
    def _index_from_text(cls, v: object) -> object:
        if isinstance(v, str) and v.strip().isdigit():
            return int(v)
        return v

    @field_validator("fallback")
    @classmethod
    def _positive_index(cls, v: str | int) -> str | int:
        if isinstance(v, int) and v < 1:
            raise ValueError("a fallback region index is >= 1 (0 means continue)")
        return v

    def period_s(self, dt: float) -> float:
        """Seconds between ticks for a scene stepped by ``dt``."""
        return dt if self.rate_hz is None else 1.0 / self.rate_hz

    def mpc_overrides(self) -> dict[str, int]:
        """``MPCConfig`` fields the settings override (for ``controllers.mpc_config``)."""
        out = {}
        if self.tuning.mpc_max_iter is not None:
            out["max_iter"] = self.tuning.mpc_max_iter
        if self.tuning.mpc_max_iter_cold is not None:
            out["max_iter_cold"] = self.tuning.mpc_max_iter_cold
        return out
