"""The loop's conversation with the detector and the reasoner, one tick at a time.

Pure logic: no clock, no I/O, no messages built (the runtime in :mod:`.loop`
feeds it ages and answers and turns its notes into ``Event``s). What it
remembers beside Algorithm 1's own memory (the controller's):

* the request being waited on (``pending``), what it is about (``cause``:
  a flagged scene or a silent detector) and whether its answer has been handed
  to the controller (``delivered``);
* whether the detector is silent (``stale``) and whether this silent spell has
  raised its request (``silence_asked``);
* the verdict that raised the last request (``verdict_asked``: a verdict asks
  once), the scene it was about (``asked_about``) and the scenes the reasoner
  answered "continue" for (``cleared``: flagged again, they do not ask again
  until the flight is reset).

The policy itself is :func:`.detector.directive`; this object holds the state
around it, so that one table (``tests/unit/test_control_handshake.py``) can
show every step.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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


@dataclass
class Handshake:
    """The pending request, the detector's silence and the cleared scenes (module docstring)."""

    pending: str | None = None  # request_id the next decision must carry
    cause: Cause | None = None  # what the pending request is about
    delivered: bool = False  # its answer went to the controller
    refused: str | None = None  # request_id whose "continue" was refused (said once)
    stale: bool | None = None  # None until the flight's first tick
    monitored: bool | None = None  # verdicts and the vehicle's state were fresh last tick
    silence_asked: bool = False  # this unmonitored spell has raised its request
    verdict_asked: int | None = None  # seq of the verdict that asked
    asked_about: str | None = None  # the scene text of the pending request
    cleared: set[str] = field(default_factory=set)  # scenes answered "continue"
    said_cleared: str | None = None  # the cleared scene the last note was about

    def read(self, *, mode: Mode, age: float | None, limit: float,
             verdict: AnomalyVerdict | None, scene: str | None,
             decision: ReasonerDecision | None, vehicle: bool = True) -> Reading:
        """One tick's inputs: the age of the newest verdict (s, of the observation it
        answers; ``None`` when there is none or it is older than anything remembered),
        the freshness ``limit`` (s), that verdict, the scene text it judged, the newest
        decision on the bus, and whether the vehicle's state is fresh (``vehicle``; the
        runtime says why when it is not)."""
        notes: list[Note] = []
        fresh = age is not None and age <= limit
        if mode is Mode.WAITING:
            if not (fresh and vehicle):
                return Reading(False, None, None, not fresh, True)
            notes.append(Note("flight_started", "info", "the anomaly detector is answering and "
                              "the vehicle's state is fresh: the flight starts",
                              {"age_s": round(age or 0.0, 3)}))
        if not fresh and self.stale is not True:
            why = ("no anomaly verdict has arrived" if verdict is None else
                   "the newest anomaly verdict answers an observation older than anything "
                   "remembered" if age is None else
                   f"the newest anomaly verdict answers an observation {age:.2f} s old")
            notes.append(Note(
                "verdict_stale", "alarm",
                f"{why} (limit {limit:g} s): the detector is silent, counted as an anomaly",
                {"age_s": None if age is None else round(age, 3)}))
        elif fresh and self.stale is True:
            notes.append(Note("verdict_fresh", "info", "anomaly verdicts are answering fresh "
                              "observations again", {"age_s": round(age or 0.0, 3)}))
        self.stale = not fresh
        monitored = fresh and vehicle
        if not monitored and self.monitored is not False:  # a new unmonitored spell
            self.silence_asked = False
        self.monitored = monitored
        routed = None
        if (decision is not None and self.pending is not None and not self.delivered
                and decision.request_id == self.pending):
            routed, self.delivered = decision.choice, True
        pending = self.cause if mode is Mode.PENDING else None
        if monitored and routed == 0 and pending is Cause.ANOMALY and self.asked_about:
            self.cleared.add(self.asked_about)  # before this tick's verdict is judged
        flagged = (fresh and verdict is not None and verdict.is_anomaly
                   and verdict.seq != self.verdict_asked)
        judged = scene if flagged else None
        if judged is not None and judged in self.cleared:
            flagged = False
            if judged != self.said_cleared:  # once per run of flags on that scene
                notes.append(Note("anomaly_cleared", "info", "flagged scene already judged "
                                  "harmless by the reasoner: not asking again",
                                  {"seq": verdict.seq if verdict else None}))
        self.said_cleared = judged if judged in self.cleared else None
        act = directive(fresh=monitored, flagged=flagged, pending=pending,
                        silence_asked=self.silence_asked, decision=routed,
                        blind=Cause.SILENCE if not fresh else Cause.VEHICLE)
        if act.refused_continue:
            self.delivered = False  # a later region answer to this request still counts
            if self.refused != self.pending:  # the slot repeats its answer every tick
                self.refused = self.pending
                why = "the detector is silent" if not fresh else "the vehicle's state is stale"
                notes.append(Note("continue_refused", "warning", "the reasoner said continue, "
                                  f"but {why}: still waiting for a region or the fallback "
                                  "at K"))
        if act.ended_silence:
            notes.append(Note("silence_ended", "info", "the detector answers and the "
                              "vehicle's state is fresh again: the unmonitored spell's "
                              "episode ends"))
        return Reading(act.anomaly, act.decision, act.cause, not fresh, False, tuple(notes))

    def asked(self, request_id: str, cause: Cause | None, scene: str | None,
              verdict_seq: int | None) -> None:
        """A request went out this tick: about ``scene`` (the observation text) for a
        flagged verdict ``verdict_seq``, or about the detector's silence."""
        self.pending, self.delivered, self.cause = request_id, False, cause
        if cause in UNMONITORED:
            self.asked_about, self.silence_asked = None, True
        else:
            self.asked_about = scene
            if verdict_seq is not None:
                self.verdict_asked = verdict_seq

    def settle(self) -> None:
        """A tick without a request: an answered request is closed (a late duplicate of
        its answer is ignored)."""
        if self.delivered:
            self.pending = None

    def forget_request(self) -> None:
        """The regions changed: a request about the old ones has no answer to wait for."""
        self.pending = None
