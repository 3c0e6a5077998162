"""The dashboard's fleet overview (services/dashboard/fleet.py): pure, arrival times given."""

from __future__ import annotations

from services.dashboard.feed import Update
from services.dashboard.fleet import FleetModel


def of(robot: str, kind: str, message: dict, received: float) -> Update:
    key = {"request": "reasoner/request", "decision": "reasoner/decision",
           "event": "event/control"}.get(kind, kind)
    return Update(kind, f"aesop/{robot}/{key}", message, received)


REQUEST = {"request_id": "q1", "deadline_s": 4.3,
           "options": [{"index": 0, "label": "continue"}, {"index": 2, "label": "blue box"}]}


def test_a_request_waits_until_its_decision_and_alarms_are_counted() -> None:
    fleet = FleetModel()
    fleet.apply(of("r1", "state", {"mode": "nominal", "t": 1.5, "x": [1.0, 2.0, 3.0] + [0.0] * 9},
                   10.0))
    fleet.apply(of("r1", "anomaly", {"seq": 7, "is_anomaly": True, "score": -0.2,
                                     "threshold": -0.5, "p_value": 0.01, "stamp": 9.9}, 10.1))
    fleet.apply(of("r1", "request", REQUEST, 10.2))
    fleet.apply(of("r2", "event", {"severity": "alarm", "source": "control",
                                   "kind": "state_stale", "message": "late", "stamp": 3.0}, 10.3))
    fleet.apply(of("r2", "event", {"severity": "info", "source": "control",
                                   "kind": "mode_change", "stamp": 3.1}, 10.4))
    snap = {r.robot: r for r in fleet.snapshot("r1").robots}
    assert list(snap) == ["r1", "r2"]
    assert snap["r1"].mode == "nominal" and snap["r1"].position == [1.0, 2.0, 3.0]
    assert snap["r1"].verdict is not None and snap["r1"].verdict["seq"] == 7
    assert snap["r1"].pending is not None and snap["r1"].pending["received"] == 10.2
    assert snap["r2"].alarms == 1 and snap["r2"].last_alarm is not None
    assert snap["r2"].last_alarm["kind"] == "state_stale" and snap["r2"].seen == 10.4
    fleet.apply(of("r1", "decision", {"request_id": "q1", "choice": 2, "source": "llm",
                                      "stamp": 11.0}, 11.0))
    r1 = fleet.snapshot("r1").robots[0]
    assert r1.pending is None and r1.decision is not None
    assert r1.decision["label"] == "blue box" and r1.decision["source"] == "llm"
    # a decision that overtook its request on the bus: the late request is not pending
    fleet.apply(of("r1", "decision", {"request_id": "q2", "choice": 0, "source": "timeout"},
                   12.0))
    fleet.apply(of("r1", "request", {**REQUEST, "request_id": "q2"}, 12.1))
    assert fleet.snapshot("r1").robots[0].pending is None


def test_robots_past_the_limit_forget_the_one_heard_from_least_recently() -> None:
    fleet = FleetModel(max_robots=2)
    for i, robot in enumerate(("a", "b", "a", "c")):
        fleet.apply(of(robot, "state", {"mode": "nominal", "t": 0.0, "x": [0.0] * 12},
                       float(i)))
    assert [r.robot for r in fleet.snapshot("a").robots] == ["a", "c"]
    fleet.apply(Update("health", "aesop/health/x", {"service": "x", "alive": True}, 9.0))
    fleet.apply(of("a", "plan", {}, 9.0))  # not followed
    assert [r.seen for r in fleet.snapshot("a").robots] == [2.0, 3.0]
