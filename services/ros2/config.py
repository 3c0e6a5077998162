"""What the ROS 2 bridge maps: a YAML file (pure: text in, a checked model out).

    robot: robot0                  # the stack's robot these topics belong to
    domain_id: 0                   # ROS_DOMAIN_ID of the robot's nodes
    node: aesop_bridge             # the bridge's node name in the ROS graph
    namespace: /                   # relative topic names resolve under it
    inputs:
      odometry: {topic: /mavros/local_position/odom, frame_id: map}
      scene: {topic: /camera/scene}                 # std_msgs/msg/String
      detections:
        topic: /camera/detections
        type: vision_msgs/msg/Detection2DArray      # or std_msgs/msg/String (JSON)
        classes: {"0": a red box on the ground, ...}
      task: landing on the red box
    outputs:
      setpoint: {topic: /mavros/setpoint_accel/accel_stamped,
                 type: geometry_msgs/msg/AccelStamped, frame_id: map}
      mode: {topic: /aesop/mode}                    # std_msgs/msg/String, JSON
      decision: {topic: /aesop/decision}
      alarms: {topic: /aesop/alarms}

Every field is checked (an unknown one is an error naming it), so is every topic name
and type (:mod:`.wire`). ``type_hash`` on a topic overrides the hash computed from the
type store (for a message package of another version: ``ros2 topic info -v`` prints it).
``max_bytes`` on an input is the largest sample the bridge takes on it (its CDR, header
included; each kind has a default well above what it needs, at most
:data:`MAX_SAMPLE_BYTES`): a larger one is refused before it is copied or decoded.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from . import wire

ODOMETRY: Final = "nav_msgs/msg/Odometry"
STRING: Final = "std_msgs/msg/String"
DETECTIONS: Final = "vision_msgs/msg/Detection2DArray"
ACCEL: Final = "geometry_msgs/msg/AccelStamped"
TWIST: Final = "geometry_msgs/msg/TwistStamped"
MAX_CLASSES = 10_000
# the most an input's max_bytes may be: half the 1 MiB the stack's router passes on
# (tools/stack/acl.py, MAX_MESSAGE_BYTES), which a robot's own router does not enforce
MAX_SAMPLE_BYTES = 512 * 1024


class ConfigError(ValueError):
    """A bridge config that cannot be used (the message names the field)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Topic(_Strict):
    type: str  # pkg/msg/Name: each kind of topic names the types it takes
    topic: str = Field(min_length=1, max_length=256)
    type_hash: str | None = None  # RIHS01_<64 hex>; None: from the type store
    depth: int = Field(default=wire.DEFAULT_DEPTH, ge=1, le=1000)  # its QoS history depth

    @field_validator("topic")
    @classmethod
    def _topic(cls, v: str) -> str:
        try:
            wire.fully_qualified(v)
        except wire.WireError as exc:
            raise ValueError(str(exc)) from None
        return v

    @field_validator("type_hash")
    @classmethod
    def _hash(cls, v: str | None) -> str | None:
        if v is not None:
            try:
                wire.check_hash(v)
            except wire.WireError as exc:
                raise ValueError(str(exc)) from None
        return v


def _max_bytes(default: int) -> int:
    """An input's ``max_bytes`` field, ``default`` unless the config says."""
    field: int = Field(default=default, ge=1024, le=MAX_SAMPLE_BYTES)
    return field


class Input(Topic):
    """A topic the bridge reads: ``max_bytes``, the largest sample it takes (its CDR)."""

    max_bytes: int = _max_bytes(MAX_SAMPLE_BYTES)


class OdometryIn(Input):
    type: Literal["nav_msgs/msg/Odometry"] = ODOMETRY
    # 708 bytes and the two frames' names
    max_bytes: int = _max_bytes(16 * 1024)
    # the ROS frame its poses must be in (header.frame_id); others are dropped
    frame_id: str = Field(default="map", min_length=1, max_length=64)
    # the name the stack gives that frame (VehicleState.frame; control's AESOP_CONTROL_VEHICLE)
    frame: str = Field(default="world", min_length=1, max_length=64)


class SceneIn(Input):
    type: Literal["std_msgs/msg/String"] = STRING
    # an observation's text: 16,000 characters (shared.messages.MAX_TEXT_CHARS) of UTF-8
    max_bytes: int = _max_bytes(64 * 1024)


class DetectionsIn(Input):
    type: Literal["vision_msgs/msg/Detection2DArray", "std_msgs/msg/String"] = DETECTIONS
    # class_id -> the phrase the detector embeds ("a red box on the ground"); for String
    # JSON the labels are the phrases, and classes (when given) maps them too
    classes: dict[str, str] = Field(default_factory=dict, max_length=MAX_CLASSES)
    min_score: float = Field(default=0.0, ge=0.0, le=1.0)  # hypotheses below it are left out
    # about 600 detections of one hypothesis each (420 bytes), or 256 KiB of JSON
    max_bytes: int = _max_bytes(256 * 1024)

    @field_validator("classes")
    @classmethod
    def _phrases(cls, v: dict[str, str]) -> dict[str, str]:
        bad = next((k for k, p in v.items() if not p.strip() or len(p) > 200), None)
        if bad is not None:
            raise ValueError(f"classes[{bad!r}]: a phrase of 1 to 200 characters")
        return v


