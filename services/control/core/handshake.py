"""The loop's conversation with the detector and the reasoner, one tick at a time.

Pure logic: no clock, no I/O, no messages built (the runtime in
:mod:`services.control.loop` feeds it ages and answers and turns its notes into ``Event``s).
A tick is two transitions of one immutable :class:`Handshake`:

* :func:`step` (before the controller's ``make_step``): the tick's inputs in, what the
  controller is handed (:class:`Reading`) and the state after out;
* :func:`conclude` (after it): a request went out (:class:`Asked`), or none did.

The request lifecycle is an explicit :class:`Phase`: ``idle`` (nothing asked), ``asked``
(a request out, its answer not yet handed to the controller), ``answered`` (handed on;
closed at the end of the tick). Beside it the state remembers what the request is about
(``cause``: a flagged scene, a silent detector, a stale vehicle state); whether the loop
is unmonitored (``stale`` verdicts, or not ``monitored``) and whether this unmonitored
spell has asked (``silence_asked``); the verdict that raised the last request (a verdict
asks once), the scene it was about and the scenes the reasoner answered "continue" for
(``cleared``: flagged again, they do not ask again until the flight is reset).

The policy itself is :func:`.verdicts.directive`; one table
(``tests/unit/test_control_handshake.py``) shows every step.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import StrEnum

from shared.messages import AnomalyVerdict, Mode, ReasonerDecision, Severity

from .verdicts import UNMONITORED, Cause, directive

NoteData = dict[str, str | int | float | bool | None]


@dataclass(frozen=True)
class Note:
    """Something a person should see, for the runtime to publish as an ``Event``."""

    kind: str
    severity: Severity
    message: str
    data: NoteData = field(default_factory=dict)


@dataclass(frozen=True)
class Reading:
    """What one tick hands the controller, and what to tell a person."""

    anomaly: bool  # the flag for make_step
    decision: int | None  # the reasoner's answer for make_step, at most once per request
    cause: Cause | None  # of the request make_step may raise this tick
    stale: bool  # the detector is silent (no fresh verdict)
    waiting: bool  # the flight has not started: hold, step nothing
    notes: tuple[Note, ...] = ()


class Phase(StrEnum):
    """Where the request to the reasoner is in its life."""

    IDLE = "idle"  # nothing asked, or the last request closed
    ASKED = "asked"  # a request out; its answer has not reached the controller
    ANSWERED = "answered"  # its answer went to the controller (closed after this tick)


@dataclass(frozen=True)
class Handshake:
    """The request, the detector's silence and the cleared scenes (module docstring)."""

    phase: Phase = Phase.IDLE
    request_id: str | None = None  # of the request asked (the next decision must carry it)
    cause: Cause | None = None  # what it is about
    refused: str | None = None  # request_id whose "continue" was refused (said once)
    stale: bool | None = None  # verdicts stale last tick; None until the flight's first tick
    monitored: bool | None = None  # verdicts and the vehicle's state were fresh last tick
    silence_asked: bool = False  # this unmonitored spell has raised its request
    verdict_asked: int | None = None  # seq of the verdict that asked
    asked_about: str | None = None  # the scene of the request (its text and detections)
    cleared: frozenset[str] = frozenset()  # scenes answered "continue"
    said_cleared: str | None = None  # the cleared scene the last note was about

    @property
    def pending(self) -> str | None:
        """The request being waited on (asked, or answered this tick)."""
        return None if self.phase is Phase.IDLE else self.request_id


@dataclass(frozen=True)
class Inputs:
    """One tick's inputs: the loop's mode, the age of the newest verdict (s, of the
    observation it answers; ``None`` when there is none or it is older than anything
    remembered), the freshness ``limit`` (s), that verdict, the scene text it judged, the
    newest decision on the bus, and whether the vehicle's state is fresh (``vehicle``;
    the runtime says why when it is not)."""

    mode: Mode
    age: float | None
    limit: float
    verdict: AnomalyVerdict | None = None
    scene: str | None = None
    decision: ReasonerDecision | None = None
    vehicle: bool = True


@dataclass(frozen=True)
class Asked:
    """A request that went out this tick: about ``scene`` (the observation text) for a
    flagged verdict ``verdict_seq``, or about the loop being unmonitored (``cause``)."""

    request_id: str
    cause: Cause | None
    scene: str | None
    verdict_seq: int | None


