"""The dashboard's pure parts: the flight model, the regions answer, the fan-out hub."""

from __future__ import annotations

import asyncio
import json

import pytest

from services.dashboard.feed import Update
from services.dashboard.hub import ClientQueue, Hub
from services.dashboard.model import FlightModel, Limits
from shared import topics
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

ROBOT = "r1"
REGION = {"index": 1, "name": "roof", "label": "rooftop", "kind": "landing",
          "position_lo": [2.0, -0.5, 1.0], "position_hi": [4.0, 1.5, 1.2]}


def update(kind: str, message: Message, received: float = 100.0) -> Update:
    if kind == "event":
        key = topics.event(ROBOT, str(getattr(message, "source", "control")))
    else:
        key = {"state": topics.state, "plan": topics.plan, "anomaly": topics.anomaly,
               "request": topics.reasoner_request, "decision": topics.reasoner_decision,
               "regions": topics.regions}[kind](ROBOT)
    return Update(kind, key, message.model_dump(mode="json"), received)


def state(t: float, x: float = 0.0, mode: str = "nominal") -> Update:
    return update("state", ControlState(robot=ROBOT, t=t, x=(x, 1.0, 2.0) + (0.0,) * 9,
                                        u=(0.0,) * 4, mode=mode))


def verdict(seq: int, score: float, flagged: bool) -> Update:
    return update("anomaly", AnomalyVerdict(
        robot=ROBOT, seq=seq, score=score, threshold=-0.7, is_anomaly=flagged, k=5,
        model="m", cache="c", cache_version=1, latency_ms=1.0))


def request(request_id: str = "q1") -> Update:
    return update("request", ReasonerRequest(
        robot=ROBOT, request_id=request_id, deadline_s=1.5,
        observation=Observation(robot=ROBOT, seq=0, text="smoke"),
        options=(Option(index=0, label="continue"), Option(index=1, label="rooftop"))))


def decision(request_id: str = "q1", choice: int = 1) -> Update:
    return update("decision", ReasonerDecision(robot=ROBOT, request_id=request_id,
                                               choice=choice, source="timeout",
                                               latency_ms=1500.0))


def health(service: str, alive: bool) -> Update:
    return Update("health", topics.health(service), {"service": service, "alive": alive}, 1.0)


def test_an_item_is_the_message_with_its_kind_topic_and_arrival() -> None:
    model = FlightModel(ROBOT)
    item = model.apply(state(0.5, x=3.0))
    assert item["kind"] == "state" and item["topic"] == "aesop/r1/state"
    assert item["received"] == 100.0 and item["message"]["x"][0] == 3.0
    assert json.loads(json.dumps(item)) == item


def test_the_trail_is_bounded_and_restarts_with_the_flight() -> None:
    model = FlightModel(ROBOT, Limits(trail=10))
    for i in range(25):
        model.apply(state(i / 10, x=float(i)))
    trail = model.snapshot()["trail"]
    assert len(trail) == 10 and trail[-1] == [2.4, 24.0, 1.0, 2.0, "nominal"]
    model.apply(state(0.0, x=-1.0, mode="nominal"))  # POST /v1/reset on the control service
    assert model.snapshot()["trail"] == [[0.0, -1.0, 1.0, 2.0, "nominal"]]
    assert model.snapshot()["state"]["x"][0] == -1.0


def test_scores_keep_what_the_timeline_draws_and_are_bounded() -> None:
    model = FlightModel(ROBOT, Limits(scores=10))
    for seq in range(30):
        model.apply(verdict(seq, -0.5 if seq % 3 == 0 else -0.9, seq % 3 == 0))
    snap = model.snapshot()
    assert [s["seq"] for s in snap["scores"]] == list(range(20, 30))
    assert set(snap["scores"][0]) == {"seq", "stamp", "score", "threshold", "is_anomaly"}
    assert snap["scores"][1]["is_anomaly"] is True and snap["scores"][1]["score"] == -0.5
    assert snap["verdict"]["seq"] == 29 and snap["verdict"]["model"] == "m"


def test_a_decision_carries_the_label_of_the_option_it_chose() -> None:
    model = FlightModel(ROBOT)
    model.apply(request("q1"))
    item = model.apply(decision("q1", 1))
    assert item["label"] == "rooftop" and item["message"]["source"] == "timeout"
    assert model.snapshot()["decisions"][-1]["label"] == "rooftop"
    assert model.apply(decision("unknown", 1))["label"] is None
    assert model.apply(decision("q1", 7))["label"] is None


def test_a_decision_that_overtook_its_request_gets_its_label_when_the_request_comes() -> None:
    model = FlightModel(ROBOT)
    assert model.apply(decision("q2", 1))["label"] is None  # separate keys: no order between
    model.apply(request("q2"))
    assert model.snapshot()["decisions"][-1]["label"] == "rooftop"


def test_requests_decisions_and_events_keep_the_latest() -> None:
    model = FlightModel(ROBOT, Limits(log=3))
    for i in range(5):
        model.apply(request(f"q{i}"))
        model.apply(update("event", Event(robot=ROBOT, source="control", kind=f"e{i}")))
    snap = model.snapshot()
    assert [r["request_id"] for r in snap["requests"]] == ["q2", "q3", "q4"]
    assert [e["kind"] for e in snap["events"]] == ["e2", "e3", "e4"]
    assert snap["counts"] == {"request": 5, "event": 5}


def proposal(ident: str, what: str, count: int = 1, source: str = "embedding") -> Update:
    return update("event", Event(robot=ROBOT, source=source, kind=f"proposal_{what}", data={
        "cache": "scene", "id": ident, "state": "pending" if what == "proposed" else what,
        "count": count, "text": f"scene {ident}", "model": "llm"}))


