"""How the control loop reads the fast detector: freshness, and what silence means.

Pure logic: no clock, no I/O (the runtime in :mod:`services.control.loop` feeds it).

* :class:`Sightings` — when this service first saw each observation, by ``seq``.
  A verdict is as old as the observation it answers: a backlog of verdicts on old
  observations is not fresh, however recently it arrived. With no observations on
  the bus at all, the verdict's own arrival is all there is to go by. A count that
  starts again (the camera restarted) starts the record again.
* :func:`directive` — the fail-safe policy, one tick at a time. Silence is an
  anomaly: while verdicts are stale the reasoner is asked once per silent spell,
  told that the detector is silent and not offered "continue"; a "continue" for
  any pending anomaly is refused while the detector is silent; the tree of
  recoveries is kept and the fallback is committed at K as for any anomaly.
  Fresh verdicts end a silent spell's episode (unless the reasoner has already
  chosen a region, which stands). A vehicle whose state has gone stale is the same:
  the loop is unmonitored (:data:`UNMONITORED`) until both are fresh again.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import StrEnum


class Cause(StrEnum):
    """What a pending request to the reasoner is about."""

    ANOMALY = "anomaly"  # the detector flagged the scene
    SILENCE = "silence"  # the detector went silent
    VEHICLE = "vehicle"  # the vehicle's state went stale (or was refused)


UNMONITORED = (Cause.SILENCE, Cause.VEHICLE)  # the loop cannot see: "continue" is withheld


class Sightings:
    """Arrival times of recent observations, by ``seq`` (the newest ``size`` of them)."""

    def __init__(self, size: int = 512) -> None:
        self._seen: deque[tuple[int, float]] = deque(maxlen=size)

    def record(self, seq: int, at: float) -> None:
        """Observation ``seq`` was first seen at ``at`` (the runtime's clock, s). A number
        below the newest means the publisher counts again from the start (it restarted):
        what was seen before is forgotten."""
        if self._seen and seq < self._seen[-1][0]:
            self._seen.clear()
        if not self._seen or seq > self._seen[-1][0]:
            self._seen.append((seq, at))

    @property
    def any(self) -> bool:
        return bool(self._seen)

    def seen_at(self, seq: int) -> float | None:
        """When the observation a verdict for ``seq`` answers was seen: that of ``seq``,
        else of the newest earlier one seen (a tick can miss one); ``None`` if older than
        anything remembered."""
        for number, at in reversed(self._seen):
            if number <= seq:
                return at
        return None


def verdict_age(sightings: Sightings, seq: int, arrived_at: float, now: float) -> float | None:
    """How old the verdict for observation ``seq`` is (s): the age of that observation,
    or, when no observation has ever been seen, of the verdict's arrival. ``None``:
    older than anything remembered."""
    if not sightings.any:
        return now - arrived_at
    seen = sightings.seen_at(seq)
    return None if seen is None else now - seen


@dataclass(frozen=True)
class Directive:
    """What one tick hands the controller, and what it refused or ended."""

    anomaly: bool  # the flag for make_step
    decision: int | None  # the decision for make_step
    cause: Cause | None = None  # of the request make_step may raise this tick
    refused_continue: bool = False  # a "continue" refused because the detector is silent
    ended_silence: bool = False  # fresh verdicts ended a silent spell's episode


def directive(*, fresh: bool, flagged: bool, pending: Cause | None, silence_asked: bool,
              decision: int | None, blind: Cause = Cause.SILENCE) -> Directive:
    """The fail-safe policy for one tick (module docstring).

    ``fresh``: the loop is monitored (a verdict answers a recent observation and the
    vehicle's state is fresh); when it is not, ``blind`` says why (:data:`UNMONITORED`).
    ``flagged``: that verdict is an anomaly worth asking about (new, not cleared).
    ``pending``: the cause of the request being waited on, if any. ``silence_asked``:
    this unmonitored spell has raised its request already. ``decision``: the reasoner's
    answer to the pending request, if it came this tick.
    """
    if not fresh:
        refused = decision == 0
        ask = pending is None and not silence_asked
        return Directive(anomaly=ask, decision=None if refused else decision,
                         cause=blind if ask else None, refused_continue=refused)
    if pending in UNMONITORED and not decision:
        # the detector is back: the silence is over, and the scene is judged afresh
        return Directive(anomaly=flagged, decision=0, cause=Cause.ANOMALY if flagged else None,
                         ended_silence=True)
    return Directive(anomaly=flagged, decision=decision,
                     cause=Cause.ANOMALY if flagged else None)
