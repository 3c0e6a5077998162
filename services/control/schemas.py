"""What the control service's routes take and answer (``/openapi.json``, :mod:`.client`)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict

from shared.messages import ControlState, Mode, Point3, RegionBox


class Body(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Answer(BaseModel):
    model_config = ConfigDict(extra="ignore")


class RegionsBody(Body):
    # checked by scenario.regions_from_list, whose errors name the entry and field
    regions: list[Any]


class ResetBody(Body):
    start: Point3 | None = None  # m; None: a fresh draw from the start box


class State(Answer):
    """``GET /v1/state``: the last tick and the loop's timing."""

    robot: str
    state: ControlState | None  # None before the first tick
    mode: Mode
    status: str | None  # the last solve's status
    method: str  # aesop, fsmpc or naive
    scenario: str
    verdict_stale: bool | None
    pending_request: str | None  # request_id of the request being waited on
    loop: dict[str, float | int | None]  # rate_hz, ticks, overruns, jitter and tick percentiles


class RegionsAnswer(Answer):
    """``GET`` / ``POST /v1/regions``: the recovery regions, the goal and the mode."""

    regions: list[RegionBox]
    goal: Point3
    mode: Mode


class ResetAnswer(Answer):
    start: Point3  # m
    mode: Mode
