"""What the simulator's routes take and answer (``/openapi.json``, :mod:`.client`)."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, StrictBool

from shared.messages import Float, Int, NotBool, Point3

PositiveS = Annotated[float, Field(gt=0.0, le=3600.0), NotBool]


class Body(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Answer(BaseModel):
    model_config = ConfigDict(extra="ignore")


class ResetBody(Body):
    start: Point3 | None = None  # m, inside the fence; None: a fresh draw from the start box


class ReportingBody(Body):
    """How the vehicle reports its state from now on (each field optional)."""

    rate_hz: Annotated[float, Field(gt=0.0, le=1000.0), NotBool] | None = None
    delay_s: Annotated[float, Field(ge=0.0, le=10.0), NotBool] | None = None
    position_noise_m: Annotated[float, Field(ge=0.0, le=10.0), NotBool] | None = None
    velocity_noise_m_s: Annotated[float, Field(ge=0.0, le=10.0), NotBool] | None = None
    drop_rate: Annotated[float, Field(ge=0.0, lt=1.0), NotBool] | None = None
    clock_offset_s: Annotated[float, Field(ge=-1e6, le=1e6), NotBool] | None = None


class FaultsBody(Body):
    """Faults from now on: report nothing for ``dropout_s``; stop reporting for good
    (``stop``) or start again (``resume``, which also ends a drop-out); lose the
    set-points that arrive within ``deaf_s``; add ``jump`` (m) to the reported position
    for ``jump_s``."""

    dropout_s: PositiveS | None = None
    stop: StrictBool = False
    resume: StrictBool = False
    deaf_s: PositiveS | None = None
    jump: Point3 | None = None
    jump_s: PositiveS | None = None


class Truth(Answer):
    position: Point3  # m
    velocity: Point3  # m/s
    attitude: Point3  # roll, pitch, yaw (rad)
    body_rates: Point3  # rad/s


class SimState(Answer):
    """``GET /v1/state``: the truth, what the vehicle is doing and how it reports."""

    robot: str
    scenario: str
    t: Float  # simulated s since the last reset
    time_scale: Float
    truth: Truth
    holding: bool  # no valid set-point: the vehicle holds on its own
    setpoint_seq: Int | None
    # received, refused (and refused_<reason>: kind, older, future, validity), age_p50_ms/p99/max
    setpoints: dict[str, Float | Int | None]
    states_published: Int
    reporting: dict[str, Float]
    faults: dict[str, Float | bool | None]


class TraceAnswer(Answer):
    """``GET /v1/trace``: the truth since the last reset, at ``AESOP_SIM_TRACE__HZ``."""

    t: list[Float]  # simulated s since the reset
    x: list[list[Float]]  # 12-state truth
    holding: list[bool]
