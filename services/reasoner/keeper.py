"""The deadline keeper: a process of its own, the one sender of the reasoner's decisions.

Why a process: the decision must leave by K whatever the service is doing, and a thread
inside the service cannot promise that. Under CPU contention CPython's collections hold
the GIL for up to 110 ms in the service (it holds HTTP clients, streams and tasks for
32 decisions at once), and a timer thread there cannot publish meanwhile
(``aesop bench reasoner --cpu-hog 2`` missed 19 of 2000 that way). The keeper holds
almost nothing, runs its threads ahead of ordinary processes where the OS allows
(:func:`shared.realtime.urgent`), and so wakes and publishes on time.

The keeper owns the reasoner's Zenoh session and its liveliness token (announced once it
listens). For each request on ``aesop/*/reasoner/request`` it stamps the arrival, checks
the limits HTTP applies (:func:`.limits.check_request`; a request over them is dropped,
unanswered: see :mod:`.worker`), arms the timeout fallback at
``arrival + deadline_s - margin_s`` and hands the request to the service
(:class:`~shared.bus.Received`). It publishes on ``aesop/{robot}/reasoner/decision`` the
first of: the service's decision (:class:`Answer`) and the fallback at the deadline; the
other is dropped. A decision's ``latency_ms`` is stamped as it leaves: from the request's
arrival here to its publication. The service is told what left (:class:`Left`), what was
refused (:class:`Refused`) and what did not decode (:class:`Undecodable`), for its metrics
and logs.

Nothing leaves after its deadline (``arrival + deadline_s``): a decision that would (the
keeper was stopped or starved past it, and its timer fires late) is dropped and the service
told (:class:`Late`). By then the robot has committed its own fallback at K and ignores a
decision for it; sent, it could only displace the answer to the robot's next question.

The two talk over a pipe (:func:`multiprocessing.Pipe`). When the service goes, the pipe
closes and the keeper exits. Once on the bus, the keeper's timer thread, the one that
sends the fallbacks, writes a heartbeat into memory the two share every ``HEARTBEAT_S``.
The service watches it: a keeper that dies, or whose heartbeat stops for ``STALL_S``
(``SIGSTOP``, a starved core), is killed if need be and replaced, and meanwhile the
service sends the decisions itself (:mod:`.standby`, which is this module's
:class:`Keeper` on a Zenoh session of the service's own).
"""

from __future__ import annotations

import gc
import heapq
import itertools
import logging
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

from shared import topics
from shared.bus import Bus, Received
from shared.logs import configure
from shared.messages import ReasonerDecision, ReasonerRequest
from shared.realtime import Priority, urgent

from .deciding import FallbackPolicy, fallback_decision, settle, timeout_reason
from .limits import LimitError, check_request
from .settings import ReasonerSettings

log = logging.getLogger(__name__)

MAX_PENDING = 1024  # requests armed at once; more are refused (field "pending")
# one robot's requests armed at once (a loop has one out, a re-ask after a silence another):
# past it that robot's are refused, so its flood takes no other robot's place
MAX_PENDING_PER_ROBOT = 32
SWITCH_INTERVAL_S = 0.001  # a thread that wants the GIL waits at most this (default 5 ms)
HEARTBEAT_S = 0.05  # the keeper's timer thread says it runs this often (.standby.Watched)
# no heartbeat for this long: the keeper is stopped or starved, and the service takes over
# (well under any K a robot flies: the paper's is 4.3 s)
STALL_S = 0.25


# --------------------------------------------------------------------------- the pipe


@dataclass(frozen=True, slots=True)
class Answer:
    """Service -> keeper: the decision reached for ``robot``'s request."""

    robot: str
    decision: ReasonerDecision


@dataclass(frozen=True, slots=True)
class Left:
    """Keeper -> service: ``decision`` was published for ``robot``."""

    robot: str
    decision: ReasonerDecision


@dataclass(frozen=True, slots=True)
class Refused:
    """Keeper -> service: the request on ``key`` was dropped, unanswered."""

    key: str
    field: str
    problem: str


@dataclass(frozen=True, slots=True)
class Undecodable:
    """Keeper -> service: a sample on the request key was not a request."""


@dataclass(frozen=True, slots=True)
class Listening:
    """Keeper -> service: subscribed and announced; requests are answered from now on."""

    priority: Priority


@dataclass(frozen=True, slots=True)
class Late:
    """Keeper -> service: ``decision`` was not published: it would have left ``late_s``
    after its request's deadline."""

    robot: str
    decision: ReasonerDecision
    late_s: float


Report = Received[ReasonerRequest] | Left | Refused | Undecodable | Listening | Late


# --------------------------------------------------------------------------- the timer


