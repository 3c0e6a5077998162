"""Settings of the dashboard service (``AESOP_*`` environment variables).

Its own names carry a ``dashboard_`` prefix, since ``aesop up`` shares one
environment between services. The dashboard is read-only, but it follows the
shared rule all the same: off loopback only with ``AESOP_ADMIN_TOKEN`` set.
"""

from __future__ import annotations

from pydantic import Field

from shared.settings import ServiceSettings


class DashboardSettings(ServiceSettings):
    port: int = Field(default=8080, ge=0, le=65535)
    dashboard_trail: int = Field(default=3000, ge=10)  # states kept for the flown path
    dashboard_scores: int = Field(default=600, ge=10)  # verdicts kept for the timeline
    dashboard_log: int = Field(default=50, ge=1)  # requests, decisions and events kept, each
    dashboard_client_queue: int = Field(default=256, ge=1)  # per page; the oldest is dropped
