"""The reasoner on the bus: requests in, decisions out, each by its deadline.

The bus side is the deadline keeper (:mod:`.keeper`), a process this worker starts and
watches: it subscribes ``aesop/*/reasoner/request``, stamps each request's arrival (the
deadline counts from there), arms the timeout fallback and hands the request over a pipe
to this worker, which asks the decider and hands the decision back. The keeper publishes
on ``aesop/{robot}/reasoner/decision`` the first of that decision and the fallback at the
deadline, so a decision leaves by K whatever this process is doing (a collection, a
loaded loop). A keeper that dies is started again after ``RESTART_S`` (doubling, up to
``MAX_RESTART_S``, while none gets as far as listening).

A request over the limits that HTTP applies (:func:`.limits.check_request`: the
observation's length, the number of options, a finite deadline no longer than
``max_deadline_s``) is dropped by the keeper: no decision is published for it, rather
than a fallback decision. The control loop takes a missing decision as silence and
commits to its own fallback at K, so dropping is safe; answering is not: the controller
keeps only the newest decision on the robot's topic, so an answer to a bad request (from
a misconfigured or hostile publisher) could displace the answer to the robot's real
question before it is read. Every drop is counted in
``aesop_reasoner_bus_rejected_total{field}`` and logged here, at most one line per field
per 10 s, which says how many drops it covers.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import time
from collections import Counter
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from shared import topics
from shared.bus import Received
from shared.messages import ReasonerRequest

from . import keeper
from .deciding import Decider
from .keeper import Answer, Left, Listening, Refused, Report, Undecodable
from .settings import ReasonerSettings

log = logging.getLogger(__name__)

LOG_INTERVAL_S = 10.0  # at most one line per field this often about dropped requests
RESTART_S = 1.0  # a keeper that died is started again after this, doubled while none
MAX_RESTART_S = 30.0  # listens (a bad Zenoh config fails every start), up to this
STOP_S = 5.0  # how long a stopping keeper may take before it is killed


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
        self._conn: Connection | None = None
        self._process: Any = None
        self._stopping = asyncio.Event()
        self._listening = False
        self._gone: asyncio.Event | None = None  # set once the keeper's last report is handled
        self.keepers_started = 0

    @classmethod
    def factory(cls, settings: ReasonerSettings) -> Callable[[Decider, Any], ReasonerWorker]:
        def make(decider: Decider, metrics: Any) -> ReasonerWorker:
            return cls(decider, settings, metrics=metrics)

        return make

    @property
    def listening(self) -> bool:
        """Whether a keeper is on the bus, answering requests."""
        return self._listening and self._process is not None and self._process.is_alive()

    async def run(self) -> None:
        """Keep a keeper running until :meth:`stop`."""
        loop = asyncio.get_running_loop()
        pause = RESTART_S
        while not self._stopping.is_set():
            gone = asyncio.Event()
            try:
                process, (reports, answers) = await asyncio.to_thread(self._start_keeper)
            except Exception:
                log.exception("starting the deadline keeper failed: requests go unanswered "
                              "(the robots' own fallback at K); trying again in %g s", pause)
                await self._pause(pause)
                pause = min(2 * pause, MAX_RESTART_S)
                continue
            self._process, self._conn, self._gone = process, answers, gone
            # read on the loop itself: a reader thread would wait for the GIL to hand over
            loop.add_reader(reports.fileno(), self._drain, loop, reports, gone)
            waits = {asyncio.ensure_future(self._stopping.wait()),
                     asyncio.ensure_future(gone.wait())}
            _, pending = await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
            for waiting in pending:
                waiting.cancel()
            listened, self._listening = self._listening, False
            if self._stopping.is_set():
                return
            pause = RESTART_S if listened else pause
            await asyncio.to_thread(process.join, STOP_S)
            log.error("the deadline keeper exited (code %s%s): requests go unanswered (the "
                      "robots' own fallback at K) until another starts in %g s",
                      process.exitcode, "" if listened else ", before it listened", pause)
            self._conn = None
            answers.close()
            await self._pause(pause)
            pause = min(2 * pause, MAX_RESTART_S)

    async def _pause(self, seconds: float) -> None:
        """``seconds``, or less if stopped meanwhile."""
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._stopping.wait(), seconds)

    def _start_keeper(self) -> tuple[Any, tuple[Connection, Connection]]:
        """The keeper's process and this side's (reports in, answers out) ends of two
        one-way pipes: closing the answers' end is what stops the keeper (a closed end
        wakes its reader; one closed under a blocked reader of its own would not)."""
        context = multiprocessing.get_context("spawn")  # never fork Zenoh's threads
        reports, their_reports = context.Pipe(duplex=False)
        their_answers, answers = context.Pipe(duplex=False)
        process = context.Process(
            target=keeper.main, name="aesop-reasoner-keeper", daemon=True,
            args=(self.settings, their_answers, their_reports, self.decider.policy,
                  self.decider.config.margin_s))
        process.start()
        their_answers.close()
        their_reports.close()
        self.keepers_started += 1
        return process, (reports, answers)

    def _drain(self, loop: asyncio.AbstractEventLoop, reports: Connection,
               gone: asyncio.Event) -> None:
        """The keeper's reports waiting in the pipe (on the loop); at its end, ``gone``."""
        try:
            while reports.poll():
                self.report(reports.recv())
        except (EOFError, OSError):
            loop.remove_reader(reports.fileno())
            reports.close()
            gone.set()

    def report(self, item: Report) -> None:
        """One report from the keeper (on the loop)."""
        if isinstance(item, Received):
            task = asyncio.create_task(self._decide(item))
            self._tasks.add(task)
            task.add_done_callback(self._done)
        elif isinstance(item, Left):
            if self.metrics is not None:
                self.metrics.observe(item.decision)
        elif isinstance(item, Refused):
            self._dropped(item)
        elif isinstance(item, Undecodable):
            if self.metrics is not None:
                self.metrics.reject("message")
        elif isinstance(item, Listening):
            self._listening = True
            log.info("the deadline keeper is listening (pid %s, priority: %s)",
                     self._process.pid if self._process else "?", item.priority)
            if item.priority == "normal":
                log.warning("the deadline keeper runs at normal priority (no CAP_SYS_NICE): "
                            "on a busy machine decisions may leave late")

    async def _decide(self, received: Received[ReasonerRequest]) -> None:
        request = received.message
        async with self._slots:
            decision = await self.decider.decide(request, received_at=received.received_at)
        conn = self._conn
        if conn is None:
            return
        # a keeper that is gone answered nothing: the robot falls back at K
        with contextlib.suppress(OSError, ValueError):
            conn.send(Answer(topics.robot_of(received.key), decision))

    def _done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("deciding a request failed", exc_info=task.exception())

    def _dropped(self, refused: Refused) -> None:
        """Count a dropped request; log at most once per field per ``LOG_INTERVAL_S``."""
        field = refused.field
        if self.metrics is not None:
            self.metrics.reject(field)
        now = self._clock()
        self._unlogged[field] += 1
        last = self._logged_at.get(field)
        if last is not None and now - last < LOG_INTERVAL_S:
            return
        self._logged_at[field] = now
        count = self._unlogged.pop(field)
        log.warning("dropped %d reasoner request(s) over the %s limit, unanswered "
                    "(latest on %s: %s)", count, field, refused.key, refused.problem)

    async def stop(self) -> None:
        """Let the decisions under way finish, then close the pipe: the keeper exits."""
        self._stopping.set()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        conn, process = self._conn, self._process
        self._conn = None
        if conn is not None:
            conn.close()
        if process is not None:
            await asyncio.to_thread(process.join, STOP_S)
            if process.is_alive():
                log.warning("the deadline keeper did not stop in %g s: killed", STOP_S)
                process.kill()
                await asyncio.to_thread(process.join, STOP_S)
        if self._gone is not None:  # its reports, down to the last, have been handled
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._gone.wait(), STOP_S)