class DeadlineTimer:
    """One thread that runs callbacks at ``time.monotonic()`` deadlines, earliest first,
    independent of any event loop. The thread asks the OS to run it ahead of every other
    thread, its process's own real-time ones included (:func:`shared.realtime.urgent`;
    ``priority`` says what it got)."""

    def __init__(self, name: str = "aesop-deadlines") -> None:
        self._name = name
        self._heap: list[tuple[float, int]] = []
        self._pending: dict[int, Callable[[], None]] = {}  # not yet run nor cancelled
        self._ready = threading.Condition()
        self._order = itertools.count()
        self._thread: threading.Thread | None = None
        self._closed = False
        self.priority: Priority | None = None  # once the thread runs

    def at(self, due: float, fn: Callable[[], None]) -> int:
        with self._ready:
            if self._thread is None:
                self._thread = threading.Thread(target=self._serve, name=self._name,
                                                daemon=True)
                self._thread.start()
            handle = next(self._order)
            self._pending[handle] = fn
            heapq.heappush(self._heap, (due, handle))
            self._ready.notify()
        return handle

    def cancel(self, handle: int) -> None:
        with self._ready:
            self._pending.pop(handle, None)

    def close(self) -> None:
        with self._ready:
            self._closed = True
            self._ready.notify()

    def _serve(self) -> None:
        self.priority = urgent(above=1)  # ahead of the process's other threads too
        while True:
            with self._ready:
                while not self._closed and (
                        not self._heap or self._heap[0][0] > time.monotonic()):
                    self._ready.wait(None if not self._heap
                                     else self._heap[0][0] - time.monotonic())
                if self._closed:
                    return
                _, handle = heapq.heappop(self._heap)
                fn = self._pending.pop(handle, None)
            if fn is not None:
                try:
                    fn()
                except Exception:
                    log.exception("a deadline callback failed")


# --------------------------------------------------------------------------- the keeper


@dataclass(slots=True)
class _Armed:
    robot: str
    received_at: float
    deadline: float  # received_at + deadline_s: nothing leaves after it
    fallback: ReasonerDecision
    handle: int
    # the standby's (.standby): the keeper that sends this one, and the service's answer
    # held meanwhile (sent at once should that keeper be lost)
    owner: Any = None
    answer: ReasonerDecision | None = None


class Keeper:
    """What the keeper does with requests and answers, apart from its process: ``publish``
    puts a decision on a key, ``tell`` hands a :data:`Report` to the service (both must
    be quick; the process queues what it tells)."""

    def __init__(self, settings: ReasonerSettings, policy: FallbackPolicy, margin_s: float,
                 publish: Callable[[str, ReasonerDecision], None],
                 tell: Callable[[Report], None], timer: DeadlineTimer, *,
                 clock: Callable[[], float] = time.monotonic,
                 max_pending: int = MAX_PENDING,
                 max_pending_per_robot: int = MAX_PENDING_PER_ROBOT) -> None:
        self._settings, self._policy, self._margin_s = settings, policy, margin_s
        self._publish, self._tell, self._timer = publish, tell, timer
        self._clock, self._max_pending = clock, max_pending
        self._max_per_robot = max_pending_per_robot
        self._lock = threading.Lock()
        self._armed: dict[tuple[str, str], _Armed] = {}
        self._per_robot: dict[str, int] = {}  # armed requests of each robot (none: absent)

    @property
    def armed(self) -> int:
        return len(self._armed)

    def undecodable(self) -> None:
        self._tell(Undecodable())

    def arrived(self, received: Received[ReasonerRequest]) -> None:
        """A request from the bus (on a Zenoh thread): arm its fallback, hand it on."""
        request = received.message
        try:
            check_request(self._settings, observation=request.observation,
                          options=request.options, deadline_s=request.deadline_s)
        except LimitError as exc:
            self._tell(Refused(received.key, exc.field, exc.problem))
            return
        robot = topics.robot_of(received.key)
        ident = (robot, request.request_id)
        fallback = fallback_decision(request, self._policy, "timeout",
                                     timeout_reason(request.deadline_s), 0.0)
        due = received.received_at + request.deadline_s - self._margin_s
        with self._lock:
            if ident in self._armed:
                return  # a repeat of a request being decided: one answer
            if self._per_robot.get(robot, 0) >= self._max_per_robot:
                refused = Refused(received.key, "pending",
                                  f"{self._max_per_robot} requests of robot {robot} are being "
                                  "decided")
            elif len(self._armed) >= self._max_pending:
                refused = Refused(received.key, "pending",
                                  f"{self._max_pending} requests are being decided")
            else:
                refused = None
                handle = self._timer.at(due, lambda: self._expire(ident))
                self._armed[ident] = _Armed(robot, received.received_at,
                                            received.received_at + request.deadline_s,
                                            fallback, handle,
                                            self._owner(ident, received.received_at))
                self._per_robot[robot] = self._per_robot.get(robot, 0) + 1
        self._tell(refused or received)

    def answered(self, answer: Answer) -> None:
        """The service's decision: published unless the fallback left first."""
        ident = (answer.robot, answer.decision.request_id)
        with self._lock:
            armed = self._armed.get(ident)
            if armed is None:
                return  # too late (the fallback left), or never armed
            if self._defers(armed):
                armed.answer = answer.decision  # another sends it
                return
            self._disarm(ident)
        self._timer.cancel(armed.handle)
        self._send(armed, answer.decision)

    def _expire(self, ident: tuple[str, str]) -> None:
        with self._lock:
            armed = self._disarm(ident)
            if armed is None or self._defers(armed):
                return
        self._send(armed, armed.answer or armed.fallback)

    def _owner(self, ident: tuple[str, str], received_at: float) -> Any:
        """Who else sends the decision for request ``ident`` that arrived at
        ``received_at`` (None: this keeper; under the lock). The keeper's own is always
        itself."""
        return None

    def _defers(self, armed: _Armed) -> bool:
        """Whether ``armed``'s decision is another's to send (under the lock)."""
        return False

    def _disarm(self, ident: tuple[str, str]) -> _Armed | None:
        """Forget ``ident``'s request (under the lock); what was armed for it, if anything."""
        armed = self._armed.pop(ident, None)
        if armed is not None:
            left = self._per_robot[armed.robot] - 1
            if left:
                self._per_robot[armed.robot] = left
            else:
                del self._per_robot[armed.robot]  # a made-up robot leaves nothing behind
        return armed

    def _send(self, armed: _Armed, decision: ReasonerDecision) -> None:
        """Publish ``decision`` stamped as it leaves, unless its deadline has passed."""
        now = self._clock()
        if now > armed.deadline:
            self._tell(Late(armed.robot, decision, now - armed.deadline))
            return
        decision = decision.model_copy(update={
            "robot": armed.robot, "stamp": time.time(),
            "latency_ms": max(0.0, (now - armed.received_at) * 1000.0)})
        try:
            self._publish(topics.reasoner_decision(armed.robot), decision)
        except Exception:
            log.exception("publishing the decision for %s failed", armed.robot)
            return
        self._tell(Left(armed.robot, decision))


