"""The loop's handshake with the detector and the reasoner, as one table of the pure
transition ``step``: the state before, one tick's inputs, what the controller is handed,
what a person is told, the state after; then ``conclude``, the end of a tick."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import pytest

from services.control.core.handshake import (
    Asked,
    Handshake,
    Inputs,
    Phase,
    conclude,
    forget_request,
    step,
)
from services.control.core.verdicts import Cause
from shared.messages import AnomalyVerdict, Mode, ReasonerDecision

LIMIT = 0.5  # s: verdict freshness
FRESH, OLD = 0.1, 2.0  # s: verdict ages
KEYBOARD = "a keyboard on the ground"
REQ = "req-1"


def verdict(seq: int, flagged: bool) -> AnomalyVerdict:
    return AnomalyVerdict(seq=seq, score=-0.5, threshold=-0.7, is_anomaly=flagged, k=1,
                          model="m", cache="c", cache_version=1, latency_ms=1.0)


def answer(choice: int, request_id: str = REQ) -> ReasonerDecision:
    return ReasonerDecision(request_id=request_id, choice=choice, source="llm", latency_ms=1.0)


@dataclass(frozen=True)
class Tick:
    mode: Mode = Mode.NOMINAL
    age: float | None = FRESH
    verdict: AnomalyVerdict | None = field(default_factory=lambda: verdict(7, False))
    scene: str | None = KEYBOARD
    decision: ReasonerDecision | None = None
    vehicle: bool = True  # the vehicle's state is fresh


@dataclass(frozen=True)
class Handed:
    anomaly: bool = False
    decision: int | None = None
    cause: Cause | None = None
    stale: bool = False
    waiting: bool = False
    notes: tuple[str, ...] = ()


ASKING = {"phase": Phase.ASKED, "request_id": REQ}
SILENT = Handshake(stale=True, monitored=False, silence_asked=True, cause=Cause.SILENCE,
                   **ASKING)
BLIND = Handshake(stale=False, monitored=False, silence_asked=True, cause=Cause.VEHICLE,
                  **ASKING)
ASKED = Handshake(stale=False, cause=Cause.ANOMALY, verdict_asked=7, asked_about=KEYBOARD,
                  **ASKING)
IDLE = {"phase": Phase.IDLE, "request_id": None, "cause": None}
PENDING, FLAG = Mode.PENDING, verdict(8, True)

# (name, state before, tick, handed, fields of the state after)
TABLE: list[tuple[str, Handshake, Tick, Handed, dict[str, Any]]] = [
    ("waiting, no verdict: hold", Handshake(), Tick(Mode.WAITING, None, None),
     Handed(stale=True, waiting=True), {"stale": None}),
    ("waiting, a stale verdict: hold", Handshake(), Tick(Mode.WAITING, OLD),
     Handed(stale=True, waiting=True), {"stale": None}),
    ("waiting, a fresh verdict: the flight starts", Handshake(), Tick(Mode.WAITING),
     Handed(notes=("flight_started",)), {"stale": False}),
    ("a fresh nominal verdict", Handshake(stale=False), Tick(), Handed(), {}),
    ("a new flagged verdict asks", Handshake(stale=False), Tick(verdict=FLAG),
     Handed(anomaly=True, cause=Cause.ANOMALY), {}),
    ("a verdict asks once", replace(ASKED, **IDLE),
     Tick(verdict=verdict(7, True)), Handed(), {}),
    ("silence is an anomaly: alarm once, ask about the silence", Handshake(stale=False),
     Tick(age=OLD), Handed(anomaly=True, cause=Cause.SILENCE, stale=True,
                           notes=("verdict_stale",)), {"stale": True, "silence_asked": False}),
    ("no verdict at all is silence", Handshake(stale=False), Tick(age=None, verdict=None),
     Handed(anomaly=True, cause=Cause.SILENCE, stale=True, notes=("verdict_stale",)), {}),
    ("a silent spell asks once", replace(SILENT, **IDLE), Tick(age=OLD),
     Handed(stale=True), {}),
    ("continue is refused while silent, said once", SILENT,
     Tick(PENDING, OLD, decision=answer(0)),
     Handed(stale=True, notes=("continue_refused",)), {"phase": Phase.ASKED, "refused": REQ}),
    ("the refusal is not said again", replace(SILENT, refused=REQ),
     Tick(PENDING, OLD, decision=answer(0)), Handed(stale=True), {"phase": Phase.ASKED}),
    ("a region answer while silent is handed on", replace(SILENT, refused=REQ),
     Tick(PENDING, OLD, decision=answer(2)), Handed(decision=2, stale=True),
     {"phase": Phase.ANSWERED}),
    ("fresh verdicts end the silence's episode", SILENT, Tick(PENDING),
     Handed(decision=0, notes=("verdict_fresh", "silence_ended")), {"stale": False}),
    ("fresh and flagged after silence: ask about the scene", SILENT,
     Tick(PENDING, verdict=FLAG),
     Handed(anomaly=True, decision=0, cause=Cause.ANOMALY,
            notes=("verdict_fresh", "silence_ended")), {}),
    ("a region chosen during silence stands when the detector is back",
     replace(SILENT, refused=REQ), Tick(PENDING, decision=answer(3)),
     Handed(decision=3, notes=("verdict_fresh",)), {"phase": Phase.ANSWERED}),
    ("continue for a flagged scene clears it", ASKED, Tick(PENDING, decision=answer(0)),
     Handed(decision=0), {"phase": Phase.ANSWERED, "cleared": {KEYBOARD}}),
    ("a cleared scene flagged again does not ask, said once",
     Handshake(stale=False, cleared=frozenset({KEYBOARD})), Tick(verdict=FLAG),
     Handed(notes=("anomaly_cleared",)), {"said_cleared": KEYBOARD}),
    ("and is not said again while it stays flagged",
     Handshake(stale=False, cleared=frozenset({KEYBOARD}), said_cleared=KEYBOARD),
     Tick(verdict=FLAG),
     Handed(), {"said_cleared": KEYBOARD}),
    ("another scene flagged still asks", Handshake(stale=False, cleared=frozenset({KEYBOARD})),
     Tick(verdict=FLAG, scene="a quadrotor on the red box"),
     Handed(anomaly=True, cause=Cause.ANOMALY), {"said_cleared": None}),
    ("an answer to another request is ignored", ASKED,
     Tick(PENDING, decision=answer(2, "req-old")), Handed(), {"phase": Phase.ASKED}),
    ("an answer is handed on once", replace(ASKED, phase=Phase.ANSWERED),
     Tick(PENDING, decision=answer(2)), Handed(), {}),
    ("waiting, a fresh verdict but no fresh state: hold", Handshake(),
     Tick(Mode.WAITING, vehicle=False), Handed(waiting=True), {"stale": None}),
    ("a stale vehicle state is an anomaly: ask about the vehicle",
     Handshake(stale=False, monitored=True), Tick(vehicle=False),
     Handed(anomaly=True, cause=Cause.VEHICLE), {"monitored": False, "silence_asked": False}),
    ("a flagged verdict while the state is stale asks about the vehicle, once",
     Handshake(stale=False, monitored=True), Tick(verdict=FLAG, vehicle=False),
     Handed(anomaly=True, cause=Cause.VEHICLE), {}),
    ("continue is refused while the state is stale", BLIND,
     Tick(PENDING, decision=answer(0), vehicle=False), Handed(notes=("continue_refused",)),
     {"phase": Phase.ASKED, "refused": REQ}),
    ("the detector falling silent in the same spell does not ask again",
     replace(BLIND, **IDLE), Tick(age=OLD, vehicle=False),
     Handed(stale=True, notes=("verdict_stale",)), {}),
    ("a fresh state ends the vehicle's episode", BLIND, Tick(PENDING),
     Handed(decision=0, notes=("silence_ended",)), {"monitored": True}),
    ("a region chosen while the state was stale stands", replace(BLIND, refused=REQ),
     Tick(PENDING, decision=answer(1)), Handed(decision=1), {"phase": Phase.ANSWERED}),
    ("a verdict older than anything remembered is silence", Handshake(stale=False),
     Tick(age=None), Handed(anomaly=True, cause=Cause.SILENCE, stale=True,
                            notes=("verdict_stale",)), {}),
]


@pytest.mark.parametrize(("before", "tick", "handed", "after"),
                         [row[1:] for row in TABLE], ids=[row[0] for row in TABLE])
def test_one_tick_of_the_handshake(before: Handshake, tick: Tick, handed: Handed,
                                   after: dict[str, Any]) -> None:
    state, reading = step(before, Inputs(tick.mode, tick.age, LIMIT, tick.verdict, tick.scene,
                                         tick.decision, tick.vehicle))
    got = Handed(reading.anomaly, reading.decision, reading.cause, reading.stale,
                 reading.waiting, tuple(n.kind for n in reading.notes))
    assert got == handed
    for name, value in after.items():
        assert getattr(state, name) == value, name


def test_a_stale_alarm_says_why() -> None:
    told = {}
    for age, v in ((None, None), (None, verdict(1, False)), (OLD, verdict(1, False))):
        (note,) = step(Handshake(stale=False), Inputs(Mode.NOMINAL, age, LIMIT, v))[1].notes
        told[(age, v is None)] = note.message
    assert told[(None, True)].startswith("no anomaly verdict has arrived")
    assert "older than anything remembered" in told[(None, False)]
    assert "2.00 s old" in told[(OLD, False)] and "limit 0.5 s" in told[(OLD, False)]


def test_a_request_remembers_what_it_asked_and_an_answer_closes_it() -> None:
    state = conclude(Handshake(stale=False), Asked(REQ, Cause.ANOMALY, KEYBOARD, 8))
    assert (state.phase, state.pending, state.cause, state.asked_about,
            state.verdict_asked) == (Phase.ASKED, REQ, Cause.ANOMALY, KEYBOARD, 8)
    state = conclude(state, None)
    assert state.pending == REQ  # not answered yet: still waited on
    state, reading = step(state, Inputs(Mode.PENDING, FRESH, LIMIT, verdict(9, True),
                                        KEYBOARD, answer(2)))
    assert reading.decision == 2 and state.phase is Phase.ANSWERED
    state = conclude(state, None)
    assert state.pending is None and state.phase is Phase.IDLE
    state, reading = step(state, Inputs(Mode.RECOVERING, FRESH, LIMIT, verdict(10, False),
                                        None, answer(2)))
    assert reading.decision is None  # a late duplicate of the answer is ignored


def test_a_silence_request_asks_once_and_names_no_scene() -> None:
    state = conclude(Handshake(stale=True, asked_about="old scene"),
                     Asked(REQ, Cause.SILENCE, KEYBOARD, 3))
    assert state.silence_asked and state.asked_about is None and state.verdict_asked is None


def test_new_regions_drop_the_request() -> None:
    assert forget_request(ASKED).pending is None


def test_a_transition_never_changes_the_state_it_was_given() -> None:
    before = replace(ASKED, cleared=frozenset({"a mop"}))
    after, _ = step(before, Inputs(Mode.PENDING, FRESH, LIMIT, decision=answer(0)))
    assert before.phase is Phase.ASKED and before.cleared == {"a mop"}
    assert after.phase is Phase.ANSWERED and after.cleared == {"a mop", KEYBOARD}
