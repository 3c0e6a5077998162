"""ROS 2 messages <-> the stack's messages (pure; CDR by ``rosbags``).

In: ``nav_msgs/msg/Odometry`` -> :class:`VehicleState` (REP 103/105: the pose in
``header.frame_id``, the twist in ``child_frame_id``, the body: so the linear velocity is
rotated into the world by the attitude); ``std_msgs/msg/String`` scene text and
``vision_msgs/msg/Detection2DArray`` (class ids -> phrases by the config) or a String of
JSON -> :class:`Observation`. Out: :class:`VehicleSetpoint` -> ``AccelStamped`` (its
acceleration) or ``TwistStamped`` (the plan's velocity), both stamped on the vehicle's
clock; anything else -> ``std_msgs/msg/String`` of JSON.

A sample that cannot be used raises :class:`BadSample` with its reason (one of
:data:`REASONS`), which the bridge counts and logs once per topic and reason.
"""

from __future__ import annotations

import functools
import json
import math
import struct
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from shared.frames import rotate
from shared.messages import MAX_DETECTIONS, Detection, Observation, VehicleSetpoint, VehicleState

from .config import ACCEL, DETECTIONS, ODOMETRY, STRING, TWIST, DetectionsIn, Mapped

# why a sample was dropped: in (the first eight, and ``size``: over its topic's
# ``max_bytes``), out (the set-point cannot be written as the configured type), either way
# (``queue``: the oldest of a full queue) or a fault of the bridge's own (logged with its
# traceback)
REASONS = ("attachment", "type", "cdr", "non_finite", "frame", "unknown_class", "json",
           "empty", "size", "queue", "unsupported", "error")
# CDR's primitive sizes (XCDR1, as rmw_zenoh's Fast-CDR writes): each aligned to its size
_PRIMITIVE_BYTES = {"bool": 1, "byte": 1, "char": 1, "int8": 1, "uint8": 1, "int16": 2,
                    "uint16": 2, "int32": 4, "uint32": 4, "float32": 4, "int64": 8,
                    "uint64": 8, "float64": 8}
ENCAPSULATIONS = (b"\x00\x00", b"\x00\x01")  # CDR big- and little-endian

# vision_msgs 4.x (Humble and later; ros-perception/vision_msgs, ros2 branch), which the
# ROS 2 stores of rosbags do not hold
VISION_MSGS = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\n"
                                     "float64 size_y\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": "vision_msgs/ObjectHypothesis hypothesis\n"
                                                "geometry_msgs/PoseWithCovariance pose\n",
    "vision_msgs/msg/Detection2D": "std_msgs/Header header\n"
                                   "vision_msgs/ObjectHypothesisWithPose[] results\n"
                                   "vision_msgs/BoundingBox2D bbox\nstring id\n",
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\n"
                                        "vision_msgs/Detection2D[] detections\n",
}


class BadSample(ValueError):
    def __init__(self, reason: str, detail: str) -> None:
        assert reason in REASONS, reason
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


@functools.cache
def typestore() -> Typestore:
    """Jazzy's message types, with vision_msgs."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for name, text in VISION_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def type_hash(ros_type: str) -> str:
    """The RIHS01 hash of ``ros_type`` (as ``ros2 topic info -v`` prints it)."""
    return str(typestore().hash_rihs01(ros_type))


def topic_hash(mapped: Mapped) -> str:
    """A mapped topic's hash: the config's, else its type's."""
    return mapped.settings.type_hash or type_hash(mapped.ros_type)


def serialize(msg: Any, ros_type: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, ros_type))


def deserialize(raw: bytes, ros_type: str) -> Any:
    """``raw`` (CDR with its header) as ``ros_type`` (:class:`BadSample` ``cdr`` when it
    is not one)."""
    try:
        return typestore().deserialize_cdr(raw, ros_type)
    except Exception as exc:  # rosbags raises struct, index, unicode and its own errors
        raise BadSample("cdr", f"not a CDR {ros_type}: {type(exc).__name__}") from None


