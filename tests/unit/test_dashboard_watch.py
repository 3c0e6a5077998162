"""``aesop watch``'s lines (services.dashboard.watch.Terminal): pure, clock passed in."""

from __future__ import annotations

from services.dashboard.feed import Update
from services.dashboard.watch import Terminal


def at(kind: str, message: dict, received: float) -> Update:
    return Update(kind, f"aesop/r1/{kind}", message, received)


def state(t: float, received: float, mode: str = "nominal", chosen: int | None = None) -> Update:
    x = [1.0, 2.0, 3.0, 0.3, 0.4, 0.0] + [0.0] * 6
    return at("state", {"t": t, "x": x, "u": [0.0] * 4, "mode": mode, "chosen": chosen},
              received)


def verdict(seq: int, flagged: bool, threshold: float | None = -0.7) -> Update:
    return at("anomaly", {"seq": seq, "score": -0.5 if flagged else -0.9,
                          "threshold": threshold, "is_anomaly": flagged,
                          "reason": None}, 10.0 + seq)


def test_states_are_throttled_but_a_mode_change_always_shows() -> None:
    term = Terminal(state_every_s=1.0)
    lines = [term.line(state(i * 0.1, 100.0 + i * 0.1)) for i in range(25)]
    shown = [line for line in lines if line is not None]
    assert len(shown) == 3  # at 100.0, 101.0, 102.0 s
    assert "t=   0.00 s" in shown[0] and "pos=(  1.00,   2.00,   3.00) m" in shown[0]
    assert "|v|=0.50 m/s" in shown[0] and " state " in shown[0]
    changed = term.line(state(2.55, 102.55, mode="recovering", chosen=3))
    assert changed is not None and "recovering" in changed and "y=3" in changed


def test_a_run_of_flags_is_one_line_and_the_return_to_nominal_sums_it_up() -> None:
    """Issue 44, item 12: every flagged verdict was a line (10 a second from a camera at
    10 Hz: 47 lines in 5 s). Now the first of a run, one whose reason changes, and the
    return to nominal saying how many there were."""
    term = Terminal()
    assert term.line(verdict(0, False)) is None
    first = term.line(verdict(1, True))
    assert first is not None and "ANOMALY seq=1" in first and "tau=-0.700" in first
    assert [term.line(verdict(i, True)) for i in range(2, 30)] == [None] * 28
    other = verdict(30, True)
    other.message["reason"] = "a keyboard"
    changed = term.line(other)
    assert changed is not None and "ANOMALY seq=30" in changed and "(a keyboard)" in changed
    back = term.line(verdict(31, False))
    assert back is not None and "nominal again seq=31" in back
    assert "after 30 flagged verdict(s) in 30.0 s (highest score -0.500)" in back
    assert term.line(verdict(32, False)) is None
    uncalibrated = term.line(verdict(33, True, threshold=None))
    assert uncalibrated is not None and "tau=none (uncalibrated)" in uncalibrated


def test_events_of_one_kind_show_a_few_at_a_time_and_then_a_count() -> None:
    term = Terminal()

    def event(kind: str, received: float) -> Update:
        return at("event", {"severity": "warning", "source": "control", "kind": kind,
                            "message": ""}, received)

    flapping = [term.line(event(kind, 100.0 + i * 0.1))
                for i in range(40) for kind in ("verdict_stale", "verdict_fresh")]
    shown = [line for line in flapping if line is not None]
    assert len(shown) == 2 * 3  # 4 s of flapping: the first three of each kind
    later = term.line(event("verdict_stale", 106.0))
    assert later is not None and "(and 37 more like it since the last one shown)" in later
    assert term.line(event("verdict_fresh", 106.1)) is not None
    # a flight's mode changes, a few in a row, all show
    changes = [term.line(event("mode_change", 107.0 + i * 0.05)) for i in range(3)]
    assert all(line is not None for line in changes)


def test_a_request_and_its_decision_with_the_chosen_label_and_source() -> None:
    term = Terminal()
    request = term.line(at("request", {
        "request_id": "0123456789abcdef", "deadline_s": 1.5,
        "observation": {"text": "a person\n on the pad"},
        "options": [{"index": 0, "label": "continue"}, {"index": 3, "label": "rooftop"}]},
        5.0))
    assert request is not None
    assert 'K=1.50 s "a person on the pad" options: 0 continue | 3 rooftop' in request
    assert "01234567 " in request and "89abcdef" not in request
    decision = term.line(at("decision", {
        "request_id": "0123456789abcdef", "choice": 3, "source": "llm", "latency_ms": 812.4,
        "rationale": "the pad is taken"}, 5.5))
    assert decision is not None
    assert "y=3 rooftop (source=llm, 812 ms) the pad is taken" in decision
    unknown = term.line(at("decision", {"request_id": "zz", "choice": 0,
                                        "source": "timeout", "latency_ms": 1500.0}, 6.0))
    assert unknown is not None and "y=0 ? (source=timeout" in unknown


def test_events_services_and_nothing_for_plans() -> None:
    term = Terminal()
    event = term.line(at("event", {"severity": "alarm", "source": "control",
                                   "kind": "verdict_stale", "message": "no verdicts"}, 1.0))
    assert event is not None and event.endswith("[alarm] control/verdict_stale: no verdicts")
    gone = term.line(at("health", {"service": "reasoner", "alive": False}, 1.0))
    assert gone is not None and gone.endswith("health   reasoner gone")
    assert term.line(at("plan", {"nominal": []}, 1.0)) is None


def test_a_fleet_is_watched_robot_by_robot_each_line_led_by_its_robot() -> None:
    term = Terminal(state_every_s=1.0, fleet=True)

    def of(robot: str, kind: str, message: dict, received: float) -> Update:
        return Update(kind, f"aesop/{robot}/{kind}", message, received)

    x = [1.0, 2.0, 3.0] + [0.0] * 9
    first = term.line(of("robot0", "state", {"t": 0.0, "x": x, "mode": "nominal"}, 100.0))
    other = term.line(of("robot1", "state", {"t": 0.0, "x": x, "mode": "nominal"}, 100.1))
    # each robot's states throttled on their own: robot1's first state shows
    assert first is not None and " robot0     state " in first
    assert other is not None and " robot1     state " in other
    assert term.line(of("robot0", "state", {"t": 0.2, "x": x, "mode": "nominal"}, 100.2)) is None
    flagged = {"seq": 1, "score": -0.5, "threshold": -0.7, "is_anomaly": True, "reason": None}
    calm = {**flagged, "is_anomaly": False, "score": -0.9}
    assert "robot1     anomaly  ANOMALY" in str(term.line(of("robot1", "anomaly", flagged, 101)))
    assert term.line(of("robot0", "anomaly", calm, 101.1)) is None  # robot0 never flagged
    back = term.line(of("robot1", "anomaly", calm, 101.2))
    assert back is not None and "nominal again" in back
    gone = term.line(Update("health", "aesop/health/embedding", {"service": "embedding",
                                                                  "alive": False}, 102.0))
    assert gone is not None and " -          health   embedding gone" in gone
