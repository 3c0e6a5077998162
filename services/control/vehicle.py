"""The vehicle as the control loop sees it (pure: every time comes in as an argument).

* :class:`ClockMap` — the vehicle's clock on this host's (``time.monotonic()``). The
  two are not assumed to be one clock. When the vehicle answers clock queries
  (``aesop/{robot}/vehicle/clock``), the answer with the shortest round trip among the
  recent ones gives the offset, wrong by at most half that round trip (``sync``).
  Without them, the fastest arrival seen among the recent states is taken as instant
  (``arrival``): a state is then never judged younger than the time since it arrived,
  but a constant delay in the vehicle goes unseen.
* :class:`StateInput` — the newest usable state. A message is *new* when its ``seq``
  moved on (or the vehicle restarted: a lower ``seq`` with a later stamp); a repeated
  one refreshes nothing. A state is *refused* when it is not finite, is in another
  frame, has an attitude that is no unit quaternion, or has jumped: it lies farther from
  where the last accepted one was heading (its position plus its velocity times the time
  between their stamps) than ``jump_m`` plus what ``max_accel`` could add in that time
  (``a t^2 / 2``). A jumped estimate that stays self-consistent for ``reset_s`` is taken
  as the vehicle's new truth (an estimator reset). Freshness is judged on this host
  alone: the newest accepted state arrived at most ``limit_s`` ago. Its *age* (for delay
  compensation) is the time since it was valid, through the clock map, never less than
  the time since it arrived.
* :func:`state_vector`, :func:`setpoint` — the contract's messages to and from the
  12-state model's arrays.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np

from shared.bus import Received
from shared.frames import euler_from_quaternion
from shared.messages import MAX_AHEAD, Mode, VehicleSetpoint, VehicleState

from .aesop import ControlOutput
from .dynamics import N_STATE
from .handshake import Note
from .planning import PlanningModel

ClockSource = Literal["sync", "arrival"]
QUATERNION_SLACK = 0.05  # |q| may differ from 1 by this much before the state is refused


def state_vector(msg: VehicleState) -> np.ndarray:
    """The 12-state ``x`` of a state message: position, velocity, Z-Y-X Euler angles from
    its quaternion, body rates (SI)."""
    x = np.empty(N_STATE)
    x[0:3] = msg.position
    x[3:6] = msg.velocity
    q = msg.attitude
    norm = math.sqrt(sum(v * v for v in q)) if all(math.isfinite(v) for v in q) else math.nan
    x[6:9] = euler_from_quaternion(q) if norm > 0 else (math.nan,) * 3
    x[9:12] = msg.body_rates
    return x


class ClockMap:
    """Vehicle clock -> this host's clock (module docstring). Thread-safe: clock queries
    answer on another thread than the tick's."""

    def __init__(self, window: int = 64, sync_max_age_s: float = 30.0) -> None:
        self._lock = threading.Lock()
        self._syncs: deque[tuple[float, float, float]] = deque(maxlen=window)  # rtt, offset, at
        self._arrivals: deque[float] = deque(maxlen=window * 4)  # stamp - arrival
        self.sync_max_age_s = sync_max_age_s

    def sample(self, sent: float, answered: float, vehicle: float) -> None:
        """A clock query sent at ``sent`` and answered at ``answered`` (this host's clock)
        read ``vehicle`` on the vehicle's clock."""
        if not (math.isfinite(vehicle) and answered >= sent):
            return
        with self._lock:
            self._syncs.append((answered - sent, vehicle - (sent + answered) / 2, answered))

    def arrival(self, stamp: float, arrived: float) -> None:
        """A state stamped ``stamp`` (the vehicle's clock) arrived at ``arrived``."""
        with self._lock:
            self._arrivals.append(stamp - arrived)

    def offset(self, now: float) -> tuple[float, ClockSource] | None:
        """``vehicle - local`` and where it came from; None before any sample."""
        with self._lock:
            recent = [s for s in self._syncs if now - s[2] <= self.sync_max_age_s]
            if recent:
                return min(recent)[1], "sync"
            if self._arrivals:
                return max(self._arrivals), "arrival"  # the fastest arrival: taken as instant
        return None

    def round_trip_s(self, now: float) -> float | None:
        """The shortest recent round trip of a clock query (its half bounds the error)."""
        with self._lock:
            recent = [s[0] for s in self._syncs if now - s[2] <= self.sync_max_age_s]
        return min(recent) if recent else None


