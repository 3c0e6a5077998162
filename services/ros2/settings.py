"""Settings of the ROS 2 bridge (``AESOP_ROS2_*``, and the shared ``AESOP_*``)."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from shared.settings import ServiceSettings


class Ros2Settings(ServiceSettings):
    model_config = SettingsConfigDict(env_prefix="AESOP_ROS2_", extra="ignore",
                                      validate_by_name=True)

    port: int = Field(default=8005, ge=0, le=65535, description="HTTP port")
    # services/ros2/config.py
    config: Path | None = Field(
        default=None,
        description="the bridge's YAML file mapping the robot's topics "
                    "(`deploy/ros2/quadrotor.yaml` is the quadrotor's); required")
