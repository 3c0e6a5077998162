"""Settings of the simulated vehicle (``AESOP_SIM_*``, and the shared ``AESOP_*``)."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, field_validator
from pydantic_settings import SettingsConfigDict

from shared.settings import Group, ServiceSettings

from .vehicle import Reporting


class StateReports(Group):
    """How it reports its state (``AESOP_SIM_REPORTS``): the faults a real vehicle's
    estimator and link bring, on purpose."""

    rate_hz: float = Field(default=100.0, gt=0.0, le=1000.0)
    delay_s: float = Field(default=0.0, ge=0.0, le=10.0)  # valid instant -> publication
    position_noise_m: float = Field(default=0.0, ge=0.0, le=10.0)  # std per axis
    velocity_noise_m_s: float = Field(default=0.0, ge=0.0, le=10.0)
    drop_rate: float = Field(default=0.0, ge=0.0, lt=1.0)  # states lost at random
    clock_offset_s: float = Field(default=0.0, ge=-1e6, le=1e6)  # its clock minus the true one


class Trace(Group):
    """The truth it keeps for ``GET /v1/trace`` (``AESOP_SIM_TRACE``)."""

    points: int = Field(default=20_000, ge=100, le=1_000_000)
    hz: float = Field(default=20.0, gt=0.0, le=1000.0)


class SimSettings(ServiceSettings):
    model_config = SettingsConfigDict(env_prefix="AESOP_SIM_", extra="ignore",
                                      validate_by_name=True)

    port: int = Field(default=8004, ge=0, le=65535)
    # the scene whose vehicle, fence and start box it simulates (as control's: a bundled
    # name or a YAML/JSON file; None: paper)
    scenario: Path | None = None
    seed: int = 0  # draws the start from the scene's start box, and the noise
    start_position: tuple[float, float, float] | None = None  # m; overrides the draw
    # simulated seconds per wall second: 1 for real time; the control loop flying a scene
    # faster than its 1/dt needs the simulator as fast (rate_hz * dt)
    time_scale: float = Field(default=1.0, gt=0.0, le=100.0)
    frame: str = Field(default="world", min_length=1, max_length=64)
    reports: StateReports = StateReports()
    trace: Trace = Trace()

    @field_validator("scenario", "start_position", mode="before")
    @classmethod
    def _empty_is_none(cls, v: object) -> object:
        return None if v == "" else v

    def reporting(self) -> Reporting:
        return Reporting(**self.reports.model_dump())