@functools.cache
def min_cdr_bytes(ros_type: str) -> int:
    """The fewest bytes a CDR ``ros_type`` can take, its 4-byte encapsulation header
    included: every string empty, every sequence empty; a sample shorter is truncated."""
    store = typestore()

    def walk(at: int, desc: tuple[Any, Any]) -> int:
        kind, arg = desc
        if kind == Nodetype.NAME:
            for _, field in store.fielddefs[arg][1]:
                at = walk(at, field)
            return at
        if kind == Nodetype.ARRAY:
            sub, length = arg
            for _ in range(length):
                at = walk(at, sub)
            return at
        if kind == Nodetype.SEQUENCE:
            return -(-at // 4) * 4 + 4  # its length
        name: str = arg[0]
        if name in ("string", "wstring"):
            return -(-at // 4) * 4 + 4 + (1 if name == "string" else 0)  # its length, a NUL
        size = _PRIMITIVE_BYTES[name]
        return -(-at // size) * size + size

    return 4 + walk(0, (Nodetype.NAME, ros_type))


def check_cdr(raw: bytes, ros_type: str) -> None:
    """What can be told of ``raw`` as a CDR ``ros_type`` without decoding it (a
    :class:`BadSample` ``cdr``), in a few microseconds: its encapsulation header, its
    least length, then its layout skimmed (every string's length and terminator, each
    fixed block in bounds, the size at the end as the decoder checks it) up to the first
    sequence of messages, which only decoding walks. What the decoder takes passes."""
    if raw[:2] not in ENCAPSULATIONS:
        raise BadSample("cdr", f"not a CDR {ros_type}: no CDR encapsulation header")
    if len(raw) < min_cdr_bytes(ros_type):
        raise BadSample("cdr", f"not a CDR {ros_type}: truncated ({len(raw)} bytes, it "
                               f"takes at least {min_cdr_bytes(ros_type)})")
    u32 = _U32[raw[1]]
    end, at = len(raw), 4  # alignment counts from after the header
    for step in _plan(ros_type):
        if step[0] == "fixed":
            at = 4 + -(-(at - 4) // step[1]) * step[1] + step[2]
            if at > end:
                raise BadSample("cdr", f"not a CDR {ros_type}: truncated")
        elif step[0] == "string":
            at = 4 + -(-(at - 4) // 4) * 4
            length = u32.unpack_from(raw, at)[0] if at + 4 <= end else 0
            at += 4 + length
            if length == 0 or at > end or raw[at - 1] != 0:
                raise BadSample("cdr", f"not a CDR {ros_type}: a string's length or "
                                       "terminator is wrong")
        elif step[0] == "sequence":
            at = 4 + -(-(at - 4) // 4) * 4
            count = u32.unpack_from(raw, at)[0] if at + 4 <= end else end
            at += 4 + count * step[1]
            if at > end:
                raise BadSample("cdr", f"not a CDR {ros_type}: a sequence's length is wrong")
        else:  # a sequence of messages: the decoder walks the rest
            return
    if not 0 <= end - at <= 3:  # as the decoder: up to 3 bytes of padding at the end
        raise BadSample("cdr", f"not a CDR {ros_type}: {end} bytes where it takes {at}")


_U32 = {0: struct.Struct(">I"), 1: struct.Struct("<I")}


@functools.cache
def _plan(ros_type: str) -> tuple[tuple[Any, ...], ...]:
    """``ros_type``'s CDR layout as steps for :func:`check_cdr`: ``("fixed", align,
    size)`` (primitives in a row, each aligned within the block, the block to its first),
    ``("string",)``, ``("sequence", size)`` (of primitives of at most 4 bytes, whose
    alignment the count already gives) and ``("stop",)`` before a sequence of anything
    else."""
    store = typestore()
    steps: list[list[Any]] = []

    def fixed(align: int, size: int) -> None:
        last = steps[-1] if steps else None
        if last is not None and last[0] == "fixed" and last[1] >= align:
            last[2] = -(-last[2] // align) * align + size
        else:
            steps.append(["fixed", align, size])

    def walk(desc: tuple[Any, Any]) -> bool:  # False: stopped
        kind, arg = desc
        if kind == Nodetype.NAME:
            return all(walk(field) for _, field in store.fielddefs[arg][1])
        if kind == Nodetype.ARRAY:
            sub, length = arg
            if sub[0] == Nodetype.BASE and sub[1][0] in _PRIMITIVE_BYTES:
                size = _PRIMITIVE_BYTES[sub[1][0]]
                if length:
                    fixed(size, size * length)
                return True
            return all(walk(sub) for _ in range(length))
        if kind == Nodetype.SEQUENCE:
            sub = arg[0]
            if sub[0] == Nodetype.BASE and _PRIMITIVE_BYTES.get(sub[1][0], 8) <= 4:
                steps.append(["sequence", _PRIMITIVE_BYTES[sub[1][0]]])
                return True
            steps.append(["stop"])
            return False
        name: str = arg[0]
        if name == "string":
            steps.append(["string"])
            return True
        if name not in _PRIMITIVE_BYTES:  # wstring: left to the decoder
            steps.append(["stop"])
            return False
        fixed(_PRIMITIVE_BYTES[name], _PRIMITIVE_BYTES[name])
        return True

    walk((Nodetype.NAME, ros_type))
    return tuple(tuple(step) for step in steps)


def seconds(stamp: Any) -> float:
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def ros_time(t: float) -> Any:
    """``builtin_interfaces/msg/Time`` of ``t`` (s)."""
    sec = math.floor(t)
    nanosec = min(int(round((t - sec) * 1e9)), 999_999_999)
    return typestore().types["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=nanosec)


def header(t: float, frame_id: str) -> Any:
    return typestore().types["std_msgs/msg/Header"](stamp=ros_time(t), frame_id=frame_id)


# --------------------------------------------------------------------------- in


def vehicle_state(raw: bytes, *, robot: str, seq: int, frame_id: str, frame: str
                  ) -> VehicleState:
    """A CDR ``nav_msgs/msg/Odometry`` as the stack's vehicle state."""
    odom = deserialize(raw, ODOMETRY)
    if odom.header.frame_id != frame_id:
        raise BadSample("frame", f"pose in {odom.header.frame_id!r}, the config says "
                                 f"{frame_id!r}")
    pose, twist = odom.pose.pose, odom.twist.twist
    position = (pose.position.x, pose.position.y, pose.position.z)
    q = (pose.orientation.w, pose.orientation.x, pose.orientation.y, pose.orientation.z)
    body_v = (twist.linear.x, twist.linear.y, twist.linear.z)
    rates = (twist.angular.x, twist.angular.y, twist.angular.z)
    stamp = seconds(odom.header.stamp)
    numbers = [*position, *q, *body_v, *rates, stamp]
    if not all(math.isfinite(v) for v in numbers):
        raise BadSample("non_finite", "a position, attitude, velocity or stamp is not finite")
    norm = math.sqrt(sum(c * c for c in q))
    if abs(norm - 1.0) > 0.01:
        raise BadSample("non_finite", f"the attitude is no unit quaternion (|q| = {norm:.3g})")
    q = (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm)
    cov = np.asarray(odom.pose.covariance, dtype=float).reshape(6, 6)
    vcov = np.asarray(odom.twist.covariance, dtype=float).reshape(6, 6)
    return VehicleState(robot=robot, stamp=stamp, seq=seq, frame=frame, position=position,
                        velocity=rotate(q, body_v), attitude=q, body_rates=rates,
                        position_covariance=_covariance(cov[:3, :3]),
                        velocity_covariance=_covariance(_to_world(q, vcov[:3, :3])))


def _to_world(q: tuple[float, float, float, float], body: np.ndarray) -> np.ndarray:
    """A body-frame covariance in the world: ``R C R^T``."""
    r = np.array([rotate(q, e) for e in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))]).T
    world: np.ndarray = r @ body @ r.T
    return world


def _covariance(block: np.ndarray) -> tuple[float, ...] | None:
    """A 3x3 covariance row-major, None when unknown (all zero) or not finite."""
    if not block.any() or not np.all(np.isfinite(block)):
        return None
    return tuple(float(v) for v in block.ravel())


def scene_text(raw: bytes) -> str:
    text = deserialize(raw, STRING).data
    if not text.strip():
        raise BadSample("empty", "an empty scene description")
    return str(text)


def detections(raw: bytes, spec: DetectionsIn) -> tuple[Detection, ...]:
    """The detections of a sample on the detections topic, each as its phrase (label)
    with its score (confidence)."""
    if spec.type == DETECTIONS:
        found = _from_array(deserialize(raw, DETECTIONS), spec)
    else:
        found = _from_json(deserialize(raw, STRING).data, spec)
    return tuple(found[:MAX_DETECTIONS])


def _from_array(array: Any, spec: DetectionsIn) -> list[Detection]:
    out = []
    for det in array.detections:
        if not det.results:
            continue
        best = max(det.results, key=lambda r: r.hypothesis.score)
        class_id, score = str(best.hypothesis.class_id), float(best.hypothesis.score)
        if not math.isfinite(score):
            raise BadSample("non_finite", f"class {class_id!r}: its score is not finite")
        phrase = spec.classes.get(class_id)
        if phrase is None:
            raise BadSample("unknown_class", f"class id {class_id!r} is not in the config's "
                                             "classes")
        if score >= spec.min_score:
            out.append(Detection(label=phrase, confidence=min(max(score, 0.0), 1.0)))
    return out


def _from_json(text: str, spec: DetectionsIn) -> list[Detection]:
    """``["a red box", ...]`` or ``[{"label": ..., "confidence": ..., "where": ...}]``."""
    try:
        items = json.loads(text)
    except ValueError:
        raise BadSample("json", "the detections string is not JSON") from None
    if not isinstance(items, list):
        raise BadSample("json", "the detections JSON is not a list")
    out = []
    for item in items:
        fields = {"label": item} if isinstance(item, str) else item
        if not isinstance(fields, dict) or not isinstance(fields.get("label"), str):
            raise BadSample("json", "each detection is a string or has a string label")
        label = spec.classes.get(fields["label"], fields["label"]) if spec.classes \
            else fields["label"]
        if spec.classes and fields["label"] not in spec.classes:
            raise BadSample("unknown_class", f"label {fields['label']!r} is not in the "
                                             "config's classes")
        try:
            detection = Detection(label=label, confidence=fields.get("confidence"),
                                  where=fields.get("where"))
        except ValueError:
            raise BadSample("json", f"detection {label!r}: a bad confidence or where") from None
        if detection.confidence is None or detection.confidence >= spec.min_score:
            out.append(detection)
    return out


class Frames:
    """Pairs a camera frame's scene text with its detections, which travel on two topics
    and may arrive in either order (Zenoh runs each subscriber's callbacks on its own).

    A frame is complete when the second of its two halves arrives: :meth:`text` and
    :meth:`found` return what to publish (``(text, detections)``) or None while waiting
    for the other half. A half that is not followed by its other one before the next of
    its own kind goes out alone (a lost sample); detections go out at once, text ``None``,
    while no scene text has come for ``within_s`` (a captioner that is off or absent)."""

    def __init__(self, within_s: float) -> None:
        self.within_s = within_s
        self._text: str | None = None
        self._found: tuple[Detection, ...] | None = None
        self._text_at: float | None = None  # when the newest text came

    def text(self, text: str, now: float) -> list[tuple[str | None, tuple[Detection, ...]]]:
        self._text_at = now
        if self._found is not None:
            found, self._found = self._found, None
            return [(text, found)]
        out: list[tuple[str | None, tuple[Detection, ...]]] = []
        if self._text is not None:  # its detections never came
            out.append((self._text, ()))
        self._text = text
        return out

    def found(self, found: tuple[Detection, ...], now: float
              ) -> list[tuple[str | None, tuple[Detection, ...]]]:
        if self._text is not None:
            text, self._text = self._text, None
            return [(text, found)]
        if self._text_at is None or now - self._text_at > self.within_s:
            return [(None, found)]
        out: list[tuple[str | None, tuple[Detection, ...]]] = []
        if self._found is not None:  # its text never came
            out.append((None, self._found))
        self._found = found
        return out


def observation(*, robot: str, seq: int, text: str | None,
                found: Sequence[Detection], task: str) -> Observation:
    """The observation of one camera frame: the scene's text, or the detections' phrases
    one per line when there is none."""
    if text is None:
        text = "\n".join(d.phrase for d in found)
    if not text.strip():
        raise BadSample("empty", "no scene text and no detection")
    return Observation(robot=robot, seq=seq, task=task, text=text, detections=tuple(found))


# --------------------------------------------------------------------------- out


def setpoint(sp: VehicleSetpoint, ros_type: str, frame_id: str,
             body: tuple[float, float, float, float] | None = None) -> bytes:
    """A set-point as ``AccelStamped`` (its acceleration; a thrust/torque one has none:
    :class:`BadSample` ``unsupported``) or ``TwistStamped`` (the plan's velocity), stamped
    ``sp.t`` on the vehicle's clock; in the world frame, or with ``body`` (the vehicle's
    attitude) in its body frame (a ground robot's base takes ``cmd_vel`` there)."""
    types = typestore().types
    if ros_type == ACCEL:
        if sp.acceleration is None:
            raise BadSample("unsupported", "an AccelStamped set-point needs the point-mass "
                                           "model (the scene commands thrust and torques)")
        value, field, inner = sp.acceleration, "accel", "geometry_msgs/msg/Accel"
    elif ros_type == TWIST:
        value, field, inner = sp.velocity, "twist", "geometry_msgs/msg/Twist"
    else:
        raise BadSample("unsupported", f"no set-point as {ros_type}")
    if body is not None:
        w, x, y, z = body
        value = rotate((w, -x, -y, -z), value)
    vector = types["geometry_msgs/msg/Vector3"]
    both = types[inner](linear=vector(*value), angular=vector(0.0, 0.0, 0.0))
    return serialize(types[ros_type](header=header(sp.t, frame_id), **{field: both}), ros_type)


def string(data: Mapping[str, Any]) -> bytes:
    """``std_msgs/msg/String`` holding ``data`` as one line of JSON."""
    text = json.dumps(data, separators=(",", ":"), sort_keys=True, default=str)
    return serialize(typestore().types[STRING](data=text), STRING)
