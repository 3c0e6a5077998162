"""The bridge on the bus: ROS 2 topics carried by rmw_zenoh <-> the stack's keys.

One Zenoh session (the ``ros2`` user's) does both sides. On the ROS side it subscribes
to every data key of each input topic (``<domain>/<topic>/*/*``, so a sample of another
type or hash is seen and refused, not silently missed), declares a publisher on the
exact data key of each output topic and, as rmw_zenoh does, the liveliness tokens of its
node, its subscribers (``MS``) and publishers (``MP``), so ``ros2 node list`` and
``ros2 topic list -v`` show it. On the stack's side it publishes
``aesop/{robot}/vehicle/state`` and ``aesop/{robot}/observation`` and reads the set-point,
the control state (its mode), the reasoner's decisions and requests (their option
labels) and the events.

Zenoh callbacks only queue what arrived (a bounded drop-oldest queue); one thread
converts and publishes, in order. A sample that cannot be used (no attachment, another
type or hash, truncated CDR, a NaN, a pose in another frame, an unknown class id) is
dropped, counted in ``aesop_ros2_dropped_total{topic,reason}`` and logged once per
topic and reason; it never stops the bridge.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh
from prometheus_client import CollectorRegistry, Counter

from shared import topics
from shared.bus import Bus, Received
from shared.messages import (
    ControlState,
    Event,
    Message,
    Observation,
    ReasonerDecision,
    ReasonerRequest,
    VehicleSetpoint,
)

from . import convert, wire
from .config import BridgeConfig, DetectionsIn, Mapped, OdometryIn

log = logging.getLogger(__name__)

SERVICE = "ros2"
QUEUE = 1024  # samples waiting for the bridge's thread, the oldest dropped past it
MODE_EVERY_S = 1.0  # the mode is sent on each change and at least this often
ALARMS = ("warning", "alarm")  # the event severities sent on the alarms topic
REQUESTS_KEPT = 32  # reasoner requests remembered for their option labels


class BridgeMetrics:
    def __init__(self, registry: CollectorRegistry) -> None:
        self.received = Counter("aesop_ros2_received", "Samples received per ROS topic",
                                ["topic"], registry=registry)
        self.dropped = Counter("aesop_ros2_dropped", "Samples dropped per ROS topic and "
                               "reason", ["topic", "reason"], registry=registry)
        self.published = Counter("aesop_ros2_published", "Samples published per ROS topic",
                                 ["topic"], registry=registry)
        self.queue_dropped = Counter("aesop_ros2_queue_dropped", "Samples dropped because "
                                     "the bridge's queue was full", registry=registry)


@dataclass
class TopicStatus:
    """What ``GET /v1/bridge`` says of one mapped topic."""

    role: str
    direction: str
    topic: str
    type: str
    key: str
    received: int = 0
    published: int = 0
    dropped: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class _In:
    mapped: Mapped
    key: str
    payload: bytes
    attachment: bytes | None


@dataclass(frozen=True)
class _Out:
    role: str
    message: Message


class Bridge:
    """The bridge between ``config``'s topics and the stack, on ``bus``'s session."""

    def __init__(self, config: BridgeConfig, bus: Bus, metrics: BridgeMetrics) -> None:
        self.config, self.bus, self.metrics = config, bus, metrics
        self.robot = config.robot
        self.zid = str(bus.session.zid())
        self.node = wire.Node(config.domain_id, self.zid, config.node, config.namespace)
        self.mapped = {m.role: m for m in config.topics()}
        self.hashes = {m.role: convert.topic_hash(m) for m in self.mapped.values()}
        self.keys = {role: wire.data_key(config.domain_id, m.name, m.ros_type,
                                         self.hashes[role]) for role, m in self.mapped.items()}
        self.status = {role: TopicStatus(role, m.direction, m.name, m.ros_type, self.keys[role])
                       for role, m in self.mapped.items()}
        self._queue: deque[_In | _Out] = deque()
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._lock = threading.Lock()
        self._declared: list[Any] = []
        self._publishers: dict[str, tuple[zenoh.Publisher, bytes]] = {}
        self._sequence: dict[str, int] = {}
        self._logged: set[tuple[str, str]] = set()
        self._seq = {"state": 0, "observation": 0}
        self._frames = convert.Frames(config.inputs.scene_within_s)
        self._mode: tuple[str, float] | None = None  # last mode sent, when
        self._requests: deque[ReasonerRequest] = deque(maxlen=REQUESTS_KEPT)
        self._thread: threading.Thread | None = None
        self.queue_dropped = 0
        self._attitude: tuple[float, float, float, float] | None = None  # the newest odometry's

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        session = self.bus.session
        liveliness = session.liveliness()
        self._declared.append(liveliness.declare_token(self.node.token()))
        for role, mapped in self.mapped.items():
            kind = "MS" if mapped.direction == "in" else "MP"
            token = self.node.entity_token(mapped.entity_id, kind, mapped.name, mapped.ros_type,
                                           self.hashes[role],
                                           wire.qos_keyexpr(depth=mapped.settings.depth))
            self._declared.append(liveliness.declare_token(token))
            if mapped.direction == "in":
                self._declared.append(session.declare_subscriber(
                    wire.topic_keys(self.config.domain_id, mapped.name),
                    self._ros_sample(mapped)))
            else:
                self._publishers[role] = (session.declare_publisher(self.keys[role]),
                                          wire.gid(token))
        self._follow_stack()
        self._thread = threading.Thread(target=self._run, name="ros2-bridge", daemon=True)
        self._thread.start()

    def _follow_stack(self) -> None:
        robot, outputs = self.robot, self.config.outputs
        if outputs.setpoint is not None:
            self.bus.each(topics.vehicle_setpoint(robot), VehicleSetpoint,
                          self._stack("setpoint"))
        if outputs.mode is not None:
            self.bus.each(topics.state(robot), ControlState, self._stack("mode"))
        if outputs.decision is not None:
            self.bus.each(topics.reasoner_request(robot), ReasonerRequest,
                          self._stack("request"))
            self.bus.each(topics.reasoner_decision(robot), ReasonerDecision,
                          self._stack("decision"))
        if outputs.alarms is not None:
            self.bus.each(topics.events(robot), Event, self._stack("alarms"))

    def stop(self) -> None:
        self._stopping.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        for declared in self._declared:
            declared.undeclare()
        for publisher, _ in self._publishers.values():
            publisher.undeclare()
        self._declared, self._publishers = [], {}

    # ------------------------------------------------------------------ Zenoh threads

    def _ros_sample(self, mapped: Mapped) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            attachment = sample.attachment
            self._put(_In(mapped, str(sample.key_expr), sample.payload.to_bytes(),
                          None if attachment is None else attachment.to_bytes()))
        return on_sample

    def _stack(self, role: str) -> Callable[[Received[Any]], None]:
        return lambda got: self._put(_Out(role, got.message))

    def _put(self, item: _In | _Out) -> None:
        with self._lock:
            if len(self._queue) >= QUEUE:
                self._queue.popleft()
                self.queue_dropped += 1
                self.metrics.queue_dropped.inc()
            self._queue.append(item)
        self._wake.set()

    # ------------------------------------------------------------------ the bridge's thread

    def _run(self) -> None:
        while not self._stopping.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            while True:
                with self._lock:
                    item = self._queue.popleft() if self._queue else None
                if item is None or self._stopping.is_set():
                    break
                try:
                    if isinstance(item, _In):
                        self._inbound(item)
                    else:
                        self._outbound(item)
                except convert.BadSample as exc:
                    self._drop(_role(item), exc.reason, str(exc))
                except Exception as exc:  # a fault of ours must not stop the bridge
                    self._drop(_role(item), "error", f"{type(exc).__name__}: {exc}",
                               trace=True)

    def _inbound(self, item: _In) -> None:
        mapped, role = item.mapped, item.mapped.role
        status = self.status[role]
        status.received += 1
        self.metrics.received.labels(mapped.name).inc()
        if item.key != self.keys[role]:
            raise convert.BadSample("type", f"sample on {item.key}, expected the type and "
                                            f"hash of {self.keys[role]}")
        try:
            wire.parse_attachment(item.attachment)
        except wire.WireError as exc:
            raise convert.BadSample("attachment", str(exc)) from None
        settings = mapped.settings
        if isinstance(settings, OdometryIn):
            self._seq["state"] += 1
            state = convert.vehicle_state(item.payload, robot=self.robot,
                                          seq=self._seq["state"], frame_id=settings.frame_id,
                                          frame=settings.frame)
            self._attitude = state.attitude
            self._publish_stack(role, topics.vehicle_state(self.robot), state)
        elif role == "scene":
            text = convert.scene_text(item.payload)
            frames = [(text, ())] if self.config.inputs.detections is None \
                else self._frames.text(text, time.monotonic())
            for text_of, found in frames:
                self._observe(role, text_of, found)
        elif isinstance(settings, DetectionsIn):
            detected = convert.detections(item.payload, settings)
            for text_of, found in self._frames.found(detected, time.monotonic()):
                self._observe(role, text_of, found)

    def _observe(self, role: str, text: str | None, found: tuple[Any, ...]) -> None:
        self._seq["observation"] += 1
        obs: Observation = convert.observation(
            robot=self.robot, seq=self._seq["observation"], text=text, found=found,
            task=self.config.inputs.task)
        self._publish_stack(role, topics.observation(self.robot), obs)

    def _publish_stack(self, role: str, key: str, message: Message) -> None:
        self.bus.publish(key, message)
        self.status[role].published += 1
        self.metrics.published.labels(self.mapped[role].name).inc()

    def _outbound(self, item: _Out) -> None:
        message, outputs = item.message, self.config.outputs
        if item.role == "setpoint" and outputs.setpoint is not None:
            assert isinstance(message, VehicleSetpoint)
            body = None
            if outputs.setpoint.body:
                if self._attitude is None:
                    raise convert.BadSample("unsupported", "no odometry yet: no attitude to "
                                                           "turn the set-point into the body")
                body = self._attitude
            self._send("setpoint", convert.setpoint(message, outputs.setpoint.type,
                                                    outputs.setpoint.frame_id, body))
        elif item.role == "mode":
            assert isinstance(message, ControlState)
            self._send_mode(message)
        elif item.role == "request":
            assert isinstance(message, ReasonerRequest)
            self._requests.append(message)
        elif item.role == "decision":
            assert isinstance(message, ReasonerDecision)
            self._send("decision", convert.string(self._decision(message)))
        elif item.role == "alarms":
            assert isinstance(message, Event)
            if message.severity in ALARMS:
                self._send("alarms", convert.string(
                    {"robot": message.robot, "stamp": message.stamp, "source": message.source,
                     "kind": message.kind, "severity": message.severity,
                     "message": message.message, "data": message.data}))

    def _send_mode(self, state: ControlState) -> None:
        now = time.monotonic()
        if self._mode is not None and self._mode[0] == state.mode and \
                now - self._mode[1] < MODE_EVERY_S:
            return
        self._mode = (state.mode, now)
        self._send("mode", convert.string({
            "robot": state.robot, "mode": str(state.mode), "t": state.t,
            "t_anom": state.t_anom, "chosen": state.chosen}))

    def _decision(self, decision: ReasonerDecision) -> dict[str, Any]:
        request = next((r for r in self._requests if r.request_id == decision.request_id),
                       None)
        label = None if request is None else next(
            (o.label for o in request.options if o.index == decision.choice), None)
        return {"robot": decision.robot, "request_id": decision.request_id,
                "choice": decision.choice, "label": label, "source": decision.source,
                "rationale": decision.rationale, "latency_ms": decision.latency_ms,
                "model": decision.model}

    def _send(self, role: str, payload: bytes) -> None:
        """Put ``payload`` on ``role``'s data key with the attachment rmw_zenoh writes."""
        publisher, gid = self._publishers[role]
        self._sequence[role] = self._sequence.get(role, 0) + 1
        attachment = wire.Attachment(self._sequence[role], time.time_ns(), gid)
        publisher.put(payload, attachment=attachment.encode())
        self.status[role].published += 1
        self.metrics.published.labels(self.mapped[role].name).inc()

    def _drop(self, role: str, reason: str, detail: str, *, trace: bool = False) -> None:
        status = self.status.get(role)
        name = self.mapped[role].name if role in self.mapped else role
        if status is not None:
            status.dropped[reason] = status.dropped.get(reason, 0) + 1
        self.metrics.dropped.labels(name, reason).inc()
        if (role, reason) not in self._logged:  # once per topic and reason
            self._logged.add((role, reason))
            log.warning("ros2 bridge: dropped a sample on %s (%s); further ones for this "
                        "reason are only counted", name, detail, exc_info=trace)
            self.bus.publish(topics.event(self.robot, SERVICE), Event(
                robot=self.robot, source=SERVICE, kind="ros2_dropped", severity="warning",
                message=f"dropped a sample on {name} ({detail}); further ones are counted "
                        "on the bridge's /metrics", data={"topic": name, "reason": reason}))


def _role(item: _In | _Out) -> str:
    return item.mapped.role if isinstance(item, _In) else item.role
