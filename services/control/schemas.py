"""What the control service's routes take and answer (``/openapi.json``, :mod:`.client`)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from shared.messages import ControlState, Float, Int, Mode, NotBool, Point3, RegionBox


class Body(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Answer(BaseModel):
    model_config = ConfigDict(extra="ignore")


class RegionIn(Body):
    """One recovery region: a box of rest positions (m) inside the scenario's fence."""

    index: Annotated[int, Field(ge=1), NotBool] | None = None  # the option y; default: its place
    name: str = Field(min_length=1, max_length=64)
    label: str | None = Field(default=None, max_length=200)  # default: the name
    kind: Literal["landing", "hover"] = "landing"
    position_lo: Point3
    position_hi: Point3


class RegionsBody(Body):
    # the geometry (lo <= hi, inside the fence, indices 1..d, unique names) is checked
    # by scenario.regions_from_list and the runtime; their errors name the entry
    regions: list[RegionIn] = Field(min_length=1, max_length=16)


class ResetBody(Body):
    """Nothing: the flight restarts from wherever the vehicle is (the control service
    never moves the vehicle; a simulator has its own ``POST /v1/reset``)."""


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
    loop: dict[str, Float | Int | None]  # rate_hz, ticks, overruns, jitter and tick percentiles
    # fresh, seq, age_ms, clock (sync | arrival), clock_round_trip_ms, accepted, refused,
    # age_p50_ms, age_p99_ms, age_max_ms, stale_ticks, setpoints
    vehicle: dict[str, Float | Int | bool | str | None]


class RegionsAnswer(Answer):
    """``GET`` / ``POST /v1/regions``: the recovery regions, the goal and the mode."""

    regions: list[RegionBox]
    goal: Point3
    mode: Mode


class ResetAnswer(Answer):
    position: Point3 | None  # m: the vehicle's newest position; None before any state
    mode: Mode
