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

    rate_hz: float = Field(default=100.0, gt=0.0, le=1000.0, description="states a second")
    delay_s: float = Field(
        default=0.0, ge=0.0, le=10.0,
        description="s from the instant a state is valid to its publication")
    position_noise_m: float = Field(default=0.0, ge=0.0, le=10.0,
                                    description="m: standard deviation per axis")
    velocity_noise_m_s: float = Field(default=0.0, ge=0.0, le=10.0,
                                      description="m/s: standard deviation per axis")
    drop_rate: float = Field(default=0.0, ge=0.0, lt=1.0,
                             description="the fraction of states lost at random")
    clock_offset_s: float = Field(default=0.0, ge=-1e6, le=1e6,
                                  description="s: its clock minus the true one")


class Trace(Group):
    """The truth it keeps for ``GET /v1/trace`` (``AESOP_SIM_TRACE``)."""

    points: int = Field(default=20_000, ge=100, le=1_000_000, description="points kept")
    hz: float = Field(default=20.0, gt=0.0, le=1000.0, description="points a second")


class SimSettings(ServiceSettings):
    model_config = SettingsConfigDict(env_prefix="AESOP_SIM_", extra="ignore",
                                      validate_by_name=True)

    port: int = Field(default=8004, ge=0, le=65535, description="HTTP port")
    scenario: Path | None = Field(
        default=None,
        description="the scene whose vehicle, fence and start box it simulates, as "
                    "control's: `paper`, `hardware` or a YAML/JSON file (none: `paper`)")
    seed: int = Field(default=0,
                      description="draws the start from the scene's start box, and the noise")
    start_position: tuple[float, float, float] | None = Field(
        default=None,
        description="a JSON `[x,y,z]` (m) instead of the draw (none: drawn from the start "
                    "box)")
    time_scale: float = Field(
        default=1.0, gt=0.0, le=100.0,
        description="simulated seconds per second (1: real time); a control loop flying a "
                    "scene faster than its 1/dt needs the simulator as fast (`rate_hz * dt`)")
    frame: str = Field(default="world", min_length=1, max_length=64,
                       description="the frame its states name")
    reports: StateReports = Field(
        default=StateReports(),
        description="how it reports its state: the faults a real vehicle's estimator and "
                    "link bring, on purpose")
    trace: Trace = Field(default=Trace(), description="the truth kept for `GET /v1/trace`")

    @field_validator("scenario", "start_position", mode="before")
    @classmethod
    def _empty_is_none(cls, v: object) -> object:
        return None if v == "" else v

    def reporting(self) -> Reporting:
        return Reporting(**self.reports.model_dump())
