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

    # a state that arrived more than this many ticks ago is stale (an anomaly, flown blind
    # on the recovery branch)
    state_stale_ticks: float = Field(default=3.0, gt=0.0, le=100.0)
    # a set-point is valid this many ticks past the instant it is for (carrying the plan's
    # commands that far ahead); then the vehicle holds. 0.5 s at 20 Hz: a loop late by a
    # few ticks on a busy robot computer leaves the vehicle flying the plan, not holding
    # (PX4 leaves offboard after COM_OF_LOSS_T, 1 s by default)
    setpoint_valid_ticks: float = Field(default=10.0, gt=0.0, le=100.0)
    frame: str = Field(default="world", min_length=1, max_length=64)  # a state must name it
    # a state farther than this (m), plus what 5 m/s^2 adds over the time between them (their
    # stamps' span, never more than passed here), from where the last accepted one was
    # heading is a jump: refused until it has held state_reset_s
    state_jump_m: float = Field(default=0.5, gt=0.0)
    # s: refused states that hold together this long are taken (a jump, or a run outside
    # the window: no single state locks the real ones out)
    state_reset_s: float = Field(default=0.5, ge=0.0)
    # s: a state stamped further ahead of the vehicle's clock as mapped at its arrival, or
    # valid longer than state_max_delay_s before it, is refused; a clock answer that puts the
    # states' arrivals outside that is in another time base, refused
    state_window_s: float = Field(default=0.5, gt=0.0, le=10.0)
    state_max_delay_s: float = Field(default=30.0, gt=0.0)
    state_max_speed: float = Field(default=20.0, gt=0.0)  # m/s: a faster state is refused
    # s between queries of the vehicle's clock (aesop/{robot}/vehicle/clock); 0: never ask
    clock_sync_s: float = Field(default=1.0, ge=0.0)


class ControlTuning(Group):
    """The solver and the tick thread (``AESOP_CONTROL_TUNING``)."""

    mpc_max_iter: int | None = Field(default=None, ge=1)  # OSQP iterations per warm solve
    mpc_max_iter_cold: int | None = Field(default=None, ge=1)  # none: the scene's
    stats_window: int = Field(default=1000, ge=10)  # ticks behind the jitter percentiles
    # s: how soon Python hands the GIL to the tick thread once it wakes (sys.setswitchinterval)
    switch_interval_s: float = Field(default=0.0002, gt=0.0, le=0.01)


class ControlSettings(ServiceSettings):
    model_config = SettingsConfigDict(env_prefix="AESOP_CONTROL_", extra="ignore",
                                      validate_by_name=True)

    port: int = Field(default=8003, ge=0, le=65535)
    # ticks per second of wall time; None: the scene's own, 1 / dt (its plant advances dt a tick)
    rate_hz: float | None = Field(default=None, gt=0.0, le=1000.0)
    # a bundled scenario's name (paper, hardware) or a YAML/JSON file; None: paper
    scenario: Path | None = None
    method: Literal["aesop", "fsmpc", "naive"] = "aesop"
    # the recovery committed at k = K without a decision: cheapest, first, or a region index
    fallback: Literal["cheapest", "first"] | int = "cheapest"
    # a verdict older than this (s), or none at all, counts as an anomaly (fail-safe)
    verdict_stale_s: float = Field(default=0.5, gt=0.0)
    # time kept back from the reasoner's deadline for the trip back over Zenoh (s)
    decision_margin_s: float = Field(default=0.02, ge=0.0)
    vehicle: VehicleLink = VehicleLink()
    tuning: ControlTuning = ControlTuning()

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
