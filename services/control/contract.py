"""The vehicle contract as the loop keeps it: freshness, refusals, clock map, set-points.

Pure: every time comes in as an argument.

* :class:`ClockMap` — the vehicle's clock on this host's (``time.monotonic()``). The
  two are not assumed to be one clock. When the vehicle answers clock queries
  (``aesop/{robot}/vehicle/clock``), the answer with the shortest round trip among the
  recent ones gives the offset, wrong by at most half that round trip (``sync``).
  Without them, the fastest arrival seen among the recent states taken is taken as
  instant (``arrival``): a state is then never judged younger than the time since it
  arrived, but a constant delay in the vehicle goes unseen. A clock answer is judged by
  the states taken: one by which the fastest of them arrived more than ``ahead_s`` before
  it was valid, or more than ``late_s`` after, is in another time base than the stamps,
  refused (``disagreement``).
* :class:`StateInput` — the newest usable state. A message is *new* when its ``seq``
  moved on (or the vehicle restarted: a lower ``seq`` with a later stamp); a repeated
  one refreshes nothing. A state is *refused*, counted by reason and said in a
  ``state_refused`` alarm (once a run of one reason), when it cannot be right: it is not
  finite, is in another frame, has an attitude that is no unit quaternion or a speed over
  ``max_speed``; when it falls outside the *window* of the states taken: not newer than
  the last one (``older``), its ``seq`` moved on faster than ``MAX_STATE_HZ`` since that
  one arrived (``seq``), stamped more than ``window_s`` ahead of the vehicle's clock as
  mapped at its arrival (``future``) or valid more than ``max_delay_s`` before it
  (``late``); or, in flight, when it has jumped: it lies farther from where the last one
  was heading (its position plus its velocity times the time between their stamps) than
  ``jump_m`` plus what ``max_accel`` could add in the time that passed (``a t^2 / 2``,
  ``t`` the stamps' span but never more than passed here between their arrivals: a
  shifted stamp buys no reach). Refused states that hold together — each arrived within
  ``limit_s`` of the one before, newer than it, with the same delay to within
  ``window_s``, within reach of it — for ``reset_s`` on this host are taken as the
  vehicle's new truth (``state_reset``): an estimator reset, a vehicle restarted on a
  clock that went back, a first state that was forged (the clock map's arrivals then
  start afresh). So no single state locks the real ones out. Freshness is judged on
  this host alone: the newest accepted state arrived at most ``limit_s`` ago. Its *age*
  (for delay compensation) is the time since it was valid, through the clock map, never
  less than the time since it arrived.
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

from .core.aesop import ControlOutput
from .core.dynamics import N_STATE
from .core.handshake import Note, NoteData
from .core.planning import PlanningModel

ClockSource = Literal["sync", "arrival"]
RefusalKind = Literal["frame", "finite", "attitude", "speed", "older", "seq", "future", "late",
                      "jump"]
QUATERNION_SLACK = 0.05  # |q| may differ from 1 by this much before the state is refused
MAX_STATE_HZ = 10_000.0  # a vehicle's seq moves on at most this fast (the simulator's top rate)
MAX_DELAY_S = 30.0  # s: a state valid longer before it arrived is refused (the bench flies 10)
_Sync = tuple[float, float, float]  # round trip, offset, answered at


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

    def __init__(self, window: int = 64, sync_max_age_s: float = 30.0, ahead_s: float = 0.5,
                 late_s: float = MAX_DELAY_S) -> None:
        self._lock = threading.Lock()
        self._syncs: deque[_Sync] = deque(maxlen=window)
        self._arrivals: deque[float] = deque(maxlen=window * 4)  # stamp - arrival
        self.sync_max_age_s, self.ahead_s, self.late_s = sync_max_age_s, ahead_s, late_s

    def sample(self, sent: float, answered: float, vehicle: float) -> None:
        """A clock query sent at ``sent`` and answered at ``answered`` (this host's clock)
        read ``vehicle`` on the vehicle's clock."""
        if not (math.isfinite(vehicle) and answered >= sent):
            return
        with self._lock:
            self._syncs.append((answered - sent, vehicle - (sent + answered) / 2, answered))

    def arrival(self, stamp: float, arrived: float) -> None:
        """A state stamped ``stamp`` (the vehicle's clock) was taken; it arrived at
        ``arrived``."""
        with self._lock:
            self._arrivals.append(stamp - arrived)

    def restart(self) -> None:
        """Forget the arrivals: they mapped an outlier's clock (a re-anchored stream)."""
        with self._lock:
            self._arrivals.clear()

    def _judged(self, now: float) -> tuple[list[_Sync], list[_Sync], float | None]:
        """The recent clock answers that agree with the states taken and those that do not,
        and the fastest arrival (None before any state: every answer agrees then)."""
        with self._lock:
            recent = [s for s in self._syncs if now - s[2] <= self.sync_max_age_s]
            fastest = max(self._arrivals) if self._arrivals else None
        if fastest is None:
            return recent, [], None
        agree = [s for s in recent if -self.ahead_s <= s[1] - fastest <= self.late_s]
        return agree, [s for s in recent if s not in agree], fastest

    def offset(self, now: float) -> tuple[float, ClockSource] | None:
        """``vehicle - local`` and where it came from; None before any sample."""
        agree, _, fastest = self._judged(now)
        if agree:
            return min(agree)[1], "sync"
        if fastest is not None:
            return fastest, "arrival"  # the fastest arrival: taken as instant
        return None

    def disagreement(self, now: float) -> float | None:
        """How far (s) the newest recent clock answer puts the vehicle's clock from what
        the states taken say, when it is refused for that; else None."""
        agree, refused, fastest = self._judged(now)
        newest = max(agree + refused, key=lambda s: s[2], default=None)
        if newest is None or fastest is None or newest in agree:
            return None
        return newest[1] - fastest

    def round_trip_s(self, now: float) -> float | None:
        """The shortest round trip of a recent clock answer in use (its half bounds the
        error)."""
        agree = self._judged(now)[0]
        return min(agree)[0] if agree else None


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
    refusals: tuple[RefusalKind, ...] = ()  # why each state refused since the last read was
    acceleration: np.ndarray | None = None  # m/s^2 realized, where the vehicle reports it

    @property
    def position(self) -> tuple[float, float, float] | None:
        if self.x is None:
            return None
        return (float(self.x[0]), float(self.x[1]), float(self.x[2]))


@dataclass(frozen=True)
class Refusal:
    """Why a state was refused: its ``kind`` (one alarm per run of one kind) and words."""

    kind: RefusalKind
    why: str


@dataclass
class _State:
    """A state as offered: taken, or refused and perhaps the newest of a run."""

    x: np.ndarray
    seq: int
    stamp: float
    arrived: float
    acceleration: np.ndarray | None = None  # as the vehicle reported it

    def newer(self, than: _State) -> bool:
        """A higher seq, or a later stamp (a restarted vehicle counts again)."""
        return self.seq > than.seq or self.stamp > than.stamp


class StateInput:
    """The newest usable vehicle state, offered each tick from the bus's slot (module
    docstring). ``max_accel`` (m/s^2) bounds how far the vehicle may stray between two
    states from where it was heading before a state counts as a jump; ``max_speed`` (m/s)
    how fast it can fly; ``window_s`` how far ahead of the vehicle's clock as mapped at its
    arrival a stamp may lie, ``max_delay_s`` how far behind (and so a clock answer from the
    states' arrivals)."""

    def __init__(self, *, limit_s: float, frame: str = "world", jump_m: float = 0.5,
                 reset_s: float = 0.5, max_accel: float = 5.0, max_speed: float = 20.0,
                 window_s: float = 0.5, max_delay_s: float = MAX_DELAY_S,
                 clock: ClockMap | None = None) -> None:
        self.limit_s, self.frame = limit_s, frame
        self.jump_m, self.reset_s, self.max_accel = jump_m, reset_s, max_accel
        self.max_speed, self.window_s, self.max_delay_s = max_speed, window_s, max_delay_s
        self.clock = clock or ClockMap(ahead_s=window_s, late_s=max_delay_s)
        self._last: _State | None = None
        self._offered: tuple[int, float] | None = None  # (seq, arrival) of the last offer
        self._candidate: _State | None = None  # the newest of a run of refused states
        self._candidate_since: float | None = None  # when the run's first arrived
        self._refusal: Refusal | None = None  # why the newest new message was refused
        self._refusals: list[RefusalKind] = []  # since the last read
        self._notes: list[Note] = []
        self._fresh: bool | None = None  # as the last read said
        self._clock_refused = False  # as the last read said
        self._newest: np.ndarray | None = None
        self.accepted = 0
        self.refused = 0

    @property
    def last(self) -> tuple[np.ndarray, float] | None:
        """The newest accepted state and its stamp."""
        return None if self._last is None else (self._last.x.copy(), self._last.stamp)

    @property
    def newest(self) -> np.ndarray | None:
        """The newest finite state in the frame and the window, accepted or not (where a new
        flight starts: a vehicle moved between flights is refused as a jump until the
        reset)."""
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
        if last is not None and (msg.seq, msg.stamp) == (last.seq, last.stamp):
            return  # a repeat: nothing new
        here = _State(state_vector(msg), msg.seq, msg.stamp, got.received_at,
                      None if msg.acceleration is None else np.array(msg.acceleration))
        why = self._check(msg, here.x)
        if why is None:
            why = self._window(here, last)
            if why is None:
                self._newest = here.x
            if why is None and last is not None and gate and not self._within(here, last):
                why = self._jumped(here, last)
            if why is not None and self._outlasts(here):
                self._reanchor(here, why)
                why = None
        if why is not None:
            self.refused += 1
            self._refusals.append(why.kind)
            if self._refusal is None or why.kind != self._refusal.kind:  # once a run
                self._notes.append(Note("state_refused", "alarm", f"vehicle state {msg.seq} "
                                        f"refused: {why.why}", {"seq": msg.seq,
                                                                "refusal": why.kind}))
            self._refusal = why
            return
        self._refusal = None
        self._accept(here)

    def _check(self, msg: VehicleState, x: np.ndarray) -> Refusal | None:
        if msg.frame != self.frame:
            return Refusal("frame", f"frame {msg.frame!r} is not the loop's {self.frame!r}")
        if not (np.all(np.isfinite(x)) and math.isfinite(msg.stamp)
                and all(math.isfinite(a) for a in msg.acceleration or ())):
            return Refusal("finite", "not finite")
        norm = math.sqrt(sum(v * v for v in msg.attitude))
        if abs(norm - 1.0) > QUATERNION_SLACK:
            return Refusal("attitude", f"the attitude is not a unit quaternion "
                                       f"(norm {norm:.3f})")
        speed = float(np.linalg.norm(x[3:6]))
        if speed > self.max_speed:
            return Refusal("speed", f"its speed, {speed:.4g} m/s, is more than a vehicle flies "
                                    f"({self.max_speed:g} m/s)")
        return None

    def _window(self, s: _State, last: _State | None) -> Refusal | None:
        """None if ``s`` is newer than the last state taken, its seq within reach of that
        one's, and its stamp at most ``window_s`` ahead of the vehicle's clock at its arrival
        and at most ``max_delay_s`` behind."""
        if last is not None:
            if not s.newer(last):
                return Refusal("older", f"it is not newer than state {last.seq}, taken before "
                                        "(its seq and its stamp)")
            most = MAX_STATE_HZ * (max(0.0, s.arrived - last.arrived) + self.window_s)
            if s.seq - last.seq > most:
                return Refusal("seq", f"its seq moved on {s.seq - last.seq} from state "
                                      f"{last.seq}'s, more than {most:.0f} in the time since")
        mapped = self.clock.offset(s.arrived)
        if mapped is None:
            return None
        delay = s.arrived + mapped[0] - s.stamp  # as the vehicle's clock is mapped
        if delay < -self.window_s:
            return Refusal("future", f"it is stamped {-delay:.4g} s ahead of the vehicle's "
                                     f"clock ({mapped[1]}) at its arrival")
        if delay > self.max_delay_s:
            return Refusal("late", f"it was valid {delay:.4g} s before its arrival by the "
                                   f"vehicle's clock ({mapped[1]})")
        return None

    def _within(self, s: _State, ref: _State) -> bool:
        """``s`` lies within reach of where ``ref`` was heading."""
        span = min(abs(s.stamp - ref.stamp), abs(s.arrived - ref.arrived))
        heading = ref.x[0:3] + ref.x[3:6] * (s.stamp - ref.stamp)
        reach = self.jump_m + 0.5 * self.max_accel * span * span
        return bool(np.linalg.norm(s.x[0:3] - heading) <= reach)

    @staticmethod
    def _moved(s: _State, ref: _State) -> float:
        return float(np.linalg.norm(s.x[0:3] - ref.x[0:3] - ref.x[3:6] * (s.stamp - ref.stamp)))

    def _jumped(self, s: _State, last: _State) -> Refusal:
        return Refusal("jump", f"it jumped {self._moved(s, last):.2f} m from where the last "
                               "accepted state was heading")

    def _outlasts(self, s: _State) -> bool:
        """Whether ``s``, refused though it could be right, continues a run of refused
        states that has held together for ``reset_s``; else it starts or continues one."""
        c = self._candidate
        if c is None or not self._follows(s, c):
            self._candidate, self._candidate_since = s, s.arrived
            return False
        self._candidate = s
        since = s.arrived if self._candidate_since is None else self._candidate_since
        return s.arrived - since >= self.reset_s

    def _follows(self, s: _State, c: _State) -> bool:
        """``s`` holds together with ``c``, the state refused before it: it arrived within
        ``limit_s`` of it, is newer, with the same delay to within ``window_s``, its seq
        and its position within reach."""
        gap = s.arrived - c.arrived
        return (0.0 <= gap <= self.limit_s and s.newer(c)
                and abs((s.stamp - c.stamp) - gap) <= self.window_s
                and s.seq - c.seq <= MAX_STATE_HZ * (gap + self.window_s)
                and self._within(s, c))

    def _reanchor(self, s: _State, why: Refusal) -> None:
        """Take ``s``, the newest of a run of refused states that has held together."""
        since = s.arrived if self._candidate_since is None else self._candidate_since
        held, last = s.arrived - since, self._last
        data: NoteData = {"seq": s.seq, "refusal": why.kind}
        if why.kind == "jump" and last is not None:
            moved = self._moved(s, last)
            data["moved_m"] = round(moved, 3)
            what = f"the vehicle's estimate moved {moved:.2f} m and has held there"
        else:  # the last state taken, or the clock map, was the outlier
            self.clock.restart()
            what = f"its states were refused ({why.why}) and have held together"
        self._notes.append(Note("state_reset", "alarm", f"vehicle state {s.seq} taken as its "
                                f"new state: {what} for {held:.2f} s", data))
        self._newest = s.x

    def _accept(self, state: _State) -> None:
        self._last = state
        self._candidate = self._candidate_since = None
        self.accepted += 1
        self.clock.arrival(state.stamp, state.arrived)

    def read(self, now: float) -> StateReading:
        """What the tick at ``now`` (this host's clock) sees."""
        last = self._last
        notes, self._notes = self._notes, []
        refusals, self._refusals = tuple(self._refusals), []
        mapped = self.clock.offset(now)
        if last is None:
            fresh, arrival_age, age, source = False, None, None, None
        else:
            arrival_age = max(0.0, now - last.arrived)
            fresh = arrival_age <= self.limit_s
            source = None if mapped is None else mapped[1]
            age = arrival_age if mapped is None else max(arrival_age,
                                                         now - (last.stamp - mapped[0]))
        notes.extend(self._clock_notes(now, mapped))
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
                            tuple(notes), refusals,
                            None if last is None or last.acceleration is None
                            else last.acceleration.copy())

    def _clock_notes(self, now: float, mapped: tuple[float, ClockSource] | None
                     ) -> list[Note]:
        """A ``clock_refused`` alarm when the vehicle's newest clock answer is refused;
        ``clock_agrees`` when its answers are in use again."""
        off = self.clock.disagreement(now)
        if off is not None and not self._clock_refused:
            self._clock_refused = True
            return [Note("clock_refused", "alarm", f"the vehicle's clock answers are {off:+.4g} s"
                         " off the clock its states are stamped on (another time base?): "
                         "refused, its clock mapped by the states' arrivals instead (a "
                         "constant delay goes uncompensated)", {"off_s": round(off, 3)})]
        if off is None and self._clock_refused and mapped is not None and mapped[1] == "sync":
            self._clock_refused = False
            return [Note("clock_agrees", "info", "the vehicle's clock answers agree with its "
                         "states again: in use")]
        return []


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
