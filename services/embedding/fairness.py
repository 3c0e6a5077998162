"""One robot cannot starve another: observations wait per robot and are served in turn.

The detector's bus worker used to put every robot's observations in one drop-oldest
queue, so a robot flooding its own key filled it and the others' observations waited
behind the flood or were dropped (issue 26: robot0 got 15 of 150 verdicts while robot1
published at 2 kHz). Here each robot has

* a **rate**: a token bucket of ``rate_hz`` observations per second (a burst of one
  second's worth); past it an observation is refused before it is even decoded;
* a **queue** of at most ``depth`` observations; a full queue drops its oldest (the
  newest scene matters most to a control loop);
* at most ``per_robot`` observations **being scored** at once: one by default.

:meth:`FairInbox.take` hands out the next observation round-robin over the robots
that have one waiting and a free slot, so a robot's wait for a verdict does not grow
with another robot's load. What is being scored at once is what the embedding batches
are made of (the service's micro-batcher puts every observation that arrives while a
batch is embedded into the next one), so ``per_robot`` is also each robot's share of
every batch. With one, an observation waits for the batch being embedded when it is
taken, which holds at most one observation of each other robot, and is embedded in the
next, beside at most one of each other robot's again (none of a robot whose one was in
the batch before: its next is taken only once that one is done). Issue 43, finding 10:
with 4 a robot flooding distinct texts (which the vector memo cannot make free) had 4
in those batches, and another robot's verdicts waited for all of them (p50 5-7 ms ->
156-178 ms; ``aesop bench fairness``). Every refusal is counted per robot and reason
(``rate``, ``full``; and ``robots``, counted under :data:`OTHER`: past ``max_robots``
robots tracked, the least recently seen idle one is forgotten to make room, or the
newcomer refused if none is idle), so the counters, and the metrics' labels, stay
bounded whatever robot ids arrive.

Pure and thread-safe (one lock; the bus worker calls :meth:`admit` on a Zenoh thread,
the rest on its event loop); the clock is injectable.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Generic, Literal, TypeVar

T = TypeVar("T")
Reason = Literal["rate", "full", "robots"]
DEPTH = 32  # observations waiting per robot
PER_ROBOT = 1  # observations of one robot being scored at once: its share of a batch
OTHER = "(other)"  # the robot a refused newcomer is counted under


@dataclass
class _Robot(Generic[T]):
    tokens: float
    stamp: float
    queue: deque[T] = field(default_factory=deque)
    scoring: int = 0

    @property
    def idle(self) -> bool:
        return not self.queue and self.scoring == 0


class FairInbox(Generic[T]):
    def __init__(self, *, rate_hz: float, max_robots: int, depth: int = DEPTH,
                 per_robot: int = PER_ROBOT, clock: Callable[[], float] = time.monotonic
                 ) -> None:
        if rate_hz <= 0 or max_robots < 1 or depth < 1 or per_robot < 1:
            raise ValueError("rate_hz, max_robots, depth and per_robot must be positive")
        self.rate_hz, self.max_robots = rate_hz, max_robots
        self.depth, self.per_robot, self.clock = depth, per_robot, clock
        self.burst = max(1.0, rate_hz)  # one second's worth
        self.dropped: Counter[tuple[str, Reason]] = Counter()
        self._robots: OrderedDict[str, _Robot[T]] = OrderedDict()  # least recently seen first
        self._turn: deque[str] = deque()  # robots with an observation waiting, in turn
        self._lock = threading.Lock()

    def admit(self, robot: str) -> Reason | None:
        """Whether ``robot`` may send one more observation now (None), or why not; the
        refusal is counted. Call before decoding it."""
        with self._lock:
            now = self.clock()
            state = self._robots.get(robot)
            if state is None:
                if not self._make_room():
                    self.dropped[OTHER, "robots"] += 1
                    return "robots"
                state = self._robots[robot] = _Robot(self.burst, now)
            self._robots.move_to_end(robot)
            state.tokens = min(self.burst, state.tokens + (now - state.stamp) * self.rate_hz)
            state.stamp = now
            if state.tokens < 1.0:
                self.dropped[robot, "rate"] += 1
                return "rate"
            state.tokens -= 1.0
            return None

    def put(self, robot: str, item: T) -> bool:
        """Queue an admitted observation; False when the robot's queue was full and its
        oldest was dropped for it (counted)."""
        with self._lock:
            state = self._robots.get(robot)
            if state is None:  # forgotten between admit and put: as a newcomer
                if not self._make_room():
                    self.dropped[OTHER, "robots"] += 1
                    return False
                state = self._robots[robot] = _Robot(self.burst - 1.0, self.clock())
            kept = len(state.queue) < self.depth
            if not kept:
                state.queue.popleft()
                self.dropped[robot, "full"] += 1
            state.queue.append(item)
            if robot not in self._turn and state.scoring < self.per_robot:
                self._turn.append(robot)
            return kept

    def take(self) -> tuple[str, T] | None:
        """The next observation to score, round-robin over the robots that have one
        waiting and a free slot; the robot's slot is taken until :meth:`done`."""
        with self._lock:
            while self._turn:
                robot = self._turn.popleft()
                state = self._robots.get(robot)
                if state is None or not state.queue or state.scoring >= self.per_robot:
                    continue
                state.scoring += 1
                item = state.queue.popleft()
                if state.queue and state.scoring < self.per_robot:
                    self._turn.append(robot)  # its next one waits for the others' turns
                return robot, item
            return None

    def done(self, robot: str) -> None:
        """An observation of ``robot`` was scored (or failed): its slot is free."""
        with self._lock:
            state = self._robots.get(robot)
            if state is None:
                return
            state.scoring = max(0, state.scoring - 1)
            if state.queue and robot not in self._turn:
                self._turn.append(robot)

    def counts(self) -> dict[tuple[str, Reason], int]:
        """The refusals so far, per robot and reason (of the robots still tracked)."""
        with self._lock:
            return dict(self.dropped)

    def _make_room(self) -> bool:
        """Room for one more robot: forget the least recently seen idle one if full."""
        if len(self._robots) < self.max_robots:
            return True
        idle = next((r for r, s in self._robots.items() if s.idle), None)
        if idle is None:
            return False
        del self._robots[idle]
        for key in [k for k in self.dropped if k[0] == idle]:
            del self.dropped[key]
        return True


class DropReports:
    """Which refusals to say, and when: each robot whose observations were refused since
    its last report gets one more, at most every ``every_s`` (pure; the clock is handed
    in)."""

    def __init__(self, every_s: float = 10.0) -> None:
        self.every_s = every_s
        self._said: dict[tuple[str, Reason], int] = {}  # counts as of each robot's report
        self._at: dict[str, float] = {}  # when each robot was last reported

    def due(self, counts: dict[tuple[str, Reason], int], now: float
            ) -> dict[str, dict[Reason, int]]:
        """The new refusals to report now, per robot and reason."""
        self._said = {k: v for k, v in self._said.items() if k in counts}
        self._at = {r: t for r, t in self._at.items() if now - t < self.every_s}
        new: dict[str, dict[Reason, int]] = {}
        for (robot, reason), n in counts.items():
            if n > self._said.get((robot, reason), 0) and robot not in self._at:
                new.setdefault(robot, {})[reason] = n - self._said.get((robot, reason), 0)
        for robot, reasons in new.items():
            self._at[robot] = now
            for reason in reasons:
                self._said[robot, reason] = counts[robot, reason]
        return new
