"""The dashboard's picture of one flight, aggregated from the bus stream. Pure: no I/O, no clock.

``FlightModel.apply`` takes one :class:`~.feed.Update`, folds it into bounded
histories and returns the item to stream to pages: ``{"kind", "topic",
"received", "message"}`` (plus ``"label"``, the chosen option's label, on a
decision). ``snapshot`` is everything a page needs to draw at once: the
latest state, the flown trail, the plan tree, the recovery regions and goal,
the score timeline, requests, decisions, events, and which services are alive.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel

from .feed import Update

Json = dict[str, Any]


@dataclass(frozen=True)
class Limits:
    trail: int = 3000  # states kept for the flown path
    scores: int = 600  # verdicts kept for the score timeline
    log: int = 50  # requests, decisions and events kept, each
    proposals: int = 50  # the detector cache's proposals (the newest state of each)


class Snapshot(BaseModel):
    """``GET /v1/snapshot`` (and the first item on ``/ws``): the flight so far. The
    messages are as they arrived on the bus (``shared.messages``, as JSON)."""

    robot: str
    state: Json | None  # the newest ControlState
    trail: list[list[Any]]  # [t, x, y, z, mode] of the flown path
    plan: Json | None  # the newest PlanSnapshot
    regions: list[Json]  # RegionBox of the newest Regions
    goal: list[float] | None  # m
    verdict: Json | None  # the newest AnomalyVerdict
    scores: list[Json]  # {seq, stamp, score, threshold, is_anomaly} for the timeline
    requests: list[Json]  # ReasonerRequests, newest last
    decisions: list[Json]
    events: list[Json]
    # the detector cache's proposals (scenes the LLM answered "continue" for), from the
    # embedding service's proposal_* events: the newest data of each, oldest first
    proposals: list[Json]
    # the detector's drift (services/embedding/detector/drift.py): the newest ``drift`` event's
    # message, data and stamp while the robot drifts; None once ``drift_cleared`` came
    drift: Json | None = None
    services: dict[str, bool]  # liveliness by service
    review_token: bool = False  # a batch review needs the admin token (one is configured)
    counts: dict[str, int]  # updates received by kind


class FlightModel:
    """Bounded histories of one robot's flight (``deque(maxlen)`` everywhere)."""

    def __init__(self, robot: str, limits: Limits = Limits()) -> None:
        self.robot = robot
        self.state: Json | None = None
        self.plan: Json | None = None
        self.verdict: Json | None = None
        self.regions: list[Json] = []
        self.goal: list[float] | None = None  # m, with the regions (``Regions``)
        self.trail: deque[list[Any]] = deque(maxlen=limits.trail)  # [t, x, y, z, mode]
        self.scores: deque[Json] = deque(maxlen=limits.scores)
        self.requests: deque[Json] = deque(maxlen=limits.log)
        self.decisions: deque[Json] = deque(maxlen=limits.log)
        self.events: deque[Json] = deque(maxlen=limits.log)
        self.proposals: dict[str, Json] = {}
        self._max_proposals = limits.proposals
        self.drift: Json | None = None
        self.services: dict[str, bool] = {}
        self.counts: Counter[str] = Counter()
        self._apply: dict[str, Callable[[Json], Json]] = {
            "state": self._state, "plan": self._plan, "anomaly": self._anomaly,
            "request": self._request, "decision": self._decision, "event": self._event,
            "health": self._health, "regions": self._regions,
        }

    def apply(self, update: Update) -> Json:
        """Fold ``update`` in; the item to stream. ``KeyError`` for an unknown kind."""
        extra = self._apply[update.kind](update.message)
        self.counts[update.kind] += 1
        return {"kind": update.kind, "topic": update.topic, "received": update.received,
                "message": update.message, **extra}

    def snapshot(self) -> Json:
        return {
            "robot": self.robot, "state": self.state, "trail": list(self.trail),
            "plan": self.plan, "regions": self.regions, "goal": self.goal,
            "verdict": self.verdict, "scores": list(self.scores),
            "requests": list(self.requests), "decisions": list(self.decisions),
            "events": list(self.events), "proposals": list(self.proposals.values()),
            "drift": self.drift,
            "services": dict(sorted(self.services.items())),
            "counts": dict(self.counts),
        }

    def _state(self, m: Json) -> Json:
        if self.trail and m["t"] is not None and m["t"] < self.trail[-1][0]:
            self.trail.clear()  # time went back: the flight was restarted
        point = [m["t"], *m["x"][:3]]
        if None not in point:  # a NaN came through the JSON encoder as null: not drawable
            self.trail.append([*point, m["mode"]])
        self.state = m
        return {}

    def _plan(self, m: Json) -> Json:
        self.plan = m
        return {}

    def _anomaly(self, m: Json) -> Json:
        self.verdict = m
        self.scores.append({k: m[k] for k in ("seq", "stamp", "score", "threshold",
                                              "is_anomaly")})
        return {}

    def _request(self, m: Json) -> Json:
        self.requests.append(m)
        for decision in self.decisions:  # one that overtook its request on the bus
            if decision["request_id"] == m["request_id"] and decision["label"] is None:
                decision["label"] = self.label_of(m["request_id"], decision["choice"])
        return {}

    def _decision(self, m: Json) -> Json:
        extra = {"label": self.label_of(m["request_id"], m["choice"])}
        self.decisions.append({**m, **extra})
        return extra

    def _event(self, m: Json) -> Json:
        self.events.append(m)
        if m.get("source") == "embedding" and m.get("kind") in ("drift", "drift_cleared"):
            self.drift = None if m["kind"] == "drift_cleared" else {
                "message": m.get("message", ""), "data": m.get("data", {}), "stamp": m["stamp"]}
        if m.get("source") == "embedding" and m.get("kind", "").startswith("proposal_") \
                and isinstance(m.get("data", {}).get("id"), str):
            ident = m["data"]["id"]
            self.proposals.pop(ident, None)  # the newest last
            self.proposals[ident] = {**m["data"], "stamp": m["stamp"]}
            while len(self.proposals) > self._max_proposals:
                del self.proposals[next(iter(self.proposals))]
        return {}

    def _health(self, m: Json) -> Json:
        self.services[m["service"]] = bool(m["alive"])
        return {}

    def _regions(self, m: Json) -> Json:
        self.regions, self.goal = m["regions"], m["goal"]
        return {}

    def label_of(self, request_id: str, choice: int) -> str | None:
        """The label of option ``choice`` in request ``request_id``, if it is still kept."""
        for request in reversed(self.requests):
            if request["request_id"] == request_id:
                return next((o["label"] for o in request["options"]
                             if o["index"] == choice), None)
        return None
