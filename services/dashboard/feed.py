"""The robot's bus traffic as one stream of :class:`Update`s (the Zenoh side of the dashboard).

Both the dashboard service and ``aesop watch`` follow the same seven topics of
one robot (or of every robot) plus the liveliness of every service; the dashboard's fleet
overview follows five of them for every robot. Each message arrives through
the shared bridge (``shared.bus``) and is handed on as a JSON-ready dict.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import zenoh

from shared import topics
from shared.bus import HEALTH_ALL, LivelinessWatch, Received, Subscription
from shared.messages import (
    AnomalyVerdict,
    ControlState,
    Event,
    Message,
    PlanSnapshot,
    ReasonerDecision,
    ReasonerRequest,
    Regions,
)

log = logging.getLogger(__name__)

# kind -> (key of the robot's topic, message type)
SOURCES: dict[str, tuple[Callable[[str], str], type[Message]]] = {
    "state": (topics.state, ControlState),
    "plan": (topics.plan, PlanSnapshot),
    "anomaly": (topics.anomaly, AnomalyVerdict),
    "request": (topics.reasoner_request, ReasonerRequest),
    "decision": (topics.reasoner_decision, ReasonerDecision),
    "event": (topics.events, Event),
    "regions": (topics.regions, Regions),
}


@dataclass(frozen=True, slots=True)
class Update:
    """One thing seen: ``kind`` (a key of ``SOURCES``, or ``health``), where it
    came from, the message as JSON-ready data, and the wall-clock time it arrived (s)."""

    kind: str
    topic: str
    message: dict[str, Any]
    received: float


Sink = Callable[[Update], None]


def message_update(kind: str, got: Received[Message], now: float) -> Update:
    """The message as JSON-ready data (through pydantic's JSON encoder: a NaN or infinity
    becomes null, never invalid JSON). An event's ``source`` is the key it came on, which
    only that source may put, whatever the event itself claims."""
    message = json.loads(got.message.model_dump_json())
    if kind == "event":
        message["source"] = topics.source_of(got.key)
    return Update(kind, got.key, message, now)


async def follow(session: zenoh.Session, robot: str, sink: Sink, *,
                 clock: Callable[[], float] = time.time, kinds: Sequence[str] | None = None,
                 health: bool = True) -> None:
    """Call ``sink`` with every update of ``robot`` (``*``: every robot's) until cancelled;
    ``kinds``: only these of :data:`SOURCES`; ``health``: the services' liveliness too.

    A sink that raises loses that one update (logged), not the stream.
    """
    subs = {kind: Subscription(session, key(robot), model, maxsize=256)
            for kind, (key, model) in SOURCES.items() if kinds is None or kind in kinds}
    alive = LivelinessWatch(session, HEALTH_ALL) if health else None
    guarded = _guard(sink)
    try:
        async with asyncio.TaskGroup() as group:
            for kind, sub in subs.items():
                group.create_task(_pump(kind, sub, guarded, clock))
            if alive is not None:
                group.create_task(_pump_health(alive, guarded, clock))
    finally:
        for sub in subs.values():
            sub.close()
        if alive is not None:
            alive.close()


async def _pump(kind: str, sub: Subscription[Any], sink: Sink,
                clock: Callable[[], float]) -> None:
    async for got in sub:
        sink(message_update(kind, got, clock()))


async def _pump_health(watch: LivelinessWatch, sink: Sink, clock: Callable[[], float]) -> None:
    """Health changes as updates; a token whose name is not a service name (anyone on the
    bus may declare one) is dropped, logged at most once per 10 s, and the feed goes on."""
    dropped, logged_at = 0, -math.inf
    async for change in watch:
        try:
            topic = topics.health(change.service)
        except ValueError as exc:
            dropped += 1
            if time.monotonic() - logged_at >= 10.0:
                log.warning("dropped %d liveliness change(s) with a bad name (latest: %s)",
                            dropped, exc)
                dropped, logged_at = 0, time.monotonic()
            continue
        sink(Update("health", topic, {"service": change.service, "alive": change.alive},
                    clock()))


def _guard(sink: Sink) -> Sink:
    def guarded(update: Update) -> None:
        try:
            sink(update)
        except Exception:  # one bad update must not end the stream
            log.exception("dropped a %s update from %s", update.kind, update.topic)

    return guarded
