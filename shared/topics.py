"""Zenoh key expressions of the stack (docs/architecture.md, "Zenoh key expressions")."""

from __future__ import annotations

import re

PREFIX = "aesop"
ANY_ROBOT = "*"

_ROBOT = re.compile(r"^[A-Za-z0-9_\-]+$")


def _check(robot: str) -> str:
    if robot != ANY_ROBOT and not _ROBOT.match(robot):
        raise ValueError(f"invalid robot id {robot!r}: use letters, digits, '_' or '-'")
    return robot


def observation(robot: str) -> str:
    return f"{PREFIX}/{_check(robot)}/observation"


def anomaly(robot: str) -> str:
    return f"{PREFIX}/{_check(robot)}/anomaly"


def reasoner_request(robot: str) -> str:
    return f"{PREFIX}/{_check(robot)}/reasoner/request"


def reasoner_decision(robot: str) -> str:
    return f"{PREFIX}/{_check(robot)}/reasoner/decision"


def state(robot: str) -> str:
    return f"{PREFIX}/{_check(robot)}/state"


def plan(robot: str) -> str:
    return f"{PREFIX}/{_check(robot)}/plan"


def regions(robot: str) -> str:
    return f"{PREFIX}/{_check(robot)}/regions"


def event(robot: str) -> str:
    return f"{PREFIX}/{_check(robot)}/event"


def health(service: str) -> str:
    return f"{PREFIX}/health/{_check(service)}"


def robot_of(key: str) -> str:
    """The robot id in a concrete key such as ``aesop/robot0/observation``."""
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != PREFIX or parts[1] == "health":
        raise ValueError(f"not a robot key: {key!r}")
    return parts[1]
