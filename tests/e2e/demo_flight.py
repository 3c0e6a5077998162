"""A scripted demo flight for the dashboard tests, published as the services would.

The geometry is the paper's quadrotor simulation (start near (10, 2, 2) m, goal
(0, 2, 1.5) m, four landing pads). The flight goes nominal, the detector
flags an anomaly, the control loop asks the reasoner (K = 1.5 s), the reasoner
answers "rooftop" and the flight recovers toward it. The regions and the goal go out
every ten ticks, as the control service sends them every second.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from typing import Any

import httpx

from shared import topics
from shared.bus import Bus
from shared.messages import (
    AnomalyVerdict,
    ControlState,
    Event,
    Message,
    Observation,
    Option,
    PlanSnapshot,
    ReasonerDecision,
    ReasonerRequest,
    RegionBox,
    Regions,
)
from tests.zenoh_peers import wait_until

Point = tuple[float, float, float]

START: Point = (10.0, 2.0, 2.0)
GOAL: Point = (0.0, 2.0, 1.5)
REGIONS: list[dict[str, Any]] = [
    {"index": 1, "name": "grass-south", "label": "grassy field", "kind": "landing",
     "position_lo": [7.0, -0.5, 0.0], "position_hi": [9.0, 1.5, 0.2]},
    {"index": 2, "name": "grass-north", "label": "grassy field", "kind": "landing",
     "position_lo": [7.0, 2.5, 0.0], "position_hi": [9.0, 4.5, 0.2]},
    {"index": 3, "name": "rooftop", "label": "rooftop", "kind": "landing",
     "position_lo": [2.0, -0.5, 1.0], "position_hi": [4.0, 1.5, 1.2]},
    {"index": 4, "name": "parking-lot", "label": "parking lot", "kind": "landing",
     "position_lo": [2.0, 2.5, 0.0], "position_hi": [4.0, 4.5, 0.2]},
]
CHOICE = 3  # the rooftop
DT = 0.1  # s per tick
SPEED = 1.0  # m/s
HORIZON = 40  # plan steps (T = 4 s)
CONSENSUS = 15  # K in steps (1.5 s)
TICKS = 60
ANOMALY_AT, REQUEST_AT, DECISION_AT = 20, 21, 30
THRESHOLD = -0.70


def regions(robot: str) -> Regions:
    """What the control service says of its regions and goal (on start and every second)."""
    return Regions(robot=robot, regions=tuple(RegionBox(**r) for r in REGIONS), goal=GOAL)


def center(region: dict[str, Any]) -> Point:
    lo, hi = region["position_lo"], region["position_hi"]
    return ((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2)


def step_toward(p: Point, target: Point, step: float = SPEED * DT) -> Point:
    d = [t - a for a, t in zip(p, target, strict=True)]
    n = math.sqrt(sum(v * v for v in d))
    if n <= step:
        return target
    return (p[0] + d[0] * step / n, p[1] + d[1] * step / n, p[2] + d[2] * step / n)


def path(p: Point, target: Point, steps: int) -> list[Point]:
    out = [p]
    for _ in range(steps):
        out.append(step_toward(out[-1], target))
    return out


def plan_at(t: float, p: Point, recovering: bool) -> PlanSnapshot:
    target = center(REGIONS[CHOICE - 1])
    if recovering:  # committed: only the chosen branch is left
        return PlanSnapshot(t=t, nominal=(), recovery={CHOICE: tuple(path(p, target, HORIZON))},
                            consensus_steps=0, solve_ms=4.0, status="solved")
    prefix = path(p, GOAL, CONSENSUS)
    recovery = {r["index"]: tuple(prefix + path(prefix[-1], center(r), HORIZON - CONSENSUS)[1:])
                for r in REGIONS}
    return PlanSnapshot(t=t, nominal=tuple(path(p, GOAL, HORIZON)), recovery=recovery,
                        consensus_steps=CONSENSUS, solve_ms=6.5, status="solved")


def script(robot: str) -> Iterator[list[tuple[str, Message]]]:
    """The messages of each tick, made when the tick comes (so stamps are current)."""
    p = START
    request_id = "demo-request-0001"
    for tick in range(TICKS):
        t = round(tick * DT, 3)
        mode = ("nominal" if tick < REQUEST_AT else
                "anomaly_pending" if tick < DECISION_AT else "recovering")
        recovering = mode == "recovering"
        flagged = ANOMALY_AT <= tick < DECISION_AT
        out: list[tuple[str, Message]] = []
        if tick % 10 == 0:
            out.append((topics.regions(robot), regions(robot)))
        score = (-0.52 if flagged else -0.85) + 0.03 * math.sin(tick / 2)
        out.append((topics.anomaly(robot), AnomalyVerdict(
            robot=robot, seq=tick, score=score, threshold=THRESHOLD, is_anomaly=flagged, k=5,
            model="all-MiniLM-L6-v2", cache="scene", cache_version=1, latency_ms=14.0)))
        if tick == REQUEST_AT:
            out.append((topics.event(robot, "control"), Event(
                robot=robot, source="control", kind="mode_change", severity="warning",
                message="nominal -> anomaly_pending", data={"to": "anomaly_pending"})))
            out.append((topics.reasoner_request(robot), ReasonerRequest(
                robot=robot, request_id=request_id, deadline_s=1.5,
                observation=Observation(robot=robot, seq=tick, text="a person is lying on the "
                                        "landing pad at the goal"),
                options=(Option(index=0, label="continue"),
                         *(Option(index=r["index"], label=r["label"]) for r in REGIONS)))))
        if tick == DECISION_AT:
            out.append((topics.reasoner_decision(robot), ReasonerDecision(
                robot=robot, request_id=request_id, choice=CHOICE, source="llm",
                rationale="a person on the pad: land on the rooftop instead",
                latency_ms=870.0, model="fake-llm")))
            out.append((topics.event(robot, "control"), Event(
                robot=robot, source="control", kind="mode_change", severity="alarm",
                message="anomaly_pending -> recovering (y=3)", data={"to": "recovering"})))
        x = (*p, -SPEED, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        out.append((topics.state(robot), ControlState(
            robot=robot, t=t, x=x, u=(0.0, 0.0, 0.0, 0.0), mode=mode,
            t_anom=ANOMALY_AT * DT if tick >= ANOMALY_AT else None,
            chosen=CHOICE if recovering else None,
            active_regions=(CHOICE,) if recovering else (1, 2, 3, 4))))
        out.append((topics.plan(robot), plan_at(t, p, recovering)))
        yield out
        p = step_toward(p, center(REGIONS[CHOICE - 1]) if recovering else GOAL)


class Flight:
    """The script published over ``bus``, a stretch at a time."""

    def __init__(self, bus: Bus, robot: str) -> None:
        self.bus, self.robot = bus, robot
        self.tick = 0
        self._ticks = script(robot)

    def fly(self, until: int = TICKS, period_s: float = 0.04) -> None:
        """Publish the ticks before ``until``, one every ``period_s`` seconds."""
        while self.tick < until:
            for key, message in next(self._ticks):
                self.bus.publish(key, message)
            self.tick += 1
            time.sleep(period_s)


def fly(bus: Bus, robot: str, period_s: float = 0.04) -> None:
    """Publish the whole script."""
    Flight(bus, robot).fly(TICKS, period_s)


def wait_following(bus: Bus, robot: str, base_url: str) -> None:
    """Publish a greeting event until the dashboard at ``base_url`` has one."""
    key = topics.event(robot, "test")

    def seen() -> bool:
        bus.publish(key, Event(robot=robot, source="test", kind="hello",
                               message="the scripted demo flight"))
        snapshot = httpx.get(f"{base_url}/v1/snapshot", timeout=5).json()
        return snapshot["counts"].get("event", 0) > 0

    wait_until(seen, "the dashboard to follow the bus", 20.0)
