"""The slow reasoner's decision under a deadline: always an answer by ``K``.

:class:`Decider` asks the LLM backends for y in the offered options and returns a
:class:`~shared.messages.ReasonerDecision` before ``received_at + deadline_s - margin_s``;
on the bus the deadline keeper (:mod:`.keeper`, a process of its own) sends the timeout
fallback at that moment if this decision has not reached it, so a loaded process still
answers by K:

- ``llm``: the first answer that parses (strictly) into an offered option wins; every
  other attempt is cancelled, and its HTTP connection closed once the decision has left.
- ``timeout``: no valid answer by the deadline; everything is cancelled.
- ``parse_error``: every attempt answered but none parsed (the reason codes of
  :mod:`services.reasoner.parsing` are in the rationale).
- ``refused``: no model was asked: a task or observation flagged by
  :func:`~services.reasoner.prompts.suspicious_scene` (reason ``injection``), or options
  the prompt cannot render (reason ``invalid_request``).
- ``backend_error``: every attempt failed in the backend (kind and HTTP status in the
  rationale). With mixed failures, ``parse_error`` wins: a model did answer.

Backends after the first wait in a queue. The next one starts ``hedge_after_s`` after
the previous start (hedging, when set), or at once when every running attempt has
failed (failover). A failed attempt never ends the decision while another may still
answer before the deadline. Every non-LLM answer is :func:`fallback_choice`.
"""

from __future__ import annotations

import asyncio
import contextvars
import gc
import logging
import math
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal

from shared.messages import (
    MAX_TEXT_CHARS,
    DecisionSource,
    Option,
    ReasonerDecision,
    ReasonerRequest,
)
from shared.realtime import favoured

from .backends import BackendError, ChatBackend, Completion
from .parsing import Parsed, ParseError, parse_decision, parse_partial
from .prompts import Variant, build_messages, load_template, suspicious_scene, unusual_of

log = logging.getLogger(__name__)

FallbackKind = Literal["first_recovery", "rank"]
DEFAULT_TASK = "carry out the current mission safely"
# the request_id being decided, for what the attempts call (a backend's logs, a bench's
# timing): set by Decider.decide, copied into each attempt's task
DECIDING: contextvars.ContextVar[str | None] = contextvars.ContextVar("aesop_deciding",
                                                                      default=None)


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

    def __reduce__(self) -> tuple[type[FallbackPolicy], tuple[str, dict[str, int]]]:
        return FallbackPolicy, (self.kind, dict(self.ranks))  # to the keeper's process


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


def fallback_decision(request: ReasonerRequest, policy: FallbackPolicy,
                      source: DecisionSource, why: str, latency_ms: float,
                      answer: str = "") -> ReasonerDecision:
    """The labelled fallback for ``request``: :func:`fallback_choice`, and why (``answer``:
    what a model wrote that did not parse)."""
    choice = fallback_choice(request.options, policy)
    return ReasonerDecision(
        robot=request.robot, request_id=request.request_id, choice=choice, source=source,
        rationale=f"{source}: {why}; fallback option {choice} ({policy.kind})",
        latency_ms=latency_ms, model="", answer=answer[:MAX_TEXT_CHARS])


def timeout_reason(deadline_s: float) -> str:
    return f"no valid answer within the deadline of {deadline_s:g} s"


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
    text: str = ""  # what the model wrote (a parse error's)


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
    margin_s: float = 0.020  # the machine's own scheduling stalls (benchmarks.md)

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

    @property
    def backends(self) -> tuple[ChatBackend, ...]:
        return self._backends

    @property
    def config(self) -> DeciderConfig:
        return self._config

    @property
    def policy(self) -> FallbackPolicy:
        return self._policy

    async def aclose(self) -> None:
        """Wait for the cancelled attempts to close, then close every backend."""
        if self._closing:
            await asyncio.gather(*self._closing, return_exceptions=True)
        for backend in self._backends:
            await backend.aclose()

    async def decide(self, request: ReasonerRequest, *,
                     received_at: float | None = None) -> ReasonerDecision:
        """y for ``request``, by ``received_at + deadline_s - margin_s`` (clock seconds)."""
        start = self._clock() if received_at is None else received_at
        deadline = start + request.deadline_s - self._config.margin_s
        DECIDING.set(request.request_id)  # this task's context only
        flagged = suspicious_scene(task=request.observation.task,
                                   observation=request.observation.text,
                                   unusual=unusual_of(request))
        if flagged:
            return self._fallback(request, start, "refused",
                                  f"injection: {flagged}; LLM not asked")
        try:
            messages = self._messages(request)
        except ValueError as exc:
            return self._fallback(request, start, "refused", f"invalid_request: {exc}")
        offered = [o.index for o in request.options]
        outcome = await self._race(messages, offered, deadline)
        return self._decision(request, start, outcome)

    def _messages(self, request: ReasonerRequest) -> list[dict[str, str]]:
        return build_messages(self._template, task=request.observation.task or DEFAULT_TASK,
                              observation=request.observation.text, options=request.options,
                              variant=self._config.variant, unusual=unusual_of(request),
                              drift=request.drift is not None)

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
                model=outcome.model, answer=outcome.completion.text[:MAX_TEXT_CHARS])
        if isinstance(outcome, Timeout):
            seen = _describe(outcome.failures)
            return self._fallback(request, start, "timeout", timeout_reason(request.deadline_s)
                                  + (f" ({seen})" if seen else ""), outcome.failures)
        source: DecisionSource = (
            "parse_error" if any(f.source == "parse_error" for f in outcome) else "backend_error")
        return self._fallback(request, start, source, _describe(outcome), outcome)

    def _fallback(self, request: ReasonerRequest, start: float, source: DecisionSource,
                  why: str, failures: Sequence[Failure] = ()) -> ReasonerDecision:
        return fallback_decision(request, self._policy, source, why, self._latency_ms(start),
                                 next((f.text for f in failures if f.text), ""))

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
        return Failure("parse_error", f"{backend.name}: {exc.reason} ({exc.detail})",
                       completion.text)
    return Win(parsed=parsed, model=backend.model, completion=completion)


def keep_up(switch_interval_s: float = 0.001) -> None:
    """Tune the service's process, once, from its entry point: a thread that wants the GIL
    waits at most ``switch_interval_s`` for it (Python's default is 5 ms), and the process
    gets a larger share of a busy machine's cores where allowed
    (:func:`shared.realtime.favoured`). The deadline does not depend on it (the keeper
    keeps that); how many answers beat the deadline does."""
    sys.setswitchinterval(switch_interval_s)
    favoured()


def settle() -> None:
    """Once started: move the objects alive now (models, clients, schemas) out of the
    garbage collector's generations, so that its full collections walk only what came
    after (they hold the GIL for as long as they walk)."""
    gc.collect()
    gc.freeze()


def _describe(failures: Sequence[Failure]) -> str:
    return "; ".join(f"{f.source} {f.detail}" for f in failures)
