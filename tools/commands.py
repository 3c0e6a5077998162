"""What the ``aesop`` command's modules share (:mod:`tools.cli` and the command
modules it calls lazily, such as :mod:`tools.recording.cli`): one error type for user
errors and one way to print a result. A module of its own, so that the error raised by a
command module is the class ``aesop`` catches even when the CLI runs as ``__main__``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


class CliError(Exception):
    """A user error: printed without a traceback, exit status 2."""


def not_joined(exc: Exception) -> CliError:
    """A Zenoh session that could not open, with what a router that checks users needs."""
    return CliError(f"cannot join the Zenoh network ({exc}); a router that checks users "
                    "needs AESOP_ZENOH_MODE=client, AESOP_ZENOH_USER and "
                    "AESOP_ZENOH_PASSWORD(_FILE), e.g. the monitor user aesop up prints")


def emit(result: dict[str, Any], as_json: bool) -> None:
    """One JSON object, or ``key  value`` lines."""
    if as_json:
        print(json.dumps(result, allow_nan=False))
        return
    width = max(len(k) for k in result)
    for key, value in result.items():
        shown = f"{value:.4f}" if isinstance(value, float) else value
        print(f"{key:<{width}}  {shown}")


DEFAULT_EMBEDDING_URL = "http://127.0.0.1:8001"  # aesop up's embedding service


def add_url_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--url", default=DEFAULT_EMBEDDING_URL,
                        help=f"the embedding service (default {DEFAULT_EMBEDDING_URL}); the "
                             "token from AESOP_ADMIN_TOKEN")


def control_scenario(path: Path | str | None, *, flag: bool = True):  # -> control's Scenario
    """The scene a command flies, or a usage error naming the file and field (and
    ``--scenario`` when the flag gave it, ``flag``)."""
    from services.control.scenario import ScenarioError, load_scenario

    try:
        return load_scenario(path)
    except (ScenarioError, OSError) as exc:
        raise CliError(f"--scenario: {exc}" if flag else str(exc)) from None


def ros2_config(path: Path | None):  # -> services.ros2.config.BridgeConfig
    """The ROS 2 bridge's config at ``path``, or a usage error naming what is wrong."""
    from services.ros2.config import ConfigError, load_config

    if path is None:
        raise CliError("the bridge needs its config: --config FILE or AESOP_ROS2_CONFIG "
                       "(deploy/ros2/quadrotor.yaml is the quadrotor's)")
    try:
        return load_config(path)
    except ConfigError as exc:
        raise CliError(str(exc)) from None
