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

Each direction has its queues and its thread (:mod:`.lanes`), so neither can starve the
other. In: a Zenoh callback refuses what it can tell cheaply (another type or hash, over
the topic's ``max_bytes``: before the payload is copied, no attachment, CDR whose layout
is wrong: :func:`.convert.check_cdr`) and queues the rest on its topic's queue, bounded in
samples and bytes, the oldest dropped past either; the inbound thread takes the topics'
queues in turn, so a flood on one topic waits behind the others' samples. Out: the
set-points have a queue of their own that the outbound thread empties before the stack's
other messages. A sample that cannot be used (those, a NaN, a pose in another frame, an
unknown class id, the oldest of a full queue) is dropped, counted in
``aesop_ros2_dropped_total{topic,reason}`` and logged once per topic and reason; it never
stops the bridge.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import zenoh
from prometheus_client import CollectorRegistry, Counter, Gauge

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
from .config import BridgeConfig, DetectionsIn, Input, Mapped, OdometryIn
from .lanes import Lanes, Limit

log = logging.getLogger(__name__)

SERVICE = "ros2"
# each ROS topic's queue: so many samples and bytes (4 MiB: at least 8 of the largest a
# topic may take), so all of them together hold at most 12 MiB however large the samples
IN_ITEMS, IN_BYTES = 64, 4 * 1024 * 1024
SETPOINTS_KEPT = 32  # set-points waiting to go out (1.6 s at 20 Hz), the oldest dropped past it
OUT_ITEMS = 64  # the stack's other messages waiting to go out, per queue
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
                                     "one of the bridge's queues was full", registry=registry)
        self.queued = Gauge("aesop_ros2_queued", "Items in each of the bridge's queues",
                            ["queue"], registry=registry)
        self.queued_bytes = Gauge("aesop_ros2_queued_bytes", "Bytes of ROS samples in each "
                                  "inbound queue of the bridge", ["queue"], registry=registry)


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
        self._max_bytes = {role: m.settings.max_bytes for role, m in self.mapped.items()
                           if isinstance(m.settings, Input)}
        # in: a queue per ROS topic, taken in turn; out: the set-points first, then the
        # stack's other messages (in order: a request before its decision), then alarms
        self._in = Lanes({role: Limit(IN_ITEMS, min(IN_BYTES, IN_ITEMS * limit))
                          for role, limit in self._max_bytes.items()}, in_turn=True)
        self._out = Lanes({"setpoint": Limit(SETPOINTS_KEPT), "stack": Limit(OUT_ITEMS),
                           "alarms": Limit(OUT_ITEMS)}, in_turn=False)
        self._stopping = threading.Event()
        self._counting = threading.Lock()  # status and _logged: Zenoh's threads and ours
        # the counters' children, looked up once (a label lookup costs as much as a check)
        self._received = {role: metrics.received.labels(m.name)
                          for role, m in self.mapped.items()}
        self._dropped: dict[tuple[str, str], Any] = {}
        self._declared: list[Any] = []
        self._publishers: dict[str, tuple[zenoh.Publisher, bytes]] = {}
        self._sequence: dict[str, int] = {}
        self._logged: set[tuple[str, str]] = set()
        self._seq = {"state": 0, "observation": 0}
        self._frames = convert.Frames(config.inputs.scene_within_s)
        self._mode: tuple[str, float] | None = None  # last mode sent, when
        self._requests: deque[ReasonerRequest] = deque(maxlen=REQUESTS_KEPT)
        self._threads: list[threading.Thread] = []
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
        for lanes, direction in ((self._in, "in"), (self._out, "out")):
            for name in lanes.status():
                self.metrics.queued.labels(name).set_function(_reading(lanes, name, "items"))
                if direction == "in":
                    self.metrics.queued_bytes.labels(name).set_function(
                        _reading(lanes, name, "bytes"))
        self._follow_stack()
        self._threads = [threading.Thread(target=self._run, args=(lanes, work),
                                          name=f"ros2-bridge-{direction}", daemon=True)
                         for lanes, work, direction in ((self._in, self._inbound, "in"),
                                                        (self._out, self._outbound, "out"))]
        for thread in self._threads:
            thread.start()

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
        for lanes in (self._in, self._out):
            lanes.close()
        for thread in self._threads:
            thread.join(timeout=5.0)
        for declared in self._declared:
            declared.undeclare()
        for publisher, _ in self._publishers.values():
            publisher.undeclare()
        self._declared, self._publishers = [], {}

    # ------------------------------------------------------------------ Zenoh threads

    def _ros_sample(self, mapped: Mapped) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                self._take_ros(mapped.role, sample)
            except Exception as exc:  # a fault of ours must never break Zenoh's thread
                self._drop(mapped.role, "error", f"{type(exc).__name__}: {exc}", trace=True)
        return on_sample

    def _take_ros(self, role: str, sample: zenoh.Sample) -> None:
        """Refuse what can be told without decoding, cheapest first, else queue it."""
        self._count(role, "received")
        key = str(sample.key_expr)
        if key != self.keys[role]:
            return self._drop(role, "type", f"sample on {key}, expected the type and hash "
                                             f"of {self.keys[role]}")
        size, limit = len(sample.payload), self._max_bytes[role]
        if size > limit:  # before the payload is copied
            return self._drop(role, "size", f"{size} bytes, the topic's max_bytes is {limit}")
        attachment = sample.attachment
        if attachment is not None and len(attachment) > wire.MAX_ATTACHMENT_BYTES:
            return self._drop(role, "attachment", f"a {len(attachment)}-byte attachment: "
                                                   "neither rmw_zenoh form")
        try:
            wire.parse_attachment(None if attachment is None else attachment.to_bytes())
        except wire.WireError as exc:
            return self._drop(role, "attachment", str(exc))
        payload = sample.payload.to_bytes()
        try:
            convert.check_cdr(payload, self.mapped[role].ros_type)
        except convert.BadSample as exc:
            return self._drop(role, exc.reason, str(exc))
        self._queued(role, self._in.put(role, payload, len(payload)))

    def _stack(self, role: str) -> Callable[[Received[Any]], None]:
        lane = "setpoint" if role == "setpoint" else "alarms" if role == "alarms" else "stack"

        def on_message(got: Received[Any]) -> None:
            if role == "alarms" and got.message.severity not in ALARMS:
                return  # not sent: no need to queue it
            dropped = self._out.put(lane, (role, got.message))
            for old_role, _ in dropped:
                self._queued(old_role, [None])
        return on_message

    def _queued(self, role: str, dropped: list[Any]) -> None:
        """Count ``dropped``, the oldest of ``role``'s full queue."""
        if dropped:
            with self._counting:
                self.queue_dropped += len(dropped)
            self.metrics.queue_dropped.inc(len(dropped))
            self._drop(role, "queue", "its queue was full: the oldest dropped",
                       n=len(dropped))

    # ------------------------------------------------------------------ the bridge's threads

    def _run(self, lanes: Lanes, work: Callable[[str, Any], None]) -> None:
        while not self._stopping.is_set():
            taken = lanes.take(0.5)
            if taken is None or self._stopping.is_set():
                continue
            name, item = taken
            role = item[0] if lanes is self._out else name
            try:
                work(role, item)
            except convert.BadSample as exc:
                self._drop(role, exc.reason, str(exc))
            except Exception as exc:  # a fault of ours must not stop the bridge
                self._drop(role, "error", f"{type(exc).__name__}: {exc}", trace=True)

    def _inbound(self, role: str, payload: bytes) -> None:
        settings = self.mapped[role].settings
        if isinstance(settings, OdometryIn):
            self._seq["state"] += 1
            state = convert.vehicle_state(payload, robot=self.robot,
                                          seq=self._seq["state"], frame_id=settings.frame_id,
                                          frame=settings.frame)
            self._attitude = state.attitude
            self._publish_stack(role, topics.vehicle_state(self.robot), state)
        elif role == "scene":
            text = convert.scene_text(payload)
            frames = [(text, ())] if self.config.inputs.detections is None \
                else self._frames.text(text, time.monotonic())
            for text_of, found in frames:
                self._observe(role, text_of, found)
        elif isinstance(settings, DetectionsIn):
            detected = convert.detections(payload, settings)
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
        self._count(role, "published")
        self.metrics.published.labels(self.mapped[role].name).inc()

    def _outbound(self, role: str, item: tuple[str, Message]) -> None:
        message, outputs = item[1], self.config.outputs
        if role == "setpoint" and outputs.setpoint is not None:
            assert isinstance(message, VehicleSetpoint)
            body = None
            if outputs.setpoint.body:
                if self._attitude is None:
                    raise convert.BadSample("unsupported", "no odometry yet: no attitude to "
                                                           "turn the set-point into the body")
                body = self._attitude
            self._send("setpoint", convert.setpoint(message, outputs.setpoint.type,
                                                    outputs.setpoint.frame_id, body))
        elif role == "mode":
            assert isinstance(message, ControlState)
            self._send_mode(message)
        elif role == "request":
            assert isinstance(message, ReasonerRequest)
            self._requests.append(message)
        elif role == "decision":
            assert isinstance(message, ReasonerDecision)
            self._send("decision", convert.string(self._decision(message)))
        elif role == "alarms":
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
        self._count(role, "published")
        self.metrics.published.labels(self.mapped[role].name).inc()

    def _count(self, role: str, what: str) -> None:
        with self._counting:
            status = self.status[role]
            setattr(status, what, getattr(status, what) + 1)
        if what == "received":
            self._received[role].inc()

    def topics(self) -> list[TopicStatus]:
        """Each mapped topic's counts (``GET /v1/bridge``), copied as they stand: Zenoh's
        threads count on while they are read."""
        with self._counting:
            return [replace(s, dropped=dict(s.dropped)) for s in self.status.values()]

    def queues(self) -> list[dict[str, Any]]:
        """Each queue's state (``GET /v1/bridge``): its items and bytes, their limits, the
        most bytes it has held, how many it dropped."""
        return [{"name": name, "direction": direction, **lane}
                for lanes, direction in ((self._in, "in"), (self._out, "out"))
                for name, lane in lanes.status().items()]

    def _drop(self, role: str, reason: str, detail: str, *, n: int = 1,
              trace: bool = False) -> None:
        """Count ``n`` samples of ``role`` dropped for ``reason``; the first of each topic
        and reason is logged and said as an event. Any thread, Zenoh's included."""
        status = self.status.get(role)
        name = self.mapped[role].name if role in self.mapped else role
        with self._counting:
            if status is not None:
                status.dropped[reason] = status.dropped.get(reason, 0) + n
            first = (role, reason) not in self._logged  # once per topic and reason
            self._logged.add((role, reason))
        counter = self._dropped.get((name, reason))
        if counter is None:
            counter = self._dropped[(name, reason)] = self.metrics.dropped.labels(name, reason)
        counter.inc(n)
        if first:
            log.warning("ros2 bridge: dropped a sample on %s (%s); further ones for this "
                        "reason are only counted", name, detail, exc_info=trace)
            self.bus.publish(topics.event(self.robot, SERVICE), Event(
                robot=self.robot, source=SERVICE, kind="ros2_dropped", severity="warning",
                message=f"dropped a sample on {name} ({detail}); further ones are counted "
                        "on the bridge's /metrics", data={"topic": name, "reason": reason}))


def _reading(lanes: Lanes, name: str, what: str) -> Callable[[], float]:
    """A gauge's reading of lane ``name``'s ``what`` (items, bytes) when scraped."""
    return lambda: float(lanes.status()[name][what])