# --------------------------------------------------------------------------- the process


def main(settings: ReasonerSettings, answers: Connection, reports: Connection,
         policy: FallbackPolicy, margin_s: float, pulse: Any) -> None:
    """The keeper process (started by :class:`.worker.ReasonerWorker`): until the service
    closes ``answers``, requests from the bus to ``reports`` and answers to the bus; once
    on the bus, ``time.monotonic()`` into ``pulse`` (a shared ``double``) every
    ``HEARTBEAT_S`` from the timer's thread."""
    configure(settings.log_level, settings.log_format)  # the service's format
    # a signal to the service's process group is the service's to handle: the keeper
    # stops when the service closes the pipe (or dies), not before its last decision
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    # before anything starts a thread: Zenoh's threads, the timer and the writer inherit it
    priority = urgent()
    outbox: queue.SimpleQueue[Report | None] = queue.SimpleQueue()
    writer = threading.Thread(target=_write, args=(reports, outbox), name="aesop-keeper-out",
                              daemon=True)
    writer.start()
    timer = DeadlineTimer()
    # the collection that moves what was imported out of the collector's way, before the
    # heartbeat starts (it holds the GIL for tens of ms); what the bus adds is frozen later
    settle()
    try:
        with Bus.open(settings, "reasoner", alive=False) as bus:
            _beat(timer, pulse)  # from here a stall is one: opening may wait for a router
            keeper = Keeper(settings, policy, margin_s, bus.publish, outbox.put, timer)
            bus.each(topics.reasoner_request(topics.ANY_ROBOT), ReasonerRequest,
                     keeper.arrived, on_error=keeper.undecodable)
            bus.announce()
            gc.freeze()
            outbox.put(Listening(priority))
            _read(answers, keeper)
    finally:
        timer.close()
        outbox.put(None)
        writer.join(timeout=1.0)
        reports.close()


def _beat(timer: DeadlineTimer, pulse: Any) -> None:
    """Say the timer's thread runs (now, and every ``HEARTBEAT_S`` after)."""
    now = time.monotonic()
    pulse.value = now
    timer.at(now + HEARTBEAT_S, lambda: _beat(timer, pulse))


def _read(conn: Connection, keeper: Keeper) -> None:
    while True:
        try:
            item: Any = conn.recv()
        except (EOFError, OSError):
            return  # the service is gone (or closed the pipe to stop us)
        if isinstance(item, Answer):
            keeper.answered(item)
        else:
            log.error("unexpected %s on the keeper's pipe", type(item).__name__)


def _write(conn: Connection, outbox: queue.SimpleQueue[Report | None]) -> None:
    """The only sender on ``conn``: a full pipe (a service stalled by a collection) holds
    this thread, never the timer's or Zenoh's."""
    while (item := outbox.get()) is not None:
        try:
            conn.send(item)
        except (OSError, ValueError):
            return
