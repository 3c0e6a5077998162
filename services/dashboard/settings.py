"""Settings of the dashboard service (``AESOP_*`` environment variables).

Its own names carry a ``dashboard_`` prefix, since ``aesop up`` shares one
environment between services. The dashboard is read-only, but it follows the
shared rule all the same: off loopback only with ``AESOP_ADMIN_TOKEN`` set.
"""

from __future__ import annotations

from pydantic import Field, field_validator

from shared.settings import ServiceSettings


class DashboardSettings(ServiceSettings):
    port: int = Field(default=8080, ge=0, le=65535)
    # the control service, asked for the recovery regions (GET /v1/regions); "" = never
    dashboard_control_url: str = "http://127.0.0.1:8003"
    dashboard_regions_poll_s: float = Field(default=5.0, gt=0.0)  # s between region fetches
    dashboard_goal: tuple[float, float, float] | None = None  # m; when control does not say
    dashboard_trail: int = Field(default=3000, ge=10)  # states kept for the flown path
    dashboard_scores: int = Field(default=600, ge=10)  # verdicts kept for the timeline
    dashboard_log: int = Field(default=50, ge=1)  # requests, decisions and events kept, each
    dashboard_client_queue: int = Field(default=256, ge=1)  # per page; the oldest is dropped

    @field_validator("dashboard_goal", mode="before")
    @classmethod
    def _empty_is_none(cls, v: object) -> object:
        return None if v == "" else v