def test_proposals_keep_the_newest_state_of_each_and_are_bounded() -> None:
    model = FlightModel(ROBOT, Limits(proposals=2))
    model.apply(proposal("a", "proposed"))
    model.apply(proposal("b", "proposed"))
    model.apply(proposal("a", "proposed", count=2))
    model.apply(proposal("a", "accepted", count=2))
    model.apply(proposal("x", "accepted", source="robot"))  # not the detector's: ignored
    assert [(p["id"], p["state"], p["count"]) for p in model.snapshot()["proposals"]] == [
        ("b", "pending", 1), ("a", "accepted", 2)]
    model.apply(proposal("c", "proposed"))
    assert [p["id"] for p in model.snapshot()["proposals"]] == ["a", "c"]


def test_plan_and_services() -> None:
    model = FlightModel(ROBOT)
    plan = PlanSnapshot(robot=ROBOT, t=1.0, nominal=((0.0, 0.0, 1.0), (0.1, 0.0, 1.0)),
                        recovery={2: ((0.0, 0.0, 1.0),)}, consensus_steps=1, solve_ms=3.0,
                        status="solved")
    model.apply(update("plan", plan))
    model.apply(health("control", True))
    model.apply(health("reasoner", True))
    model.apply(health("reasoner", False))
    snap = model.snapshot()
    assert snap["plan"]["recovery"] == {"2": [[0.0, 0.0, 1.0]]}  # JSON object keys
    assert snap["services"] == {"control": True, "reasoner": False}


def test_unknown_kinds_are_refused() -> None:
    with pytest.raises(KeyError):
        FlightModel(ROBOT).apply(Update("telemetry", "aesop/r1/x", {}, 0.0))


def test_regions_and_goal_from_the_control_service() -> None:
    model = FlightModel(ROBOT)
    assert model.snapshot()["regions"] == [] and model.snapshot()["goal"] is None
    model.apply(update("regions", Regions(robot=ROBOT, regions=(RegionBox(**REGION),),
                                          goal=(0.0, 2.0, 1.5))))
    assert model.snapshot()["regions"] == [REGION]
    assert model.snapshot()["goal"] == [0.0, 2.0, 1.5]
    model.apply(update("regions", Regions(robot=ROBOT, regions=(), goal=(1.0, 2.0, 3.0))))
    assert model.snapshot()["regions"] == [] and model.snapshot()["goal"] == [1.0, 2.0, 3.0]


@pytest.mark.parametrize("change", [
    {"position_lo": [0, 0]}, {"position_hi": [0, 0, "high"]}, {"index": 0},
    {"kind": "orbit"}, {"extra": 1},
])
def test_a_malformed_region_is_refused_on_the_bus(change: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        Regions.model_validate({"regions": [{**REGION, **change}], "goal": [0, 0, 0]})


async def test_a_slow_client_loses_its_oldest_items_and_blocks_nobody() -> None:
    hub = Hub(maxsize=3)
    slow, fast = hub.connect(), hub.connect()
    got: list[str] = []

    async def read_fast() -> None:
        while (item := await fast.get()) is not None:
            got.append(item)

    reader = asyncio.create_task(read_fast())
    for i in range(10):
        hub.publish(str(i))
        await asyncio.sleep(0)
    assert got == [str(i) for i in range(10)]
    assert [await slow.get() for _ in range(3)] == ["7", "8", "9"]
    assert slow.dropped == 7 and hub.dropped == 7
    hub.disconnect(slow)
    assert hub.dropped == 7 and slow not in hub.clients
    hub.close()
    await asyncio.wait_for(reader, 5)
    assert hub.clients == set()


async def test_a_closed_queue_ends_a_waiting_reader() -> None:
    queue = ClientQueue(2)
    waiting = asyncio.create_task(queue.get())
    await asyncio.sleep(0)
    queue.close()
    assert await asyncio.wait_for(waiting, 5) is None
    queue.put("late")
    assert len(queue) == 0
    with pytest.raises(ValueError):
        ClientQueue(0)


def test_a_state_with_a_non_finite_position_is_kept_but_not_drawn() -> None:
    model = FlightModel(ROBOT)
    model.apply(state(0.1, x=1.0))
    bad = Update("state", "aesop/r1/state", {"t": 0.2, "x": [None, 1.0, 2.0] + [0.0] * 9,
                                             "u": [0.0] * 4, "mode": "nominal"}, 1.0)
    model.apply(bad)
    assert len(model.snapshot()["trail"]) == 1 and model.snapshot()["state"]["t"] == 0.2


def test_an_events_source_is_the_key_it_came_on_not_what_it_claims() -> None:
    """Issue 26, finding 5: a robot could put on the key embedding publishes on and claim
    to be the detector: the dashboard listed its forged proposal. Each publisher has a key
    of its own now (``aesop/{robot}/event/{source}``, only that user may put it), and the
    key says who sent the event."""
    from services.dashboard.feed import message_update
    from shared.bus import Received

    forged = Event(robot=ROBOT, source="embedding", kind="proposal_proposed", data={
        "cache": "scene", "id": "f", "state": "pending", "count": 1, "text": "benign",
        "model": "llm"})
    got = message_update("event", Received(topics.event(ROBOT, "robot"), forged, 0.0), 1.0)
    assert got.message["source"] == "robot"
    model = FlightModel(ROBOT)
    model.apply(got)
    assert model.snapshot()["proposals"] == []
    real = message_update("event", Received(topics.event(ROBOT, "embedding"), forged, 0.0), 1.0)
    model.apply(real)
    assert [p["id"] for p in model.snapshot()["proposals"]] == ["f"]
