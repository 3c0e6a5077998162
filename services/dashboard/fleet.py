"""The dashboard's fleet overview: one line per robot, folded from every robot's bus stream.
Pure: no I/O, no clock (each update carries when it arrived).

Per robot: its mode and clock, where it is, its newest verdict, the reasoner request it waits
on (with when it arrived, so a page counts down to K) until a decision answers it, its last
decision, and its alarms (alarm-severity events: how many, the newest). At most
``max_robots`` robots are kept; past it the one heard from least recently is forgotten.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel

from shared import topics

from .feed import Update

Json = dict[str, Any]

KINDS = ("state", "anomaly", "request", "decision", "event")  # what the overview follows


class RobotSummary(BaseModel):
    """One robot's line of ``GET /v1/fleet``."""

    robot: str
    seen: float  # when anything of it last arrived (s, the dashboard's wall clock)
    mode: str | None = None
    t: float | None = None  # the loop's clock (s)
    position: list[float | None] | None = None  # m
    verdict: Json | None = None  # {seq, is_anomaly, score, threshold, p_value, stamp}
    # the request it waits on: {request_id, deadline_s, received, options}; None once answered
    pending: Json | None = None
    decision: Json | None = None  # the newest: {request_id, choice, label, source, stamp}
    alarms: int = 0  # alarm-severity events so far
    last_alarm: Json | None = None  # {source, kind, message, stamp}


class FleetSnapshot(BaseModel):
    """``GET /v1/fleet``: every robot heard from, by id; ``robot``: the one the page draws."""

    robot: str
    robots: list[RobotSummary]


@dataclass
class _Robot:
    seen: float
    mode: str | None = None
    t: float | None = None
    position: list[float | None] | None = None
    verdict: Json | None = None
    pending: Json | None = None
    requests: OrderedDict[str, Json] = field(default_factory=OrderedDict)  # recent, by id
    decision: Json | None = None
    alarms: int = 0
    last_alarm: Json | None = None


class FleetModel:
    def __init__(self, max_robots: int = 256) -> None:
        self.max_robots = max_robots
        self._robots: OrderedDict[str, _Robot] = OrderedDict()

    def apply(self, update: Update) -> None:
        """Fold ``update`` (any robot's, a kind of :data:`KINDS`) in; others are ignored."""
        if update.kind not in KINDS:
            return
        try:
            robot = topics.robot_of(update.topic)
        except ValueError:
            return
        seen = self._robots.pop(robot, None) or _Robot(update.received)
        self._robots[robot] = seen  # heard from most recently: last
        while len(self._robots) > self.max_robots:
            self._robots.popitem(last=False)
        seen.seen = update.received
        m = update.message
        if update.kind == "state":
            seen.mode, seen.t, seen.position = m.get("mode"), m.get("t"), (m.get("x") or [])[:3]
        elif update.kind == "anomaly":
            seen.verdict = {k: m.get(k) for k in ("seq", "is_anomaly", "score", "threshold",
                                                   "p_value", "stamp")}
        elif update.kind == "request":
            request = {"request_id": m["request_id"], "deadline_s": m.get("deadline_s"),
                       "received": update.received, "options": m.get("options", [])}
            seen.requests[m["request_id"]] = request
            while len(seen.requests) > 8:
                seen.requests.popitem(last=False)
            if seen.decision is None or seen.decision["request_id"] != m["request_id"]:
                seen.pending = request
        elif update.kind == "decision":
            asked = seen.requests.get(m["request_id"], {})
            label = next((o.get("label") for o in asked.get("options", [])
                          if o.get("index") == m.get("choice")), None)
            seen.decision = {"request_id": m["request_id"], "choice": m.get("choice"),
                             "label": label, "source": m.get("source"), "stamp": m.get("stamp")}
            if seen.pending is not None and seen.pending["request_id"] == m["request_id"]:
                seen.pending = None
        elif m.get("severity") == "alarm":
            seen.alarms += 1
            seen.last_alarm = {k: m.get(k) for k in ("source", "kind", "message", "stamp")}

    def snapshot(self, robot: str) -> FleetSnapshot:
        return FleetSnapshot(robot=robot, robots=[
            RobotSummary(robot=name, seen=r.seen, mode=r.mode, t=r.t, position=r.position,
                         verdict=r.verdict, pending=r.pending, decision=r.decision,
                         alarms=r.alarms, last_alarm=r.last_alarm)
            for name, r in sorted(self._robots.items())])
