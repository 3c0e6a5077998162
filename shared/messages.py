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
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, field_validator, model_validator

SCHEMA_VERSION = 1

M = TypeVar("M", bound="Message")


def _not_a_bool(value: Any) -> Any:
    """pydantic's lax mode reads true/false as 1/0; a number field refuses them."""
    if isinstance(value, bool):
        raise ValueError("expected a number, not true or false")
    return value


NotBool = BeforeValidator(_not_a_bool)
Int = Annotated[int, NotBool]  # an int that is not a bool
Float = Annotated[float, NotBool]  # a float that is not a bool
Finite = Annotated[float, Field(allow_inf_nan=False), NotBool]  # and neither inf nor NaN

# Ceilings of what crosses the bus, whatever a service's settings allow (each service
# applies its own, lower, limits too): a message past them is dropped undecoded and
# counted (shared.bus), like one that is not JSON.
MAX_TEXT_CHARS = 16_000
MAX_TASK_CHARS = 1_000
MAX_DETECTIONS = 64
MAX_LABEL_CHARS = 200
MAX_AHEAD = 16  # commands of a plan a set-point carries ahead
# limits of an optional number go before NotBool, or pydantic cannot publish them:
# Annotated[int, Field(ge=1), NotBool] | None


class Message(BaseModel):
    """Base of every bus message: frozen, no unknown fields, JSON on the wire."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    schema_version: Int = SCHEMA_VERSION
    robot: str = Field(default="robot0", min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_\-]+$")
    stamp: Finite = Field(default_factory=time.time)

    def encode(self) -> bytes:
        return self.model_dump_json().encode()

    @classmethod
    def decode(cls: type[M], payload: bytes | str) -> M:
        return cls.model_validate_json(payload)


class Detection(BaseModel):
    """One object detection behind a text observation (e.g. from OWL-ViT)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    label: str = Field(min_length=1, max_length=MAX_LABEL_CHARS)
    confidence: Annotated[float, Field(allow_inf_nan=False), NotBool] | None = None
    # context, e.g. "on the red box", "on the ground"
    where: str | None = Field(default=None, max_length=MAX_LABEL_CHARS)

    @property
    def phrase(self) -> str:
        """What the detector embeds: "a drill on the ground" (label, then where)."""
        return self.label if not self.where else f"{self.label} {self.where}"


class Observation(Message):
    """o_t: the robot's text observation at tick ``seq``."""

    seq: Int = Field(ge=0)
    task: str = Field(default="", max_length=MAX_TASK_CHARS)
    text: str = Field(min_length=1, max_length=MAX_TEXT_CHARS)
    detections: tuple[Detection, ...] = Field(default=(), max_length=MAX_DETECTIONS)


class Neighbor(BaseModel):
    """A nearest nominal experience in the vector cache."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    id: str
    text: str | None = None
    similarity: Float


class DetectionMatch(BaseModel):
    """One of an observation's detections beside the nearest detection of the cache's
    nominal experiences: "a keyboard on the ground", nearest "a drill on the ground", 0.61.
    ``p_value``: its own conformal p-value against the cache's calibration (None when
    the cache's detections are not calibrated)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    detection: str
    nearest: str
    similarity: Float
    p_value: Float | None = None


class PairMatch(BaseModel):
    """Two of an observation's detections, each nominal perhaps, that no nominal
    experience holds together, beside the nearest pair that one does: "a person on the
    floor" and "a forklift moving", nearest "a person on the floor" and "a shelf", 0.41
    (the smaller of the two members' similarities). ``p_value``: the pair's conformal
    p-value (None when the cache's pairs are not calibrated)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    detections: tuple[str, str]
    nearest: tuple[str, str]
    similarity: Float
    p_value: Float | None = None


class Drift(BaseModel):
    """The robot's detector flags more than its calibration allows (a binomial test on its
    recent verdicts): it may be seeing new wording (a new captioner), not new objects.
    ``phrases``: the new detection phrases its flagged observations held most often."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    flagged: Int = Field(ge=0)
    seen: Int = Field(ge=1)
    phrases: tuple[str, ...] = Field(default=(), max_length=MAX_DETECTIONS)


class AnomalyVerdict(Message):
    """Fast reasoner output for observation ``seq``: s(e_t) compared with tau.

    ``threshold`` is None when the cache has no calibration; the verdict is
    then an anomaly (fail-safe) and ``reason`` says so. For an observation with
    detections, scored against a cache whose experiences have them, ``p_value`` is the
    combined conformal p-value (anomaly iff it is below 1 - alpha) and ``detections``
    the observation's least nominal detections, worst first; ``pair``, when the cache
    calibrated pairs, its least nominal pair of detections (if no nominal experience
    holds that pair as it is).
    """

    seq: Int = Field(ge=0)
    score: Float
    threshold: Float | None
    is_anomaly: bool
    k: Int = Field(ge=1)
    neighbors: tuple[Neighbor, ...] = ()
    model: str
    cache: str
    cache_version: Int = Field(ge=0)
    latency_ms: Float = Field(ge=0.0)
    reason: str | None = None
    p_value: Float | None = None
    detections: tuple[DetectionMatch, ...] = ()
    pair: PairMatch | None = None
    drift: Drift | None = None

    @field_validator("score")
    @classmethod
    def _finite(cls, v: float) -> float:
        if not math.isfinite(v):
            raise ValueError("score must be finite")
        return v


