"""Typed, frozen, versioned messages that cross a process boundary.

Every message is a pydantic model encoded as JSON on the wire. Each carries
``schema_version`` (bumped on an incompatible change), ``robot`` (the robot id
in the topic) and ``stamp`` (wall-clock seconds, float, when it was made).
Field names follow ``docs/architecture.md``; the paper's symbols are noted where
they apply (o_t, s(e_t), tau, y, K).
"""

from __future__ import annotations

import math
import time
from enum import StrEnum
from typing import Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, field_validator

SCHEMA_VERSION = 1

M = TypeVar("M", bound="Message")


class Message(BaseModel):
    """Base of every bus message: frozen, no unknown fields, JSON on the wire."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    schema_version: int = SCHEMA_VERSION
    robot: str = Field(default="robot0", min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_\-]+$")
    stamp: float = Field(default_factory=time.time)

    def encode(self) -> bytes:
        return self.model_dump_json().encode()

    @classmethod
    def decode(cls: type[M], payload: bytes | str) -> M:
        return cls.model_validate_json(payload)


class Detection(BaseModel):
    """One object detection behind a text observation (e.g. from OWL-ViT)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    label: str
    confidence: float | None = None
    where: str | None = None  # context, e.g. "on the red box", "on the ground"


class Observation(Message):
    """o_t: the robot's text observation at tick ``seq``."""

    seq: int = Field(ge=0)
    task: str = ""
    text: str = Field(min_length=1)
    detections: tuple[Detection, ...] = ()


class Neighbor(BaseModel):
    """A nearest nominal experience in the vector cache."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    id: str
    text: str | None = None
    similarity: float


class AnomalyVerdict(Message):
    """Fast reasoner output for observation ``seq``: s(e_t) compared with tau.

    ``threshold`` is None when the cache has no calibration; the verdict is
    then an anomaly (fail-safe) and ``reason`` says so.
    """

    seq: int = Field(ge=0)
    score: float
    threshold: float | None
    is_anomaly: bool
    k: int = Field(ge=1)
    neighbors: tuple[Neighbor, ...] = ()
    model: str
    cache: str
    cache_version: int = Field(ge=0)
    latency_ms: float = Field(ge=0.0)
    reason: str | None = None

    @field_validator("score")
    @classmethod
    def _finite(cls, v: float) -> float:
        if not math.isfinite(v):
            raise ValueError("score must be finite")
        return v


class Option(BaseModel):
    """One choice offered to the slow reasoner: 0 = continue, 1..d = recovery region."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    index: int = Field(ge=0)
    label: str
    description: str = ""


class ReasonerRequest(Message):
    """Control -> reasoner: decide among ``options`` within ``deadline_s`` (K)."""

    request_id: str
    observation: Observation
    options: tuple[Option, ...] = Field(min_length=1)
    deadline_s: float = Field(gt=0.0)


DecisionSource = Literal["llm", "timeout", "parse_error", "backend_error"]


class ReasonerDecision(Message):
    """Reasoner -> control: y, the chosen option index, and where it came from."""

    request_id: str
    choice: int = Field(ge=0)
    source: DecisionSource
    rationale: str = ""
    latency_ms: float = Field(ge=0.0)
    model: str = ""


class Mode(StrEnum):
    """Algorithm 1's modes, as the control loop runs them and ``ControlState`` carries them."""

    WAITING = "waiting"  # the flight has not started: the detector has not answered yet
    NOMINAL = "nominal"
    PENDING = "anomaly_pending"
    RECOVERING = "recovering"


class ControlState(Message):
    """Closed-loop state at time ``t`` (s): x (12 states) and u, the controller's input in
    its planning model's units (thrust and torques, or 3 accelerations), Algorithm 1 mode."""

    t: float
    x: tuple[float, ...] = Field(min_length=12, max_length=12)
    u: tuple[float, ...] = Field(min_length=1, max_length=12)
    mode: Mode
    t_anom: float | None = None
    chosen: int | None = None
    active_regions: tuple[int, ...] = ()


Point3 = tuple[float, float, float]


class PlanSnapshot(Message):
    """The MPC plan tree at time ``t``: nominal branch and one branch per recovery region."""

    t: float
    nominal: tuple[Point3, ...] = ()
    recovery: dict[int, tuple[Point3, ...]] = Field(default_factory=dict)
    consensus_steps: int = Field(ge=0)
    solve_ms: float = Field(ge=0.0)
    status: str


class RegionBox(BaseModel):
    """One recovery region as the dashboard draws it: a box of rest positions (m)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    index: int = Field(ge=1)  # the option index y the reasoner may choose
    name: str
    label: str
    kind: Literal["landing", "hover"]
    position_lo: Point3
    position_hi: Point3


class Regions(Message):
    """The recovery regions the controller keeps feasible, and the goal of the nominal task.

    Published on start, whenever they change and every second, so a late subscriber
    draws them within a second.
    """

    regions: tuple[RegionBox, ...]
    goal: Point3


Severity = Literal["info", "warning", "alarm"]


class Event(Message):
    """Something a person should see: a mode change, an alarm, a fallback."""

    source: str
    kind: str
    severity: Severity = "info"
    message: str = ""
    data: dict[str, str | int | float | bool | None] = Field(default_factory=dict)