@dataclass(frozen=True)
class StateReading:
    """The vehicle's newest usable state as one tick sees it."""

    x: np.ndarray | None  # 12-state; None before any usable state
    fresh: bool  # it arrived within the limit
    seq: int | None
    stamp: float | None  # when it was valid, on the vehicle's clock
    arrival_age: float | None  # s since it arrived (this host)
    age: float | None  # s since it was valid, through the clock map (>= arrival_age)
    clock: ClockSource | None
    notes: tuple[Note, ...] = ()

    @property
    def position(self) -> tuple[float, float, float] | None:
        if self.x is None:
            return None
        return (float(self.x[0]), float(self.x[1]), float(self.x[2]))


@dataclass(frozen=True)
class Refusal:
    """Why a state was refused: its ``kind`` (one alarm per run of one kind) and words."""

    kind: Literal["frame", "finite", "attitude", "jump"]
    why: str


@dataclass
class _Accepted:
    x: np.ndarray
    seq: int
    stamp: float
    arrived: float


class StateInput:
    """The newest usable vehicle state, offered each tick from the bus's slot (module
    docstring). ``max_accel`` (m/s^2) bounds how far the vehicle may stray between two
    stamps from where it was heading before a state counts as a jump."""

    def __init__(self, *, limit_s: float, frame: str = "world", jump_m: float = 0.5,
                 reset_s: float = 0.5, max_accel: float = 5.0,
                 clock: ClockMap | None = None) -> None:
        self.limit_s, self.frame = limit_s, frame
        self.jump_m, self.reset_s, self.max_accel = jump_m, reset_s, max_accel
        self.clock = clock or ClockMap()
        self._last: _Accepted | None = None
        self._offered: tuple[int, float] | None = None  # (seq, arrival) of the last offer
        self._candidate: _Accepted | None = None  # a jumped estimate, and since when
        self._candidate_since: float | None = None
        self._refusal: Refusal | None = None  # why the newest new message was refused
        self._notes: list[Note] = []
        self._fresh: bool | None = None  # as the last read said
        self._newest: np.ndarray | None = None
        self.accepted = 0
        self.refused = 0

    @property
    def last(self) -> tuple[np.ndarray, float] | None:
        """The newest accepted state and its stamp."""
        return None if self._last is None else (self._last.x.copy(), self._last.stamp)

    @property
    def newest(self) -> np.ndarray | None:
        """The newest finite state in the frame, accepted or not (where a new flight starts:
        a vehicle moved between flights is refused as a jump until the reset)."""
        return None if self._newest is None else self._newest.copy()

    def forget(self) -> None:
        """A new flight: the next state is taken wherever it is (no jump from the last)."""
        self._last = self._candidate = None
        self._candidate_since = self._refusal = self._fresh = None

    def offer(self, got: Received[VehicleState], *, gate: bool = True) -> None:
        """The slot's newest message (perhaps the one offered last tick). ``gate``: refuse a
        jump (off while no flight is under way: a vehicle moved before it is no jump)."""
        msg = got.message
        if self._offered == (msg.seq, got.received_at):
            return
        self._offered = (msg.seq, got.received_at)
        last = self._last
        if last is not None and msg.seq <= last.seq and not msg.stamp > last.stamp:
            return  # a repeat, or older than what we have: nothing new
        x = state_vector(msg)
        why = self._check(msg, x)
        if why is None:
            self._newest = x
        if why is None and last is not None and gate:
            why = self._jump(x, msg, got.received_at, last)
        if why is not None:
            self.refused += 1
            if self._refusal is None or why.kind != self._refusal.kind:  # once a run
                self._notes.append(Note("state_refused", "alarm", f"vehicle state {msg.seq} "
                                        f"refused: {why.why}", {"seq": msg.seq,
                                                                "refusal": why.kind}))
            self._refusal = why
            return
        self._refusal = None
        self._accept(_Accepted(x, msg.seq, msg.stamp, got.received_at))

    def _check(self, msg: VehicleState, x: np.ndarray) -> Refusal | None:
        if msg.frame != self.frame:
            return Refusal("frame", f"frame {msg.frame!r} is not the loop's {self.frame!r}")
        if not (np.all(np.isfinite(x)) and math.isfinite(msg.stamp)):
            return Refusal("finite", "not finite")
        norm = math.sqrt(sum(v * v for v in msg.attitude))
        if abs(norm - 1.0) > QUATERNION_SLACK:
            return Refusal("attitude", f"the attitude is not a unit quaternion "
                                       f"(norm {norm:.3f})")
        return None

    def _jump(self, x: np.ndarray, msg: VehicleState, arrived: float, last: _Accepted
              ) -> Refusal | None:
        """None if ``x`` is within reach of the last accepted state; else why, unless it
        continues a jumped estimate that has now held for ``reset_s`` (then accepted)."""
        if self._within(x, msg.stamp, last):
            self._candidate = self._candidate_since = None
            return None
        moved = float(np.linalg.norm(x[0:3] - last.x[0:3] - last.x[3:6] * (msg.stamp
                                                                           - last.stamp)))
        here = _Accepted(x, msg.seq, msg.stamp, arrived)
        jumped = Refusal("jump", f"it jumped {moved:.2f} m from where the last accepted state "
                                 "was heading")
        candidate = self._candidate
        if candidate is None or not self._within(x, msg.stamp, candidate):
            self._candidate, self._candidate_since = here, msg.stamp
            return jumped
        self._candidate = here
        since = self._candidate_since if self._candidate_since is not None else msg.stamp
        if msg.stamp - since < self.reset_s:
            return jumped
        self._notes.append(Note("state_reset", "alarm", f"the vehicle's estimate moved "
                                f"{moved:.2f} m and has held there for {msg.stamp - since:.2f} s:"
                                " taken as its new state", {"seq": msg.seq,
                                                            "moved_m": round(moved, 3)}))
        self._candidate = self._candidate_since = None
        return None

    def _within(self, x: np.ndarray, stamp: float, ref: _Accepted) -> bool:
        span = abs(stamp - ref.stamp)
        heading = ref.x[0:3] + ref.x[3:6] * (stamp - ref.stamp)
        reach = self.jump_m + 0.5 * self.max_accel * span * span
        return bool(np.linalg.norm(x[0:3] - heading) <= reach)

    def _accept(self, state: _Accepted) -> None:
        self._last = state
        self.accepted += 1
        self.clock.arrival(state.stamp, state.arrived)

    def read(self, now: float) -> StateReading:
        """What the tick at ``now`` (this host's clock) sees."""
        last = self._last
        notes, self._notes = self._notes, []
        if last is None:
            fresh, arrival_age, age, source = False, None, None, None
        else:
            arrival_age = max(0.0, now - last.arrived)
            fresh = arrival_age <= self.limit_s
            mapped = self.clock.offset(now)
            source = None if mapped is None else mapped[1]
            age = arrival_age if mapped is None else max(arrival_age,
                                                         now - (last.stamp - mapped[0]))
        if self._fresh is True and not fresh:
            why = (f"the newest vehicle states were refused ({self._refusal.why})"
                   if self._refusal is not None else
                   f"no vehicle state for {(arrival_age or 0.0) * 1000:.0f} ms")
            notes.append(Note("state_stale", "alarm", f"{why} (limit {self.limit_s * 1000:.0f}"
                              " ms): flying blind on the last verified recovery branch, "
                              "counted as an anomaly",
                              {"age_s": None if arrival_age is None else round(arrival_age, 3)}))
        elif self._fresh is False and fresh:
            notes.append(Note("state_fresh", "info", "the vehicle's state is arriving again",
                              {"age_s": round(arrival_age or 0.0, 3)}))
        if fresh or self._fresh is not None:  # no "fresh again" for the first state
            self._fresh = fresh
        return StateReading(None if last is None else last.x.copy(), fresh,
                            None if last is None else last.seq,
                            None if last is None else last.stamp, arrival_age, age, source,
                            tuple(notes))


