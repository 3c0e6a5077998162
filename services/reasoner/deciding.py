"""The slow reasoner's decision under a deadline: always an answer by ``K``.

:class:`Decider` asks the LLM backends for y in the offered options and returns a
:class:`~shared.messages.ReasonerDecision` before ``received_at + deadline_s - margin_s``;
on the bus (:meth:`Decider.decide_and_send`) a timer thread sends the timeout fallback at
that moment if the event loop has not answered, so a loaded loop still answers by K:

- ``llm``: the first answer that parses (strictly) into an offered option wins; every
  other attempt is cancelled, and its HTTP connection closed once the decision has left.
- ``timeout``: no valid answer by the deadline; everything is cancelled.
- ``parse_error``: every attempt answered but none parsed (the reason codes of
  :mod:`services.reasoner.parsing` are in the rationale); also a task or observation
  flagged by :func:`~services.reasoner.prompts.suspicious_scene` (reason ``injection``,
  the LLM is never called) and options the prompt cannot render (reason ``invalid_request``).
- ``backend_error``: every attempt failed in the backend (kind and HTTP status in the
  rationale). With mixed failures, ``parse_error`` wins: a model did answer.

Backends after the first wait in a queue. The next one starts ``hedge_after_s`` after
the previous start (hedging, when set), or at once when every running attempt has
failed (failover). A failed attempt never ends the decision while another may still
answer before the deadline. Every non-LLM answer is :func:`fallback_choice`.
"""

from __future__ import annotations

import asyncio
import gc
import heapq
import itertools
import logging
import math
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal

from shared.messages import DecisionSource, Option, ReasonerDecision, ReasonerRequest
from shared.realtime import Priority, favoured, urgent

from .backends import BackendError, ChatBackend, Completion
from .parsing import Parsed, ParseError, parse_decision, parse_partial
from .prompts import Variant, build_messages, load_template, suspicious_scene, unusual_of

log = logging.getLogger(__name__)

FallbackKind = Literal["first_recovery", "rank"]
DEFAULT_TASK = "carry out the current mission safely"


# --------------------------------------------------------------------------- fallback