class Inputs(_Strict):
    odometry: OdometryIn | None = None
    scene: SceneIn | None = None
    detections: DetectionsIn | None = None
    task: str = Field(default="", max_length=1000)  # Observation.task
    # a frame's scene text and detections are paired as they come; with no scene text for
    # this long (s), detections go out alone at once, the phrases as the text
    scene_within_s: float = Field(default=1.0, gt=0.0, le=60.0)


class SetpointOut(Topic):
    type: Literal["geometry_msgs/msg/AccelStamped", "geometry_msgs/msg/TwistStamped"] = ACCEL
    frame_id: str = Field(default="map", min_length=1, max_length=64)
    # the vector in the vehicle's body frame (by the newest odometry's attitude), not the
    # world's: for a base that takes cmd_vel in base_link (set frame_id to match)
    body: bool = False


class StringOut(Topic):
    type: Literal["std_msgs/msg/String"] = STRING


class Outputs(_Strict):
    setpoint: SetpointOut | None = None
    mode: StringOut | None = None
    decision: StringOut | None = None
    alarms: StringOut | None = None


class BridgeConfig(_Strict):
    robot: str = Field(default="robot0", min_length=1, max_length=64,
                       pattern=r"^[A-Za-z0-9_\-]+$")
    domain_id: int = Field(default=0, ge=0, le=232)
    node: str = Field(default="aesop_bridge", pattern=r"^[A-Za-z][A-Za-z0-9_]{0,254}$")
    namespace: str = Field(default="/",
                           pattern=r"^/([A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*)?$")
    inputs: Inputs = Inputs()
    outputs: Outputs = Outputs()

    @model_validator(mode="after")
    def _something(self) -> BridgeConfig:
        if not any(self.topics()):
            raise ValueError("maps no topic: give inputs and/or outputs")
        return self

    def topics(self) -> Iterator[Mapped]:
        """Every mapped topic, inputs first, in the order of the file's schema."""
        entity = 0
        groups: tuple[tuple[Literal["in", "out"], BaseModel], ...] = (
            ("in", self.inputs), ("out", self.outputs))
        for direction, group in groups:
            for role in type(group).model_fields:
                topic = getattr(group, role)
                if isinstance(topic, Topic):
                    entity += 1
                    yield Mapped(role, direction, topic,
                                 wire.fully_qualified(topic.topic, self.namespace), entity)


@dataclass(frozen=True)
class Mapped:
    """One mapped topic: its role (``odometry``, ``setpoint``, ...), direction, settings,
    fully qualified name and the bridge's entity id for it (1, 2, ...; the node is 0)."""

    role: str
    direction: Literal["in", "out"]
    settings: Topic
    name: str
    entity_id: int

    @property
    def ros_type(self) -> str:
        return self.settings.type


def parse_config(text: str, source: str = "config", *, frame: str | None = None
                 ) -> BridgeConfig:
    """The config in ``text`` (YAML); :class:`ConfigError` names what is wrong (``source``,
    the file, and the field; for YAML that does not parse, its line and column). ``frame``:
    the frame the stack's control loop flies in (``AESOP_CONTROL_VEHICLE``'s ``frame``),
    which the odometry's must be: control refuses every state in another."""
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(_not_yaml(exc, source, text)) from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: expected a mapping at the top")
    try:
        config = BridgeConfig.model_validate(raw)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "(top)"
        raise ConfigError(f"{source}: {where}: {first['msg']}") from None
    odometry = config.inputs.odometry
    if frame is not None and odometry is not None and odometry.frame != frame:
        raise ConfigError(f"{source}: inputs.odometry.frame: {odometry.frame!r} is not "
                          f"{frame!r}, the frame control flies in (AESOP_CONTROL_VEHICLE's "
                          "frame): control would refuse every state")
    return config


def _not_yaml(exc: yaml.YAMLError, source: str, text: str) -> str:
    """One line: ``source:line:column: not YAML: the problem`` (PyYAML's own message names
    no file, ``"<unicode string>"``, over several lines)."""
    if isinstance(exc, yaml.MarkedYAMLError) and exc.problem_mark is not None:
        mark = exc.problem_mark
        where = f"{source}:{mark.line + 1}:{mark.column + 1}"
        problem = exc.problem or "a syntax error"
        if exc.context and exc.context_mark is not None:
            problem += f" ({exc.context} at line {exc.context_mark.line + 1})"
        return f"{where}: not YAML: {problem}"
    if isinstance(exc, yaml.reader.ReaderError):  # a character YAML does not allow
        line = text.count("\n", 0, exc.position) + 1
        column = exc.position - text.rfind("\n", 0, exc.position)
        char = chr(exc.character) if isinstance(exc.character, int) else exc.character
        return f"{source}:{line}:{column}: not YAML: character {char!r}: {exc.reason}"
    return f"{source}: not YAML: {' '.join(str(exc).split())}"


def load_config(path: Path, *, frame: str | None = None) -> BridgeConfig:
    """The config in the file at ``path`` (see :func:`parse_config`)."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc.strerror}") from None
    return parse_config(text, str(path), frame=frame)
