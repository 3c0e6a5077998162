"""The reasoner on the bus: requests in, decisions out, each by its deadline.

The bus side is the deadline keeper (:mod:`.keeper`), a process this worker starts and
watches: it subscribes ``aesop/*/reasoner/request``, stamps each request's arrival (the
deadline counts from there), arms the timeout fallback and hands the request over a pipe
to this worker, which asks the decider and hands the decision back. The keeper publishes
on ``aesop/{robot}/reasoner/decision`` the first of that decision and the fallback at the
deadline, so a decision leaves by K whatever this process is doing (a collection, a
loaded loop).

A keeper is lost when it exits (killed, crashed) or when its heartbeat stops for
``keeper.STALL_S`` (``SIGSTOP``, a starved core): a watchdog thread here reads the beat
from shared memory, kills a stalled keeper (nothing it holds may leave late when it runs
again) and hands its requests to the standby (:mod:`.standby`): this process's own Zenoh
session, which hears every request too and sends the decisions of a lost keeper's
requests (the answers it held at once, the fallbacks at their deadlines) and of every
request until another keeper listens. Another is started at once (after ``RESTART_S``,
doubling up to ``MAX_RESTART_S``, while none gets as far as listening). Each request is
decided once, whichever of the two told of it first, and the decision handed to both.

A request over the limits that HTTP applies (:func:`.limits.check_request`: the
observation's length, the number of options, a finite deadline no longer than
``max_deadline_s``) is dropped by the keeper: no decision is published for it, rather
than a fallback decision. The control loop takes a missing decision as silence and
commits to its own fallback at K, so dropping is safe; answering is not: the controller
keeps only the newest decision on the robot's topic, so an answer to a bad request (from
a misconfigured or hostile publisher) could displace the answer to the robot's real
question before it is read. Every drop is counted in
``aesop_reasoner_bus_rejected_total{field}`` and logged here, at most one line per field
per 10 s, which says how many drops it covers. For the same reason a decision that would
leave after its deadline is dropped (``aesop_reasoner_dropped_late_total{sender}``,
logged likewise).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import threading
import time
from collections import Counter
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.connection import wait as ready_of
from typing import Any

from shared import topics
from shared.bus import Bus, Received
from shared.messages import ReasonerDecision, ReasonerRequest

from . import keeper
from .deciding import Decider
from .keeper import (
    STALL_S,
    Answer,
    DeadlineTimer,
    Late,
    Left,
    Listening,
    Refused,
    Report,
    Undecodable,
)
from .settings import ReasonerSettings
from .standby import Standby, Watched, open_bus, standby_config

log = logging.getLogger(__name__)

LOG_INTERVAL_S = 10.0  # at most one line per field this often about dropped requests
RESTART_S = 1.0  # a keeper that died before it listened is started again after this,
MAX_RESTART_S = 30.0  # doubled while none listens (a bad Zenoh config fails every start)
STOP_S = 5.0  # how long a stopping keeper may take before it is killed
WATCH_S = 0.02  # the watchdog looks at the keeper this often
FORGET_S = 5.0  # a decision is kept this long past its deadline, for a late report of it
STANDBY_RETRY_S = 5.0  # the standby's session is tried again this long after a failure

Ident = tuple[str, str]  # (robot, request_id)


class ReasonerWorker:
    """See the module docstring. ``settings`` gives the keeper its bus and the limits;
    ``clock`` times the log lines about dropped requests."""

    def __init__(self, decider: Decider, settings: ReasonerSettings, *, metrics: Any = None,
                 max_in_flight: int = 64, clock: Callable[[], float] = time.monotonic) -> None:
        self.decider = decider
        self.settings = settings
        self.metrics = metrics
        self._clock = clock
        self._logged_at: dict[str, float] = {}
        self._unlogged: Counter[str] = Counter()
        self._slots = asyncio.Semaphore(max_in_flight)
        self._tasks: set[asyncio.Task[None]] = set()
        self._decided: dict[Ident, ReasonerDecision | None] = {}  # None: being decided
        self._conn: Connection | None = None
        self._keeper: Watched | None = None
        self._stopping = asyncio.Event()
        self._closing = threading.Event()  # from here a keeper's exit is no loss
        self._lose_lock = threading.Lock()
        self._gone: asyncio.Event | None = None  # set once the keeper's last report is handled
        self._loop: asyncio.AbstractEventLoop | None = None
        self._standby: Standby | None = None
        self._standby_bus: Bus | None = None
        self._standby_task: asyncio.Task[None] | None = None
        self.keepers_started = 0

    @classmethod
    def factory(cls, settings: ReasonerSettings) -> Callable[[Decider, Any], ReasonerWorker]:
        def make(decider: Decider, metrics: Any) -> ReasonerWorker:
            return cls(decider, settings, metrics=metrics)

        return make

    @property
    def listening(self) -> bool:
        """Whether a keeper is on the bus, answering requests alone: it has listened for
        ``SETTLE_S`` (before, the standby sends a request's decision too)."""
        watched = self._keeper
        return (watched is not None and watched.settled(time.monotonic())
                and watched.process.is_alive())

    async def run(self) -> None:
        """Keep a keeper running, the standby beside it and the watchdog on it, until
        :meth:`stop`."""
        loop = self._loop = asyncio.get_running_loop()
        self._standby_task = asyncio.create_task(self._stand_by())
        threading.Thread(target=self._watch, name="aesop-keeper-watchdog", daemon=True).start()
        pause = RESTART_S
        while not self._stopping.is_set():
            gone = asyncio.Event()
            try:
                watched, (reports, answers) = await asyncio.to_thread(self._start_keeper)
            except Exception:
                log.exception("starting the deadline keeper failed: the service sends the "
                              "decisions itself; trying again in %g s", pause)
                await self._pause(pause)
                pause = min(2 * pause, MAX_RESTART_S)
                continue
            self._keeper, self._conn, self._gone = watched, answers, gone
            # read on the loop itself: a reader thread would wait for the GIL to hand over
            loop.add_reader(reports.fileno(), self._drain, loop, reports, gone, watched)
            waits = {asyncio.ensure_future(self._stopping.wait()),
                     asyncio.ensure_future(gone.wait())}
            _, pending = await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
            for waiting in pending:
                waiting.cancel()
            if self._stopping.is_set():
                return
            process = watched.process
            await asyncio.to_thread(process.join, STOP_S)
            listened = watched.listening_since is not None
            self._lose(watched, "exited", f"code {process.exitcode}"
                       + ("" if listened else ", before it listened"))
            self._conn = None
            answers.close()
            if listened:  # another at once: the standby sends meanwhile
                pause = RESTART_S
            else:
                await self._pause(pause)
                pause = min(2 * pause, MAX_RESTART_S)

    async def _pause(self, seconds: float) -> None:
        """``seconds``, or less if stopped meanwhile."""
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._stopping.wait(), seconds)

    def _start_keeper(self) -> tuple[Watched, tuple[Connection, Connection]]:
        """The keeper's process and this side's (reports in, answers out) ends of two
        one-way pipes: closing the answers' end is what stops the keeper (a closed end
        wakes its reader; one closed under a blocked reader of its own would not)."""
        context = multiprocessing.get_context("spawn")  # never fork Zenoh's threads
        reports, their_reports = context.Pipe(duplex=False)
        their_answers, answers = context.Pipe(duplex=False)
        pulse = context.RawValue("d", 0.0)
        process = context.Process(
            target=keeper.main, name="aesop-reasoner-keeper", daemon=True,
            args=(self.settings, their_answers, their_reports, self.decider.policy,
                  self.decider.config.margin_s, pulse))
        process.start()
        their_answers.close()
        their_reports.close()
        self.keepers_started += 1
        if self.metrics is not None:
            self.metrics.keeper_started()
        return Watched(process, pulse), (reports, answers)

    # ----------------------------------------------------------------- the watchdog

    def _watch(self) -> None:
        """The watchdog's thread: a keeper that exited, or whose heartbeat stopped for
        ``STALL_S`` (killed first), is lost."""
        last = time.monotonic()
        grace_until = 0.0
        while not self._closing.wait(WATCH_S):
            now = time.monotonic()
            if now - last > STALL_S / 2:  # this process was held itself (a frozen
                grace_until = now + STALL_S  # container): judge no heartbeat missed meanwhile
            last = now
            watched = self._keeper
            if watched is None or watched.lost is not None:
                continue
            if ready_of([watched.process.sentinel], 0):
                self._lose(watched, "exited", f"code {watched.process.exitcode}")
                continue
            age = watched.beat_age(now)
            if age is not None and age > STALL_S and now >= grace_until:
                watched.process.kill()  # a stopped one too: nothing it holds leaves late
                self._lose(watched, "stalled", f"no heartbeat for {age:.2f} s; killed")

    def _lose(self, watched: Watched, why: str, detail: str) -> None:
        """``watched`` is lost (``why``: ``exited`` or ``stalled``): from now on the standby
        sends its requests' decisions (on the watchdog's thread or the loop)."""
        with self._lose_lock:
            if watched.lost is not None or self._closing.is_set():
                return
            watched.lost = why
        standby = self._standby
        sent = standby.take_over(watched) if standby is not None else 0
        if self.metrics is not None:
            self.metrics.keeper_lost(why)
        if standby is None:
            log.error("the deadline keeper %s (%s): requests go unanswered (the robots' own "
                      "fallback at K) until another listens: the service's own Zenoh session "
                      "is not open", why, detail)
        else:
            log.error("the deadline keeper %s (%s): the service sends the decisions itself "
                      "until another listens (%d held answer(s) sent at once)", why, detail,
                      sent)

    # ----------------------------------------------------------------- the standby

    async def _stand_by(self) -> None:
        """Open the standby's session (again after a failure) and stand by on it."""
        while not self._closing.is_set():
            try:
                opened = await asyncio.to_thread(self._open_standby)
            except Exception as exc:
                log.warning("the reasoner's own Zenoh session did not open (%s): should the "
                            "deadline keeper be lost, requests go unanswered (the robots' own "
                            "fallback at K); trying again in %g s", exc, STANDBY_RETRY_S)
                await self._pause(STANDBY_RETRY_S)
                continue
            if opened:
                log.info("standing by on a Zenoh session of the service's own, to send the "
                         "decisions a lost deadline keeper cannot")
            return

    def _open_standby(self) -> bool:
        """The standby's session and subscriber (in a thread: opening waits for Zenoh);
        whether it stands by (not when the worker stopped meanwhile, nor where it would
        reach nobody)."""
        conf = standby_config(self.settings)
        if conf is None:
            log.warning("the reasoner connects to no Zenoh endpoint (the robots connect to "
                        "it): should the deadline keeper be lost, requests go unanswered "
                        "until another listens (the robots' own fallback at K)")
            return False
        bus = open_bus(conf)
        if self._closing.is_set():
            bus.close()
            return False
        standby = Standby(self.settings, self.decider.policy, self.decider.config.margin_s,
                          bus.publish, self._tell_standby, DeadlineTimer("aesop-standby"),
                          lambda: self._keeper)
        self._standby, self._standby_bus = standby, bus
        bus.each(topics.reasoner_request(topics.ANY_ROBOT), ReasonerRequest, standby.arrived,
                 on_error=standby.undecodable)
        return True

    def _tell_standby(self, item: Report) -> None:
        """The standby's reports (on a Zenoh or timer thread) to the loop."""
        loop = self._loop
        if loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop has closed
                loop.call_soon_threadsafe(self._from_standby, item)

    def _from_standby(self, item: Report) -> None:
        """One report from the standby (on the loop)."""
        if isinstance(item, Received):
            self._received(item, None)
        elif isinstance(item, Left):
            if self.metrics is not None:
                self.metrics.observe(item.decision)
                self.metrics.sent_by_service.labels(item.decision.source).inc()
            count = self._once_in_a_while("sent by the service")
            if count is not None:
                log.warning("the service sent %d decision(s) itself, no deadline keeper able "
                            "to (latest: %s for %s's request %s)", count, item.decision.source,
                            item.robot, item.decision.request_id)
        elif isinstance(item, Late):
            self._late(item, "service")
        elif isinstance(item, Refused | Undecodable):
            watched = self._keeper
            if watched is None or watched.lost is not None or watched.listening_since is None:
                self.report(item)  # else the keeper counts it

    # ----------------------------------------------------------------- reports, decisions

    def _drain(self, loop: asyncio.AbstractEventLoop, reports: Connection,
               gone: asyncio.Event, watched: Watched) -> None:
        """The keeper's reports waiting in the pipe (on the loop); at its end, ``gone``."""
        try:
            while reports.poll():
                self.report(reports.recv(), watched)
        except (EOFError, OSError):
            loop.remove_reader(reports.fileno())
            reports.close()
            gone.set()

    def report(self, item: Report, watched: Watched | None = None) -> None:
        """One report from the keeper ``watched`` (on the loop)."""
        if isinstance(item, Received):
            self._received(item, watched or self._keeper)
        elif isinstance(item, Left):
            if self._standby is not None:
                self._standby.left(item.robot, item.decision.request_id)
            if self.metrics is not None:
                self.metrics.observe(item.decision)
        elif isinstance(item, Refused):
            self._dropped(item)
        elif isinstance(item, Undecodable):
            if self.metrics is not None:
                self.metrics.reject("message")
        elif isinstance(item, Late):
            self._late(item, "keeper")
        elif isinstance(item, Listening):
            watched = watched or self._keeper
            if watched is not None:
                watched.listening_since = time.monotonic()
            log.info("the deadline keeper is listening (pid %s, priority: %s)",
                     watched.process.pid if watched else "?", item.priority)
            if item.priority == "normal":
                log.warning("the deadline keeper runs at normal priority (no CAP_SYS_NICE): "
                            "on a busy machine decisions may leave late")

    def _received(self, received: Received[ReasonerRequest], watched: Watched | None) -> None:
        """A request the keeper ``watched`` (None: the standby) has armed: decided once,
        whoever told of it first; one told of it later gets the decision at once."""
        robot, request_id = topics.robot_of(received.key), received.message.request_id
        ident = (robot, request_id)
        if watched is not None and self._standby is not None:
            self._standby.cover(robot, request_id, watched,
                                until=received.received_at + received.message.deadline_s)
        if ident in self._decided:
            decision = self._decided[ident]
            if decision is not None:
                self._hand(robot, decision, keeper=watched is not None,
                           standby=watched is None)
            return
        self._decided[ident] = None
        task = asyncio.create_task(self._decide(ident, received))
        self._tasks.add(task)
        task.add_done_callback(self._done)

    async def _decide(self, ident: Ident, received: Received[ReasonerRequest]) -> None:
        request = received.message
        try:
            async with self._slots:
                decision = await self.decider.decide(request, received_at=received.received_at)
        except BaseException:
            self._decided.pop(ident, None)
            raise
        self._decided[ident] = decision
        left = received.received_at + request.deadline_s - time.monotonic()
        asyncio.get_running_loop().call_later(max(left, 0.0) + FORGET_S,
                                              self._decided.pop, ident, None)
        self._hand(ident[0], decision, keeper=True, standby=True)

    def _hand(self, robot: str, decision: ReasonerDecision, *, keeper: bool,
              standby: bool) -> None:
        """Hand ``decision`` to the keeper and/or the standby: whichever holds the request
        sends it (a keeper that is gone answered nothing: the standby has it)."""
        answer = Answer(robot, decision)
        conn = self._conn
        if keeper and conn is not None:
            with contextlib.suppress(OSError, ValueError):
                conn.send(answer)
        if standby and self._standby is not None:
            self._standby.answered(answer)

    def _done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("deciding a request failed", exc_info=task.exception())

    def _once_in_a_while(self, key: str) -> int | None:
        """How many of ``key``'s events to log now (None: not yet, at most one line per
        key per ``LOG_INTERVAL_S``)."""
        now = self._clock()
        self._unlogged[key] += 1
        last = self._logged_at.get(key)
        if last is not None and now - last < LOG_INTERVAL_S:
            return None
        self._logged_at[key] = now
        return self._unlogged.pop(key)

    def _dropped(self, refused: Refused) -> None:
        """Count a dropped request; log at most once per field per ``LOG_INTERVAL_S``."""
        field = refused.field
        if self.metrics is not None:
            self.metrics.reject(field)
        count = self._once_in_a_while(field)
        if count is not None:
            log.warning("dropped %d reasoner request(s) over the %s limit, unanswered "
                        "(latest on %s: %s)", count, field, refused.key, refused.problem)

    def _late(self, late: Late, sender: str) -> None:
        """Count a decision dropped past its deadline; log at most once per sender per
        ``LOG_INTERVAL_S``."""
        if self.metrics is not None:
            self.metrics.dropped_late.labels(sender).inc()
        count = self._once_in_a_while(f"late {sender}")
        if count is not None:
            log.warning("dropped %d decision(s) (the %s's) that would have left after their "
                        "deadline: the robot took its own fallback at K (latest: %s for %s's "
                        "request %s, %.0f ms late)", count, sender, late.decision.source,
                        late.robot, late.decision.request_id, late.late_s * 1000.0)

    async def stop(self) -> None:
        """Let the decisions under way finish, then close the pipe: the keeper exits; then
        the standby's session closes."""
        self._stopping.set()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        self._closing.set()
        conn, watched = self._conn, self._keeper
        self._conn = None
        if conn is not None:
            conn.close()
        if watched is not None:
            process = watched.process
            await asyncio.to_thread(process.join, STOP_S)
            if process.is_alive():
                log.warning("the deadline keeper did not stop in %g s: killed", STOP_S)
                process.kill()
                await asyncio.to_thread(process.join, STOP_S)
        if self._gone is not None:  # its reports, down to the last, have been handled
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._gone.wait(), STOP_S)
        if self._standby_task is not None:
            self._standby_task.cancel()
            await asyncio.gather(self._standby_task, return_exceptions=True)
        standby, bus = self._standby, self._standby_bus
        self._standby = self._standby_bus = None
        if standby is not None:
            standby.close()
        if bus is not None:
            await asyncio.to_thread(bus.close)