def step(state: Handshake, tick: Inputs) -> tuple[Handshake, Reading]:
    """The state after this tick's inputs, and what the controller is handed."""
    notes: list[Note] = []
    age, limit, verdict = tick.age, tick.limit, tick.verdict
    fresh = age is not None and age <= limit
    if tick.mode is Mode.WAITING:
        if not (fresh and tick.vehicle):
            return state, Reading(False, None, None, not fresh, True)
        notes.append(Note("flight_started", "info", "the anomaly detector is answering and "
                          "the vehicle's state is fresh: the flight starts",
                          {"age_s": round(age or 0.0, 3)}))
    if not fresh and state.stale is not True:
        why = ("no anomaly verdict has arrived" if verdict is None else
               "the newest anomaly verdict answers an observation older than anything "
               "remembered" if age is None else
               f"the newest anomaly verdict answers an observation {age:.2f} s old")
        notes.append(Note(
            "verdict_stale", "alarm",
            f"{why} (limit {limit:g} s): the detector is silent, counted as an anomaly",
            {"age_s": None if age is None else round(age, 3)}))
    elif fresh and state.stale is True:
        notes.append(Note("verdict_fresh", "info", "anomaly verdicts are answering fresh "
                          "observations again", {"age_s": round(age or 0.0, 3)}))
    monitored = fresh and tick.vehicle
    new_spell = not monitored and state.monitored is not False  # an unmonitored spell begins
    silence_asked = False if new_spell else state.silence_asked
    phase, routed = state.phase, None
    decision = tick.decision
    if decision is not None and phase is Phase.ASKED and decision.request_id == state.request_id:
        routed, phase = decision.choice, Phase.ANSWERED
    pending = state.cause if tick.mode is Mode.PENDING else None
    cleared = state.cleared
    if monitored and routed == 0 and pending is Cause.ANOMALY and state.asked_about:
        cleared = cleared | {state.asked_about}  # before this tick's verdict is judged
    flagged = (fresh and verdict is not None and verdict.is_anomaly
               and verdict.seq != state.verdict_asked)
    judged = tick.scene if flagged else None
    if judged is not None and judged in cleared:
        flagged = False
        if judged != state.said_cleared:  # once per run of flags on that scene
            notes.append(Note("anomaly_cleared", "info", "flagged scene already judged "
                              "harmless by the reasoner: not asking again",
                              {"seq": verdict.seq if verdict else None}))
    act = directive(fresh=monitored, flagged=flagged, pending=pending,
                    silence_asked=silence_asked, decision=routed,
                    blind=Cause.SILENCE if not fresh else Cause.VEHICLE)
    refused = state.refused
    if act.refused_continue:
        phase = Phase.ASKED  # a later region answer to this request still counts
        if refused != state.pending:  # the slot repeats its answer every tick
            refused = state.pending
            why = "the detector is silent" if not fresh else "the vehicle's state is stale"
            notes.append(Note("continue_refused", "warning", "the reasoner said continue, "
                              f"but {why}: still waiting for a region or the fallback at K"))
    if act.ended_silence:
        notes.append(Note("silence_ended", "info", "the detector answers and the vehicle's "
                          "state is fresh again: the unmonitored spell's episode ends"))
    after = replace(state, phase=phase, refused=refused, stale=not fresh, monitored=monitored,
                    silence_asked=silence_asked, cleared=cleared,
                    said_cleared=judged if judged in cleared else None)
    return after, Reading(act.anomaly, act.decision, act.cause, not fresh, False, tuple(notes))


def conclude(state: Handshake, asked: Asked | None) -> Handshake:
    """The end of a tick: a request went out (``asked``), or none did, and an answered
    request is closed (a late duplicate of its answer is ignored)."""
    if asked is None:
        return replace(state, phase=Phase.IDLE) if state.phase is Phase.ANSWERED else state
    state = replace(state, phase=Phase.ASKED, request_id=asked.request_id, cause=asked.cause)
    if asked.cause in UNMONITORED:
        return replace(state, asked_about=None, silence_asked=True)
    return replace(state, asked_about=asked.scene,
                   verdict_asked=state.verdict_asked if asked.verdict_seq is None
                   else asked.verdict_seq)


def forget_request(state: Handshake) -> Handshake:
    """The regions changed: a request about the old ones has no answer to wait for."""
    return replace(state, phase=Phase.IDLE)