class Option(BaseModel):
    """One choice offered to the slow reasoner: 0 = continue, 1..d = recovery region."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    index: Int = Field(ge=0)
    label: str = Field(min_length=1, max_length=200, pattern=r"\S")  # one line in the prompt
    description: str = Field(default="", max_length=1000)


class ReasonerRequest(Message):
    """Control -> reasoner: decide among ``options`` within ``deadline_s`` (K).
    ``unusual``: the detections the verdict that raised the anomaly named (the prompt
    shows them with their nearest nominal detections), ``unusual_pair`` the pair it
    named."""

    request_id: str = Field(min_length=1, max_length=128)
    observation: Observation
    options: tuple[Option, ...] = Field(min_length=1, max_length=64)
    deadline_s: Finite = Field(gt=0.0)
    unusual: tuple[DetectionMatch, ...] = Field(default=(), max_length=MAX_DETECTIONS)
    unusual_pair: PairMatch | None = None
    drift: Drift | None = None


# refused: no model was asked (the scene tripped the injection check, or its options
# cannot be put in a prompt); the others: docs/reasoner.md
DecisionSource = Literal["llm", "timeout", "parse_error", "backend_error", "refused"]


class ReasonerDecision(Message):
    """Reasoner -> control: y, the chosen option index, and where it came from. ``answer``:
    what the model wrote, as it wrote it (the winning answer, else the first that did not
    parse; empty when no model answered), so a wrong or unparsable answer can be read."""

    request_id: str = Field(min_length=1, max_length=128)
    choice: Int = Field(ge=0)
    source: DecisionSource
    rationale: str = Field(default="", max_length=MAX_TEXT_CHARS)
    latency_ms: Float = Field(ge=0.0)
    model: str = ""
    answer: str = Field(default="", max_length=MAX_TEXT_CHARS)


class Mode(StrEnum):
    """Algorithm 1's modes, as the control loop runs them and ``ControlState`` carries them."""

    WAITING = "waiting"  # the flight has not started: the detector has not answered yet
    NOMINAL = "nominal"
    PENDING = "anomaly_pending"
    RECOVERING = "recovering"


class ControlState(Message):
    """Closed-loop state at time ``t`` (s): x (12 states) and u, the controller's input in
    its planning model's units (thrust and torques, or 3 accelerations), Algorithm 1 mode."""

    t: Float
    # the arrays only the control loop writes take plain floats: a validator per number
    # made every message 2-3x slower to build and to read
    x: tuple[float, ...] = Field(min_length=12, max_length=12)
    u: tuple[float, ...] = Field(min_length=1, max_length=12)
    mode: Mode
    t_anom: Float | None = None
    chosen: Int | None = None
    active_regions: tuple[Int, ...] = ()
    # how old the vehicle state this tick planned from was (s, since it was valid);
    # None when it had none fresh (waiting, or flying blind)
    state_age_s: Float | None = None


Point3 = tuple[Float, Float, Float]
Path3 = tuple[tuple[float, float, float], ...]  # a planned path (m), as only the loop writes it


class PlanSnapshot(Message):
    """The MPC plan tree at time ``t``: nominal branch and one branch per recovery region."""

    t: Float
    nominal: Path3 = ()
    recovery: dict[int, Path3] = Field(default_factory=dict)
    consensus_steps: Int = Field(ge=0)
    solve_ms: Float = Field(ge=0.0)
    status: str


