"""Settings every service shares, read from ``AESOP_*`` environment variables.

Build them once at the edge (the CLI) and pass them down; logic never reads
``os.environ``. A service adds its own fields by subclassing ``ServiceSettings``.
Lists (Zenoh endpoints) are comma-separated in the environment, e.g.
``AESOP_ZENOH_CONNECT=tcp/127.0.0.1:7447,tcp/10.0.0.2:7447``.
"""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

Endpoints = Annotated[list[str], NoDecode]


def _split(value: object) -> object:
    if isinstance(value, str):
        return [part.strip() for part in value.split(",") if part.strip()]
    return value


class BusSettings(BaseSettings):
    """How a process joins the Zenoh network (defaults: a peer on loopback, no multicast)."""

    model_config = SettingsConfigDict(env_prefix="AESOP_", extra="ignore")

    robot: str = Field(default="robot0", pattern=r"^[A-Za-z0-9_\-]+$")
    zenoh_mode: Literal["peer", "client"] = "peer"
    zenoh_listen: Endpoints = Field(default_factory=list)
    zenoh_connect: Endpoints = Field(default_factory=list)
    zenoh_multicast: bool = False
    zenoh_config: Path | None = None  # a zenoh JSON5 config file, applied first

    _split_listen = field_validator("zenoh_listen", "zenoh_connect", mode="before")(_split)


class ServiceSettings(BusSettings):
    """A service: the Zenoh bus plus an HTTP admin API and a data directory."""

    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=0, le=65535)
    admin_token: SecretStr | None = None
    data_dir: Path = Path("data")
    log_level: Literal["debug", "info", "warning", "error"] = "info"

    @field_validator("admin_token", mode="before")
    @classmethod
    def _empty_token_is_none(cls, v: object) -> object:
        return None if v in ("", None) else v

    @field_validator("admin_token")
    @classmethod
    def _token_strength(cls, v: SecretStr | None) -> SecretStr | None:
        if v is not None and len(v.get_secret_value()) < 16:
            raise ValueError("AESOP_ADMIN_TOKEN must be at least 16 characters")
        return v

    def check_exposure(self) -> None:
        """Refuse to serve mutating routes off-loopback without a token."""
        if self.admin_token is None and not is_loopback(self.host):
            raise ValueError(
                f"refusing to listen on {self.host!r} without AESOP_ADMIN_TOKEN: "
                "set a token or bind to 127.0.0.1"
            )


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
