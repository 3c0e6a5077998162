"""Settings of the dashboard service (``AESOP_DASHBOARD_*``, and the shared ``AESOP_*``).

The dashboard reads the bus; its one write is a batch review of the detector's proposals,
forwarded to the embedding service at ``embedding_url`` with the shared admin token (the
caller must bring it too). Off loopback only with ``AESOP_ADMIN_TOKEN`` set. A browser
opened with ``/?token=`` reads through a session that lasts ``session_s``
(``AESOP_DASHBOARD_SESSION_S``), one of at most ``limits.sessions``.
"""

from __future__ import annotations

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from shared.settings import Group, ServiceSettings


class DashboardLimits(Group):
    """What it keeps (``AESOP_DASHBOARD_LIMITS``)."""

    trail: int = Field(default=3000, ge=10, description="states for the flown path")
    scores: int = Field(default=600, ge=10, description="verdicts for the score timeline")
    log: int = Field(default=50, ge=1, description="requests, decisions and events, each")
    client_queue: int = Field(default=256, ge=1,
                              description="items queued per page; the oldest is dropped")
    sessions: int = Field(default=64, ge=1, le=10000,
                          description="browser sessions; the oldest ends")


class DashboardSettings(ServiceSettings):
    model_config = SettingsConfigDict(env_prefix="AESOP_DASHBOARD_", extra="ignore",
                                      validate_by_name=True)

    port: int = Field(default=8080, ge=0, le=65535, description="HTTP port")
    embedding_url: str = Field(
        default="http://127.0.0.1:8001",
        description="where its batch review of the detector's proposals goes "
                    "(`POST /v1/proposals/...`)")
    session_s: int = Field(
        default=12 * 3600, ge=1, le=30 * 86400,
        description="how long a browser session opened with `/?token=` lasts (s; 12 h)")
    limits: DashboardLimits = Field(default=DashboardLimits(), description="what it keeps")