def setpoint(*, robot: str, seq: int, output: ControlOutput, model: PlanningModel,
             reading: StateReading, valid_s: float, mode: Mode, period_s: float,
             ahead: int = 0) -> VehicleSetpoint | None:
    """The set-point of one tick's ``output``; None when there is nothing to send: no state
    was ever seen (no clock to write the times in), or the step flew blind past the end of
    its kept branch (the vehicle's own hold is safer than repeating its last input).

    The times are on the vehicle's clock: the state's stamp plus its age at this tick,
    and ``valid_s`` more for ``valid_until``. ``ahead``: how many of the plan's next inputs
    go with it, one per ``period_s``.
    """
    if reading.stamp is None or reading.age is None or reading.x is None or output.blind == 0:
        return None
    t = reading.stamp + reading.age
    u = output.u
    if output.reference is not None:
        ref = output.reference
        position = tuple(float(ref[i]) for i in model.position)
        velocity = tuple(float(ref[i]) for i in model.velocity)
    else:  # no plan: hold where the vehicle was last seen
        position, velocity = tuple(float(v) for v in reading.x[0:3]), (0.0, 0.0, 0.0)
    if model.name == "point-mass":
        command: dict[str, object] = {"acceleration": (float(u[0]), float(u[1]), float(u[2]))}
    else:
        command = {"thrust": float(u[0]), "torque": (float(u[1]), float(u[2]), float(u[3]))}
    later = tuple(tuple(float(v) for v in a) for a in output.ahead[:min(ahead, MAX_AHEAD)])
    return VehicleSetpoint(robot=robot, seq=seq, state_seq=reading.seq or 0,
                           state_stamp=reading.stamp, t=t, valid_until=t + valid_s, mode=mode,
                           position=position, velocity=velocity, ahead=later,
                           step_s=period_s if later else None, **command)
