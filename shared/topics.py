"""Zenoh key expressions of the stack (docs/architecture.md, "Zenoh key expressions")."""

from __future__ import annotations

import re
from collections.abc import Callable

PREFIX = "aesop"
ANY_ROBOT = "*"

_ROBOT = re.compile(r"^[A-Za-z0-9_\-]+$")


def _check(robot: str) -> str:
    if robot != ANY_ROBOT and not _ROBOT.match(robot):
        raise ValueError(f"invalid robot id {robot!r}: use letters, digits, '_' or '-'")
    return robot


def _robot_key(suffix: str) -> Callable[[str], str]:
    """The function giving ``aesop/<robot>/<suffix>`` for a robot id (checked)."""

    def key(robot: str) -> str:
        return f"{PREFIX}/{_check(robot)}/{suffix}"

    key.__name__ = key.__qualname__ = suffix.replace("/", "_")
    return key


observation = _robot_key("observation")
anomaly = _robot_key("anomaly")
reasoner_request = _robot_key("reasoner/request")
reasoner_decision = _robot_key("reasoner/decision")
state = _robot_key("state")
plan = _robot_key("plan")
regions = _robot_key("regions")
event = _robot_key("event")
vehicle_state = _robot_key("vehicle/state")
vehicle_setpoint = _robot_key("vehicle/setpoint")
vehicle_clock = _robot_key("vehicle/clock")


def health(service: str) -> str:
    return f"{PREFIX}/health/{_check(service)}"


def robot_of(key: str) -> str:
    """The robot id in a concrete key such as ``aesop/robot0/observation``."""
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != PREFIX or parts[1] == "health":
        raise ValueError(f"not a robot key: {key!r}")
    return parts[1]