@dataclass(frozen=True)
class FallbackPolicy:
    """The programmatic choice when the LLM gives none.

    ``first_recovery``: the lowest-indexed recovery option. ``rank``: the option whose
    label (case-insensitive, surrounding whitespace ignored) has the lowest rank (lower =
    more conservative); unranked options come last; ties go to the lower index.
    """

    kind: FallbackKind = "first_recovery"
    ranks: Mapping[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.kind not in ("first_recovery", "rank"):
            raise ValueError(f"kind: must be 'first_recovery' or 'rank', got {self.kind!r}")
        for label, rank in self.ranks.items():
            if isinstance(rank, bool) or not isinstance(rank, int):
                raise ValueError(f"ranks[{label!r}]: must be an int")
        folded = {label.strip().casefold(): rank for label, rank in self.ranks.items()}
        object.__setattr__(self, "ranks", MappingProxyType(folded))


def fallback_choice(options: Sequence[Option], policy: FallbackPolicy) -> int:
    """The fallback option index: never 0 (continue) while a recovery option exists."""
    recovery = [o for o in options if o.index != 0]
    if not recovery:
        return 0
    if policy.kind == "first_recovery":
        return min(o.index for o in recovery)
    return min(recovery, key=lambda o: (_rank(o, policy), o.index)).index


def _rank(option: Option, policy: FallbackPolicy) -> float:
    return policy.ranks.get(option.label.strip().casefold(), math.inf)


# --------------------------------------------------------------------------- outcomes


@dataclass(frozen=True)
class Win:
    """A valid answer from ``backend``."""

    parsed: Parsed
    model: str
    completion: Completion


@dataclass(frozen=True)
class Failure:
    """An attempt that ended without a valid answer."""

    source: Literal["parse_error", "backend_error"]
    detail: str


@dataclass(frozen=True)
class Timeout:
    """The deadline came first; ``failures`` are the attempts that ended before it."""

    failures: tuple[Failure, ...]


Outcome = Win | Timeout | tuple[Failure, ...]


@dataclass(frozen=True)
class DeciderConfig:
    """Prompt domain and variant, hedging delay (s) and the safety margin (s) before K."""

    domain: str = "quadrotor"
    variant: Variant = "cot"
    hedge_after_s: float | None = None
    margin_s: float = 0.010  # covers the deadline thread waiting out a collection

    def __post_init__(self) -> None:
        if self.hedge_after_s is not None and self.hedge_after_s < 0:
            raise ValueError("hedge_after_s must be >= 0 or None")
        if self.margin_s < 0:
            raise ValueError("margin_s must be >= 0")
        load_template(self.domain)  # unknown domain -> ValueError now, not per request


# --------------------------------------------------------------------------- decider


class Decider:
    """Runs the backends against one deadline; see the module docstring."""

    def __init__(self, backends: Sequence[ChatBackend], config: DeciderConfig,
                 policy: FallbackPolicy = FallbackPolicy(),
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not backends:
            raise ValueError("backends: need at least one")
        self._backends = tuple(backends)
        self._config = config
        self._policy = policy
        self._clock = clock
        self._template = load_template(config.domain)
        self._closing: set[asyncio.Future[list[Win | Failure | BaseException]]] = set()
        self._timer = DeadlineTimer()

    @property
    def backends(self) -> tuple[ChatBackend, ...]:
        return self._backends

    async def aclose(self) -> None:
        """Wait for the cancelled attempts to close, then close every backend."""
        self._timer.close()
        if self._closing:
            await asyncio.gather(*self._closing, return_exceptions=True)
        for backend in self._backends:
            await backend.aclose()

    async def decide(self, request: ReasonerRequest, *,
                     received_at: float | None = None) -> ReasonerDecision:
        """y for ``request``, by ``received_at + deadline_s - margin_s`` (clock seconds)."""
        start = self._clock() if received_at is None else received_at
        deadline = start + request.deadline_s - self._config.margin_s
        flagged = suspicious_scene(task=request.observation.task,
                                   observation=request.observation.text,
                                   unusual=unusual_of(request))
        if flagged:
            return self._fallback(request, start, "parse_error",
                                  f"injection: {flagged}; LLM not asked")
        try:
            messages = self._messages(request)
        except ValueError as exc:
            return self._fallback(request, start, "parse_error", f"invalid_request: {exc}")
        offered = [o.index for o in request.options]
        outcome = await self._race(messages, offered, deadline)
        return self._decision(request, start, outcome)

    async def decide_and_send(self, request: ReasonerRequest, send: Send, *,
                              received_at: float | None = None) -> ReasonerDecision:
        """Call ``send`` exactly once, by the deadline whatever the event loop's load: with
        the decision :meth:`decide` reaches in time, or else, from the timer thread at the
        deadline, with the timeout fallback (computed without the loop). Returns what was
        sent. This is the bus's contract: a loaded loop (many answers streaming in at once)
        wakes late, a thread with its own timer does not."""
        start = self._clock() if received_at is None else received_at
        once = _Once(send)
        # the timer thread may wait up to a switch interval for the GIL: it starts that
        # much earlier than the loop's own deadline
        due = time.monotonic() + (start + request.deadline_s - self._config.margin_s
                                  - sys.getswitchinterval() - self._clock())
        why = f"no valid answer within the deadline of {request.deadline_s:g} s"
        handle = self._timer.at(due, lambda: once(self._fallback(request, start, "timeout", why)))
        try:
            decision = await self.decide(request, received_at=start)
        finally:
            self._timer.cancel(handle)
        once(decision)
        assert once.sent is not None
        return once.sent

    def _messages(self, request: ReasonerRequest) -> list[dict[str, str]]:
        return build_messages(self._template, task=request.observation.task or DEFAULT_TASK,
                              observation=request.observation.text, options=request.options,
                              variant=self._config.variant, unusual=unusual_of(request))

    # ------------------------------------------------------------------ the race

    async def _race(self, messages: list[dict[str, str]], offered: list[int],
                    deadline: float) -> Outcome:
        queue = list(self._backends)
        running: set[asyncio.Task[Win | Failure]] = set()
        failures: list[Failure] = []
        last_start = self._clock()

        def launch() -> None:
            nonlocal last_start
            backend = queue.pop(0)
            running.add(asyncio.create_task(_attempt(backend, messages, offered)))
            last_start = self._clock()

        launch()
        try:
            while True:
                now = self._clock()
                if now >= deadline:
                    return Timeout(tuple(failures))
                if not running:
                    if not queue:
                        return tuple(failures)
                    launch()
                    continue
                wake = self._next_hedge(last_start) if queue else None
                until = deadline if wake is None else min(deadline, wake)
                done, _ = await asyncio.wait(running, timeout=max(0.0, until - now),
                                             return_when=asyncio.FIRST_COMPLETED)
                for task in done:
                    running.discard(task)
                    result = task.result()
                    if isinstance(result, Win):
                        return result
                    failures.append(result)
                if queue and wake is not None and self._clock() >= wake:
                    launch()
        finally:
            self._close_later(running)

    def _close_later(self, tasks: set[asyncio.Task[Win | Failure]]) -> None:
        """Cancel the attempts still running; their HTTP responses are closed after the
        decision has left (awaiting that first made answers late under load)."""
        for task in tasks:
            task.cancel()
        if tasks:
            closing = asyncio.ensure_future(asyncio.gather(*tasks, return_exceptions=True))
            self._closing.add(closing)
            closing.add_done_callback(self._closing.discard)

    def _next_hedge(self, last_start: float) -> float | None:
        hedge = self._config.hedge_after_s
        return None if hedge is None else last_start + hedge

    # ------------------------------------------------------------------ answers

    def _decision(self, request: ReasonerRequest, start: float,
                  outcome: Outcome) -> ReasonerDecision:
        if isinstance(outcome, Win):
            return ReasonerDecision(
                robot=request.robot, request_id=request.request_id,
                choice=outcome.parsed.choice, source="llm",
                rationale=outcome.parsed.rationale, latency_ms=self._latency_ms(start),
                model=outcome.model)
        if isinstance(outcome, Timeout):
            seen = _describe(outcome.failures)
            return self._fallback(request, start, "timeout",
                                  f"no valid answer within the deadline of "
                                  f"{request.deadline_s:g} s" + (f" ({seen})" if seen else ""))
        source: DecisionSource = (
            "parse_error" if any(f.source == "parse_error" for f in outcome) else "backend_error")
        return self._fallback(request, start, source, _describe(outcome))

    def _fallback(self, request: ReasonerRequest, start: float, source: DecisionSource,
                  why: str) -> ReasonerDecision:
        choice = fallback_choice(request.options, self._policy)
        return ReasonerDecision(
            robot=request.robot, request_id=request.request_id, choice=choice, source=source,
            rationale=f"{source}: {why}; fallback option {choice} ({self._policy.kind})",
            latency_ms=self._latency_ms(start), model="")

    def _latency_ms(self, start: float) -> float:
        return max(0.0, (self._clock() - start) * 1000.0)


async def _attempt(backend: ChatBackend, messages: list[dict[str, str]], offered: list[int]
                   ) -> Win | Failure:
    """One backend's answer, parsed; errors become a :class:`Failure` (never raised). The
    scene was checked for injection once, before any backend was asked: each streamed
    chunk is only parsed, not scanned again."""

    def stop_when(text: str) -> bool:
        return parse_partial(text, offered) is not None

    try:
        completion = await backend.complete(messages, stop_when=stop_when, answers=offered)
    except BackendError as exc:
        status = f" {exc.status}" if exc.status is not None else ""
        return Failure("backend_error", f"{backend.name}: {exc.kind}{status}")
    try:
        parsed = parse_decision(completion.text, offered)
    except ParseError as exc:
        return Failure("parse_error", f"{backend.name}: {exc.reason} ({exc.detail})")
    return Win(parsed=parsed, model=backend.model, completion=completion)


Send = Callable[[ReasonerDecision], None]
SWITCH_INTERVAL_S = 0.001  # the GIL hand-over a deadline process asks for


def keep_deadlines(process_switch_interval_s: float = SWITCH_INTERVAL_S) -> None:
    """Tune this process for the deadline thread (call once, from the entry point, before
    other threads start): a thread that wants the GIL waits at most
    ``process_switch_interval_s`` for it (Python's default is 5 ms), and the process's
    threads get a larger share of a busy machine's cores where allowed
    (:func:`shared.realtime.favoured`), so the one holding the GIL is not kept from
    handing it over. See also :func:`settle`."""
    sys.setswitchinterval(process_switch_interval_s)
    favoured()


def settle() -> None:
    """Once started: move the objects alive now (models, clients, schemas) out of the
    garbage collector's generations. Its full collections hold the GIL, and the timer
    thread with it, for as long as they walk every live object (18 ms were measured in
    the bench before; the deadline thread cannot run during one)."""
    gc.collect()
    gc.freeze()


class _Once:
    """``send`` for the first decision offered, from whichever thread; the rest dropped."""

    def __init__(self, send: Send) -> None:
        self._send, self._lock = send, threading.Lock()
        self.sent: ReasonerDecision | None = None

    def __call__(self, decision: ReasonerDecision) -> None:
        with self._lock:
            if self.sent is not None:
                return
            self.sent = decision
        self._send(decision)


class DeadlineTimer:
    """One thread that runs callbacks at ``time.monotonic()`` deadlines, earliest first,
    independent of any event loop (it needs only the GIL, which a busy thread hands over
    every ``sys.getswitchinterval()``). The thread asks the OS to run it ahead of other
    processes (:func:`shared.realtime.urgent`; ``priority`` says what it got), so a busy
    machine does not make it late."""

    def __init__(self) -> None:
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
                self._thread = threading.Thread(target=self._serve, name="aesop-deadlines",
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
        self.priority = urgent()
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


def _describe(failures: Sequence[Failure]) -> str:
    return "; ".join(f"{f.source} {f.detail}" for f in failures)