class RegionBox(BaseModel):
    """One recovery region as the dashboard draws it: a box of rest positions (m)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    index: Int = Field(ge=1)  # the option index y the reasoner may choose
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


# --------------------------------------------------------------------------- the vehicle

Quaternion4 = tuple[Float, Float, Float, Float]
Covariance3 = tuple[Float, Float, Float, Float, Float, Float, Float, Float, Float]


class VehicleState(Message):
    """A vehicle's state estimate, vehicle -> control (``aesop/{robot}/vehicle/state``), at
    the vehicle's own rate.

    ``stamp`` is the time the estimate is valid for, on the vehicle's clock (control
    does not assume it shares that clock: it judges freshness by arrival and ``seq``,
    and reads the offset from ``aesop/{robot}/vehicle/clock`` when the vehicle answers
    it). ``frame`` names the world frame (x forward, y left, z up, m); ``attitude`` is the
    unit quaternion ``(w, x, y, z)`` from the body frame (x forward, y left, z up) to it,
    ``body_rates`` the angular velocity in the body frame. ``acceleration`` (optional) is
    the acceleration the vehicle realizes of the commands at ``stamp`` (world frame,
    gravity excluded: the planning model's lag state, e.g. the lagged command its flight
    controller tracks): with it control bounds each command's step from what the vehicle
    does, not from what it predicts of the commands it sent. Numbers are not checked for
    finiteness here: control refuses a non-finite state with an alarm, it does not drop it
    unseen.
    """

    seq: Int = Field(ge=0)
    frame: str = Field(default="world", min_length=1, max_length=64)
    position: Point3  # m
    velocity: Point3  # m/s, world frame
    attitude: Quaternion4 = (1.0, 0.0, 0.0, 0.0)
    body_rates: Point3 = (0.0, 0.0, 0.0)  # rad/s
    acceleration: Point3 | None = None  # m/s^2, world frame, realized (optional)
    position_covariance: Covariance3 | None = None  # m^2, row-major 3x3
    velocity_covariance: Covariance3 | None = None  # (m/s)^2, row-major 3x3


class VehicleSetpoint(Message):
    """What the control loop commands, control -> vehicle (``aesop/{robot}/vehicle/setpoint``),
    once per tick while it flies.

    Exactly one command: ``acceleration`` (m/s^2, world frame: the ``point-mass`` model, for
    the vehicle's flight controller to track) or ``thrust`` (N) with ``torque`` (N m, body
    frame: the ``quadrotor`` hover model, for the motors). ``position`` and ``velocity`` are
    the plan at the same instant, for a vehicle that tracks those instead. ``t`` is that
    instant and ``valid_until`` the moment past which, without a newer set-point, the vehicle
    holds position on its own: both on the *vehicle's* clock (the stamp ``state_stamp`` of
    the state ``state_seq`` this was computed from, plus that state's age when the tick
    ran), so a vehicle never compares two clocks. ``stamp`` is control's own clock.

    ``ahead``: the plan's next commands (same kind as the command), the ``j``-th due from
    ``t + j * step_s`` (packetized predictive control): a vehicle that has no newer set-point
    by then flies the plan on through a late or missed tick rather than holding one
    command for longer than it was planned for. Optional to follow; none past
    ``valid_until``.
    """

    seq: Int = Field(ge=0)
    state_seq: Int = Field(ge=0)
    state_stamp: Finite
    t: Finite
    valid_until: Finite
    mode: Mode
    acceleration: Point3 | None = None
    thrust: Float | None = None
    torque: Point3 | None = None
    position: Point3
    velocity: Point3
    ahead: tuple[tuple[Finite, ...], ...] = Field(default=(), max_length=MAX_AHEAD)
    step_s: Annotated[float, Field(gt=0.0, allow_inf_nan=False), NotBool] | None = None

    @model_validator(mode="after")
    def _one_command(self) -> VehicleSetpoint:
        motors = (self.thrust is not None, self.torque is not None)
        if motors[0] != motors[1]:
            raise ValueError("thrust and torque go together")
        if (self.acceleration is not None) == motors[0]:
            raise ValueError("a set-point carries either an acceleration or a thrust with a "
                             "torque")
        if self.ahead:
            if self.step_s is None:
                raise ValueError("ahead needs step_s")
            size = 3 if self.acceleration is not None else 4
            if any(len(u) != size for u in self.ahead):
                raise ValueError(f"each command ahead has {size} numbers, as the command")
        return self

    def _passed(self, clock: float) -> int:
        """How many commands ahead have come due by ``clock`` (the vehicle's)."""
        if not self.ahead or self.step_s is None:
            return 0
        n, step = len(self.ahead), self.step_s
        j = min(max(math.floor((clock - self.t) / step), 0), n)
        while j < n and self.t + (j + 1) * step <= clock:  # as the instants round
            j += 1
        while j > 0 and self.t + j * step > clock:
            j -= 1
        return j

    def command_at(self, clock: float) -> tuple[float, ...]:
        """The command due at ``clock`` (the vehicle's): the plan's ahead from its instant."""
        j = self._passed(clock)
        if j:
            return self.ahead[j - 1]
        if self.acceleration is not None:
            return self.acceleration
        assert self.thrust is not None and self.torque is not None  # the validator's rule
        return (self.thrust, *self.torque)

    def switches_after(self, clock: float) -> float | None:
        """The next instant after ``clock`` at which :meth:`command_at` changes, if any."""
        j = self._passed(clock)
        if self.step_s is None or j >= len(self.ahead):
            return None
        return self.t + (j + 1) * self.step_s


class VehicleClock(Message):
    """The vehicle's answer to a query on ``aesop/{robot}/vehicle/clock``: its ``stamp`` is
    the vehicle's clock when it answered, so control can map state stamps onto its own
    clock (the query's round trip bounds the error). Optional: without it control takes the
    fastest arrival it has seen as instant."""


class VehicleReset(Message):
    """A query on ``aesop/{robot}/vehicle/reset`` (optional to answer): be at rest at
    ``position`` (world frame, m), level, from now on, following no set-point older than
    the query; a simulator teleports, a real vehicle may answer nothing (an operator brings
    it there). The answer is the vehicle's :class:`VehicleState` once it is there.
    ``aesop demo`` starts each flight with one."""

    position: Point3
