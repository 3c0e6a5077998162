"""What the bridge's routes answer (``/openapi.json``)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

from shared.messages import Int


class Answer(BaseModel):
    model_config = ConfigDict(extra="ignore")


class TopicAnswer(Answer):
    role: str  # odometry, scene, detections, setpoint, mode, decision, alarms
    direction: str  # in: ROS -> stack; out: stack -> ROS
    topic: str  # fully qualified
    type: str  # pkg/msg/Name
    key: str  # the Zenoh data key
    received: Int
    published: Int
    dropped: dict[str, Int]  # reason -> samples


class QueueAnswer(Answer):
    """One of the bridge's queues: in, one per ROS topic (taken in turn); out, the
    set-points (first), the stack's other messages, the alarms."""

    name: str  # in: the topic's role; out: setpoint, stack, alarms
    direction: str
    items: Int  # held now
    max_items: Int
    bytes: Int  # of ROS samples held now (in); 0 out, where items are bounded by count
    max_bytes: Int | None  # None: bounded by count alone
    peak_bytes: Int  # the most it has held
    dropped: Int  # the oldest, dropped when it was full


class BridgeAnswer(Answer):
    """``GET /v1/bridge``: who the bridge is in the ROS graph and what each topic did."""

    robot: str
    domain_id: Int
    node: str
    zid: str
    node_token: str
    topics: list[TopicAnswer]
    queue_dropped: Int  # all queues together
    queues: list[QueueAnswer]
