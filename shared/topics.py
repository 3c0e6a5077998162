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
vehicle_state = _robot_key("vehicle/state")
vehicle_setpoint = _robot_key("vehicle/setpoint")
vehicle_clock = _robot_key("vehicle/clock")
vehicle_reset = _robot_key("vehicle/reset")  # optional: a query to start a flight over
vehicle_truth = _robot_key("vehicle/truth")  # optional: a simulator's exact state


ROBOT_SOURCE = "robot"  # the source of the events a robot (its own software) publishes


def event(robot: str, source: str) -> str:
    """``aesop/<robot>/event/<source>``: each publisher of events has a key of its own
    (``embedding``, ``reasoner``, ``control``, ``dashboard``, the robot's ``robot``), which
    the router lets only that user put, so the key says who sent an event."""
    return f"{PREFIX}/{_check(robot)}/event/{_check(source)}"


def events(robot: str) -> str:
    """Every source's events of ``robot``."""
    return f"{PREFIX}/{_check(robot)}/event/*"


def source_of(key: str) -> str:
    """The source in a concrete event key such as ``aesop/robot0/event/control``."""
    parts = key.split("/")
    if len(parts) != 4 or parts[0] != PREFIX or parts[2] != "event":
        raise ValueError(f"not an event key: {key!r}")
    return parts[3]


def health(service: str) -> str:
    return f"{PREFIX}/health/{_check(service)}"


def robot_of(key: str) -> str:
    """The robot id in a concrete key such as ``aesop/robot0/observation``."""
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != PREFIX or parts[1] == "health":
        raise ValueError(f"not a robot key: {key!r}")
    return parts[1]
