"""``aesop bench reasoner``: the slow reasoner's deadline against the fake LLM server.

Real processes: the fake OpenAI-compatible server (:mod:`tools.fakes.llm`) runs
as a child process with the paper's ``bimodal`` latency profile (mean 3.1 s, std 0.85 s,
95th percentile 4.3 s) and ``K = 4.3 s``, both multiplied by ``scale`` (default 0.1, so
``K = 0.43 s``). The reasoner runs as the service runs it on the bus: this process holds
the decider and its worker (:class:`~services.reasoner.worker.ReasonerWorker`), which
starts the deadline keeper, a process of its own; a third process plays the robot
(:func:`drive`): it publishes ``requests`` requests (the quadrotor red-box scenario,
options 0 continue / 1 alternative landing site / 2 holding zone) on its Zenoh peer,
keeping ``concurrency`` unanswered at a time.

Definitions:

- **latency**: the published decision's ``latency_ms``, stamped by the keeper: from the
  request's arrival there (where the deadline starts) to the decision's publication.
- **overshoot** = latency - K (ms; negative = answered early), over all requests and over
  the ``timeout`` decisions alone.
- **deadline miss**: latency > K + 1 ms (tolerance ``MISS_TOLERANCE_S``).
- **round trip**: from the robot's put of a request to its hearing the decision (Zenoh
  both ways and the robot process's own delays included; not the reasoner's contract).
- **fallback rate**: decisions whose source is not ``llm``, overall and by source.
- **overhead excluding the LLM**, for ``llm`` decisions, in two parts: *in the service*,
  from ``Decider.decide``'s start to the first backend call plus from the winning call's
  end to ``decide``'s return (as before the keeper, when this was all of it); and the
  keeper's *hand-over*, from the request's arrival in the keeper to ``decide``'s start
  plus from its return to the publication (pipe both ways, the keeper's own work).
  Backend time (measured by :class:`TimedBackend`) includes the client side of HTTP
  (httpx), so it counts as "the LLM".
- **hedging**: the same requests against a fresh primary server (same seed) plus a second
  server (seed + 1), ``hedge_after_s`` = the single-backend run's p50 decision latency
  unless given; p95 latency and fallback rate, hedged / single, as ratios.

Each server draws latencies from one seeded RNG in arrival order, so with concurrency
the draws are reproducible in distribution, not request by request.

With ``cpu_hog`` = N, N other processes spin on the CPU through both phases (a busy
robot computer: the deadline must hold when the cores are not the reasoner's alone).
Beside each phase runs :mod:`tools.bench.canary`, a bare real-time thread in a process of
its own: how late it wakes is the machine's share of any lateness (the reference).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from services.reasoner.backends import (
    BackendConfig,
    ChatBackend,
    Completion,
    OpenAIChatBackend,
    StopWhen,
    make_client,
)
from services.reasoner.deciding import DECIDING, Decider, DeciderConfig, settle
from services.reasoner.settings import ReasonerSettings
from services.reasoner.worker import ReasonerWorker
from shared import topics
from shared.bus import Bus
from shared.messages import Observation, Option, ReasonerDecision, ReasonerRequest
from shared.process import ServiceProcess, free_port
from shared.settings import BusSettings
from shared.tables import table
from tools import progress
from tools.bench.canary import canary

log = logging.getLogger(__name__)

ROBOT = "bench"
LOST_AFTER_S = 30.0  # the robot process's whole run may take this long past K per request
# s after K: a request still without a decision is unanswered (nothing leaves past its
# deadline: a decision the keeper would have sent late was dropped, the robot took its own
# fallback at K), counted as a deadline miss; the robot sends the next one
UNANSWERED_AFTER_S = 2.0
PAPER_K_S = 4.3  # s: the paper's deadline, the bimodal profile's 95th percentile
MISS_TOLERANCE_S = 0.001  # s: an answer later than K + this is a deadline miss
TARGET_OVERSHOOT_P99_MS = 20.0
TARGET_OVERHEAD_P99_MS = 5.0
SOURCES = ("llm", "timeout", "parse_error", "backend_error", "refused")

TASK = "land the quadrotor on the red box"
RED_BOX = "another quadrotor is parked on the red box\na blue box on the ground"
OPTIONS = (
    Option(index=0, label="continue", description="proceed with landing on the red box"),
    Option(index=1, label="alternative landing site", description="land on the blue box instead"),
    Option(index=2, label="holding zone", description="hover in the designated holding zone"),
)


# --------------------------------------------------------------------------- timing


@dataclass
class Call:
    """One ``complete`` call: monotonic start/end and whether it returned a completion."""

    backend: str
    t0: float
    t1: float = 0.0
    ok: bool = False


class TimedBackend:
    """A :class:`ChatBackend` that records every ``complete`` call under the request being
    decided (:data:`~services.reasoner.deciding.DECIDING`) in ``calls``."""

    def __init__(self, inner: ChatBackend, calls: dict[str, list[Call]]) -> None:
        self._inner = inner
        self._calls = calls
        self.name = inner.name
        self.model = inner.model

    async def complete(self, messages: list[dict[str, str]], *,
                       stop_when: StopWhen | None = None,
                       answers: Sequence[int] | None = None) -> Completion:
        call = Call(self.name, time.monotonic())
        self._calls.setdefault(DECIDING.get() or "", []).append(call)
        try:
            completion = await self._inner.complete(messages, stop_when=stop_when,
                                                    answers=answers)
            call.ok = True
            return completion
        finally:
            call.t1 = time.monotonic()

    async def aclose(self) -> None:
        await self._inner.aclose()


@dataclass(frozen=True)
class Decided:
    """One ``Decider.decide`` in the service: the keeper's arrival stamp, start, return."""

    received_at: float
    start: float
    end: float


class TimedDecider(Decider):
    """A :class:`Decider` that records each decision's :class:`Decided` in ``decided``."""

    def __init__(self, *args: Any, decided: dict[str, Decided], **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.decided = decided

    async def decide(self, request: ReasonerRequest, *,
                     received_at: float | None = None) -> ReasonerDecision:
        start = time.monotonic()
        decision = await super().decide(request, received_at=received_at)
        self.decided[request.request_id] = Decided(
            start if received_at is None else received_at, start, time.monotonic())
        return decision


@dataclass
class Sample:
    """One published decision, its round trip, the service's decide and backend calls."""

    decision: ReasonerDecision
    round_trip_s: float
    calls: list[Call] = field(default_factory=list)
    decided: Decided | None = None

    @property
    def latency_s(self) -> float:
        return self.decision.latency_ms / 1e3

    def overhead_parts_s(self) -> tuple[float, float] | None:
        """(in the service, the keeper's hand-over) outside the LLM, for an ``llm``
        decision (see the module docstring)."""
        done = [c for c in self.calls if c.ok]
        if self.decision.source != "llm" or not done or self.decided is None:
            return None
        first = min(c.t0 for c in self.calls)
        winner = min(done, key=lambda c: c.t1)
        d = self.decided
        service = (first - d.start) + (d.end - winner.t1)
        return service, self.latency_s - (d.end - d.start)

    def overhead_s(self) -> float | None:
        """Time outside the LLM for an ``llm`` decision, both parts."""
        parts = self.overhead_parts_s()
        return None if parts is None else parts[0] + parts[1]


# --------------------------------------------------------------------------- the run


@contextlib.contextmanager
def cpu_hogs(n: int) -> Iterator[None]:
    """``n`` processes spinning on the CPU until the block ends, at normal priority (nice
    0, as other work on the robot's computer would run), whatever this process's is."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"],
                             preexec_fn=lambda: os.setpriority(os.PRIO_PROCESS, 0, 0))
            for _ in range(n)]
    try:
        yield
    finally:
        for hog in hogs:
            hog.kill()
        for hog in hogs:
            hog.wait(10)


def run_reasoner_bench(*, requests: int = 1000, scale: float = 0.1, concurrency: int = 8,
                       seed: int = 0, hedge_after_s: float | None = None,
                       table: bool = True, cpu_hog: int = 0) -> dict[str, Any]:
    """Run the single-backend and the hedged phase; return one JSON-able dict.

    Tables go to stdout when ``table``; progress goes to stderr (stray prints too).
    """
    if requests < 1 or concurrency < 1 or not scale > 0:
        raise ValueError("requests and concurrency must be >= 1 and scale > 0")
    out = sys.stdout
    started = time.perf_counter()
    load_start = list(os.getloadavg())
    deadline_s = PAPER_K_S * scale
    model = f"fake-bimodal-scale-{scale:g}"
    with contextlib.redirect_stdout(sys.stderr), cpu_hogs(cpu_hog), \
            tempfile.TemporaryDirectory(prefix="aesop-bench-reasoner-") as tmp:
        logs = Path(tmp)
        log.info("bench reasoner: %d requests, K = %.3f s (scale %g), concurrency %d, seed %d",
                 requests, deadline_s, scale, concurrency, seed)
        progress.step(f"one backend: {requests} decisions", 1, 2)
        with _fake_servers(logs, scale, [seed], "single") as urls, canary() as platform:
            single, loop_lag = asyncio.run(_phase(urls, model, requests, deadline_s,
                                                  concurrency, None))
        single_lat = [s.latency_s for s in single]
        hedge = (hedge_after_s if hedge_after_s is not None else
                 float(np.percentile(single_lat, 50)) if single_lat else deadline_s / 2)
        log.info("bench reasoner: hedged phase, hedge_after_s = %.3f s", hedge)
        progress.step(f"two backends, hedged after {hedge:.3f} s: {requests} decisions", 2, 2)
        with _fake_servers(logs, scale, [seed, seed + 1], "hedged") as urls, \
                canary() as hedged_platform:
            hedged, hedged_lag = asyncio.run(_phase(urls, model, requests, deadline_s,
                                                    concurrency, hedge))
    result = _summarise(single, hedged, deadline_s=deadline_s, hedge_after_s=hedge,
                        hedge_given=hedge_after_s is not None, requests=requests)
    result["meta"] = {
        "scale": scale, "paper_deadline_s": PAPER_K_S, "concurrency": concurrency,
        "seed": seed, "model": model, "profile": "bimodal", "cpu_hog": cpu_hog,
        "miss_tolerance_ms": MISS_TOLERANCE_S * 1e3, "margin_s": DeciderConfig().margin_s,
        "loop_lag_ms": {"single": loop_lag, "hedged": hedged_lag},
        "platform_lateness_ms": {"single": platform, "hedged": hedged_platform},
        "cpus": os.cpu_count(), "load_average_start": load_start,
        "load_average_end": list(os.getloadavg()), "wall_s": time.perf_counter() - started,
    }
    if table:
        progress.out(render(result), file=out)
    return result


@contextlib.contextmanager
def _fake_servers(logs: Path, scale: float, seeds: Sequence[int], phase: str
                  ) -> Iterator[list[str]]:
    """Fake LLM processes (bimodal, ``scale``), one per seed; always stopped on exit."""
    procs: list[ServiceProcess] = []
    try:
        for i, seed in enumerate(seeds):
            port = free_port()
            proc = ServiceProcess(
                ["serve", "fake-llm", "--port", str(port), "--profile", "bimodal",
                 "--time-scale", f"{scale:g}", "--seed", str(seed), "--log-level", "warning"],
                port=port, log_path=logs / f"fake_llm_{phase}_{i}.log")
            procs.append(proc)
            proc.start()
            log.info("bench reasoner: fake LLM %s/%d (seed %d) at %s", phase, i, seed, proc.url)
        yield [p.url for p in procs]
    finally:
        for proc in reversed(procs):
            proc.stop()


async def _count(decided: Mapping[str, Any], n: int, stop: asyncio.Event) -> None:
    """The decisions taken so far, on the progress line, twice a second."""
    while not stop.is_set():
        progress.count(len(decided), n, "decisions")
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), 0.5)


async def _phase(urls: Sequence[str], model: str, n: int, deadline_s: float,
                 concurrency: int, hedge_after_s: float | None
                 ) -> tuple[list[Sample], dict[str, float]]:
    client = make_client()  # shared, so the warm-up opens the connections the run uses
    configs = [BackendConfig(name=f"fake{i}", base_url=f"{url}/v1", model=model)
               for i, url in enumerate(urls)]
    calls: dict[str, list[Call]] = {}
    decided: dict[str, Decided] = {}
    backends = [TimedBackend(OpenAIChatBackend(c, client=client), calls) for c in configs]
    decider = TimedDecider(backends, DeciderConfig(domain="quadrotor",
                                                   hedge_after_s=hedge_after_s),
                           decided=decided)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    context = multiprocessing.get_context("spawn")
    ours, theirs = context.Pipe()
    robot = context.Process(target=drive, args=(endpoint, n, deadline_s, concurrency, theirs),
                            name="aesop-bench-robot", daemon=True)
    robot.start()
    theirs.close()
    worker = ReasonerWorker(decider, ReasonerSettings(zenoh_connect=[endpoint],
                                                      log_level="warning"))
    running = asyncio.create_task(worker.run())
    try:
        await asyncio.to_thread(_expect, ours, "listening", 60.0)  # the robot's peer is up
        await _warm_up(client, urls, concurrency)
        while not worker.listening:
            await asyncio.sleep(0.05)
        settle()  # as the service does once started: what exists now is long-lived
        stop = asyncio.Event()
        lag_task = asyncio.create_task(_loop_lag(stop))
        counting = asyncio.create_task(_count(decided, n, stop))
        ours.send("go")
        heard: list[tuple[ReasonerDecision, float] | None] = await asyncio.to_thread(
            _expect, ours, "heard", n * (deadline_s + LOST_AFTER_S))
        stop.set()
        lags = await lag_task
        await counting
    finally:
        ours.close()
        await worker.stop()
        await running
        await decider.aclose()
        await client.aclose()
        robot.join(10)
        if robot.is_alive():
            robot.kill()
    samples = []
    for i, got in enumerate(heard):
        if got is None:
            continue  # unanswered: counted by _phase_summary from requests - samples
        sample = Sample(*got)
        sample.calls = calls.get(f"bench-{i}", [])
        sample.decided = decided.get(f"bench-{i}")
        samples.append(sample)
    return samples, lags


def _expect(conn: Connection, kind: str, timeout_s: float) -> Any:
    """The robot process's next message, which must be ``(kind, payload)``."""
    if not conn.poll(timeout_s):
        raise RuntimeError(f"the bench's robot process said nothing ({kind}) in {timeout_s} s")
    got, payload = conn.recv()
    if got == "failed":
        raise RuntimeError(f"the bench's robot process failed: {payload}")
    if got != kind:
        raise RuntimeError(f"the bench's robot process said {got!r}, not {kind!r}")
    return payload


def drive(endpoint: str, n: int, deadline_s: float, concurrency: int, conn: Connection) -> None:
    """The robot's side, in a process of its own (its Zenoh session must not share the
    service's GIL): listen on ``endpoint``, say ``listening``; on ``go``, once the keeper is
    heard, send ``n`` requests ``concurrency`` at a time; answer ``("heard", [(decision,
    round trip s)])`` in request order."""
    try:
        with Bus.open(BusSettings(zenoh_listen=[endpoint]), "bench") as bus:
            conn.send(("listening", None))
            if conn.recv() != "go":
                return
            heard = asyncio.run(_closed_loop(bus, n, deadline_s, concurrency))
            conn.send(("heard", heard))
    except Exception as exc:  # said to the bench, which raises it
        conn.send(("failed", f"{type(exc).__name__}: {exc}"))


async def _closed_loop(bus: Bus, n: int, deadline_s: float, concurrency: int
                       ) -> list[tuple[ReasonerDecision, float] | None]:
    """``n`` requests, ``concurrency`` unanswered at a time: each decision heard, or each
    request given up ``UNANSWERED_AFTER_S`` past its K (None), lets the next request go.
    Starts once the keeper's token (announced after its subscriber) is seen."""
    decisions = bus.subscribe(topics.reasoner_decision(topics.ANY_ROBOT), ReasonerDecision,
                              maxsize=max(64, 4 * concurrency))
    deadline = time.monotonic() + 60.0
    while "reasoner" not in await asyncio.to_thread(bus.alive):
        if time.monotonic() > deadline:
            raise RuntimeError("the reasoner's deadline keeper was not heard in 60 s")
        await asyncio.sleep(0.05)
    sent_at: dict[str, float] = {}
    heard: dict[str, tuple[ReasonerDecision, float] | None] = {}
    key = topics.reasoner_request(ROBOT)

    def send(i: int) -> None:
        request = _request(i, deadline_s)
        sent_at[request.request_id] = time.monotonic()
        bus.publish(key, request)

    for i in range(min(concurrency, n)):
        send(i)
    sent = min(concurrency, n)
    while len(heard) < n:
        waiting = [rid for rid in sent_at if rid not in heard]
        give_up = min(sent_at[rid] for rid in waiting) + deadline_s + UNANSWERED_AFTER_S
        try:
            got = await asyncio.wait_for(anext(decisions),
                                         max(give_up - time.monotonic(), 0.0))
        except TimeoutError:
            done = [rid for rid in waiting
                    if time.monotonic() >= sent_at[rid] + deadline_s + UNANSWERED_AFTER_S]
        else:
            rid = got.message.request_id
            if rid not in sent_at or rid in heard:
                continue
            heard[rid] = (got.message, got.received_at - sent_at[rid])
            done = []
        for rid in done:
            heard[rid] = None
        for _ in range(len(done) + (0 if done else 1)):
            if sent < n:
                send(sent)
                sent += 1
    return [heard[f"bench-{i}"] for i in range(n)]


async def _warm_up(client: Any, urls: Sequence[str], concurrency: int) -> None:
    """Open ``concurrency`` connections per server with instant answers (not measured)."""
    messages = [{"role": "user", "content": "warm-up"}]
    for i, url in enumerate(urls):
        warm = OpenAIChatBackend(BackendConfig(name=f"warm{i}", base_url=f"{url}/v1",
                                               model="fake-fixed-0", stream=False),
                                 client=client)
        await asyncio.gather(*(warm.complete(messages) for _ in range(concurrency)))


async def _loop_lag(stop: asyncio.Event, period_s: float = 0.001) -> dict[str, float]:
    """How late a 1 ms sleep wakes up while the run goes on (event-loop load), in ms."""
    late: list[float] = []
    while not stop.is_set():
        t0 = time.monotonic()
        await asyncio.sleep(period_s)
        late.append((time.monotonic() - t0 - period_s) * 1e3)
    ms = np.asarray(late or [0.0])
    return {"p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)),
            "max": float(ms.max())}


def _request(i: int, deadline_s: float) -> ReasonerRequest:
    return ReasonerRequest(
        robot=ROBOT, request_id=f"bench-{i}",
        observation=Observation(robot=ROBOT, seq=i, task=TASK, text=RED_BOX),
        options=OPTIONS, deadline_s=deadline_s)


# --------------------------------------------------------------------------- statistics


def _stats(values_ms: Sequence[float], keys: Sequence[str] = ("p50", "p99", "max")
           ) -> dict[str, float | None]:
    """Percentiles (``pNN``), ``max`` and ``mean`` of values in ms; None when empty."""
    if not values_ms:
        return {k: None for k in keys}
    a = np.asarray(values_ms, dtype=np.float64)
    out: dict[str, float | None] = {}
    for k in keys:
        if k == "max":
            out[k] = float(a.max())
        elif k == "mean":
            out[k] = float(a.mean())
        else:
            out[k] = float(np.percentile(a, float(k[1:])))
    return out


def _phase_summary(samples: Sequence[Sample], deadline_s: float, requests: int
                   ) -> dict[str, Any]:
    """One phase: ``samples`` are the decisions heard of ``requests`` sent; one never heard
    (dropped rather than sent past its deadline) is a deadline miss."""
    over = [(s.latency_s - deadline_s) * 1e3 for s in samples]
    timeouts = [o for o, s in zip(over, samples, strict=True) if s.decision.source == "timeout"]
    sources: Counter[str] = Counter(s.decision.source for s in samples)
    n = max(len(samples), 1)
    unanswered = requests - len(samples)
    overhead = [o * 1e3 for s in samples if (o := s.overhead_s()) is not None]
    backend_ms = [(c.t1 - c.t0) * 1e3 for s in samples for c in s.calls if c.ok]
    return {
        "requests": requests,
        "unanswered": unanswered,
        "deadline_misses": sum(1 for o in over if o > MISS_TOLERANCE_S * 1e3) + unanswered,
        "overshoot_ms": _stats(over),
        "overshoot_timeouts_ms": {"n": len(timeouts), **_stats(timeouts)},
        "fallback_rate": (n - sources["llm"]) / n,
        "by_source": {src: sources[src] for src in SOURCES},
        "fallback_by_reason": {src: sources[src] / n for src in SOURCES if src != "llm"},
        "overhead_ms": {"n": len(overhead), **_stats(overhead, ("p50", "p99", "max"))},
        "overhead_service_ms": _stats([p[0] * 1e3 for s in samples
                                       if (p := s.overhead_parts_s()) is not None]),
        "overhead_handover_ms": _stats([p[1] * 1e3 for s in samples
                                        if (p := s.overhead_parts_s()) is not None]),
        "round_trip_ms": _stats([s.round_trip_s * 1e3 for s in samples],
                                ("p50", "p99", "max")),
        "latency_ms": _stats([s.latency_s * 1e3 for s in samples], ("p50", "p95", "p99", "max")),
        "backend_ms": _stats(backend_ms, ("p50", "p95", "max")),
        "backend_calls": sum(len(s.calls) for s in samples),
        "llm_choices": dict(sorted(Counter(s.decision.choice for s in samples
                                           if s.decision.source == "llm").items())),
    }


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b == 0 else a / b


def _summarise(single: Sequence[Sample], hedged: Sequence[Sample], *, deadline_s: float,
               hedge_after_s: float, hedge_given: bool, requests: int) -> dict[str, Any]:
    s, h = (_phase_summary(single, deadline_s, requests),
            _phase_summary(hedged, deadline_s, requests))
    hedging = {
        "hedge_after_s": hedge_after_s,
        "hedge_after_rule": "given" if hedge_given else "single-backend p50 decision latency",
        "backends": 2,
        "p95_latency_ms": {"single": s["latency_ms"]["p95"], "hedged": h["latency_ms"]["p95"]},
        "p95_latency_ratio": _ratio(h["latency_ms"]["p95"], s["latency_ms"]["p95"]),
        "fallback_rate": {"single": s["fallback_rate"], "hedged": h["fallback_rate"]},
        "fallback_rate_ratio": _ratio(h["fallback_rate"], s["fallback_rate"]),
        "hedged_run": h,
    }
    targets = {
        "deadline_misses_zero": s["deadline_misses"] == 0 and h["deadline_misses"] == 0,
        "overshoot_p99_le_20ms": _le(s["overshoot_ms"]["p99"], TARGET_OVERSHOOT_P99_MS)
        and _le(h["overshoot_ms"]["p99"], TARGET_OVERSHOOT_P99_MS),
        "overhead_p99_le_5ms": _le(s["overhead_service_ms"]["p99"], TARGET_OVERHEAD_P99_MS),
    }
    return {
        "requests": s["requests"], "deadline_s": deadline_s,
        "deadline_misses": s["deadline_misses"],
        "overshoot_ms": s["overshoot_ms"],
        "overshoot_timeouts_ms": s["overshoot_timeouts_ms"],
        "fallback_rate": s["fallback_rate"], "fallback_by_reason": s["fallback_by_reason"],
        "overhead_ms": {k: s["overhead_ms"][k] for k in ("p50", "p99")},
        "overhead_service_ms": s["overhead_service_ms"],
        "overhead_handover_ms": s["overhead_handover_ms"],
        "hedging": hedging, "targets": targets, "single_run": s,
    }


def _le(value: float | None, limit: float) -> bool:
    return value is not None and value <= limit


# --------------------------------------------------------------------------- tables


def render(r: Mapping[str, Any]) -> str:
    meta, h = r["meta"], r["hedging"]
    runs = {"single": r["single_run"], "hedged": h["hedged_run"]}
    k_ms = r["deadline_s"] * 1e3
    parts = [
        f"reasoner bench: {r['requests']} requests per run, bimodal fake LLM x{meta['scale']:g}"
        f", K = {k_ms:.0f} ms (paper {meta['paper_deadline_s']} s x{meta['scale']:g}), "
        f"concurrency {meta['concurrency']}, {meta.get('cpu_hog', 0)} CPU hog(s), seed "
        f"{meta['seed']}, decider margin "
        f"{meta['margin_s'] * 1e3:g} ms, miss = answer > K + {meta['miss_tolerance_ms']:g} ms\n",
        table("deadline (overshoot = latency - K, ms, latency stamped by the keeper; negative "
              "= early; platform max = how late a bare real-time thread woke meanwhile)", [
            {"run": name, "misses": x["deadline_misses"], "p50": x["overshoot_ms"]["p50"],
             "p99": x["overshoot_ms"]["p99"], "max": x["overshoot_ms"]["max"],
             "timeouts": x["overshoot_timeouts_ms"]["n"],
             "timeout p50": x["overshoot_timeouts_ms"]["p50"],
             "timeout p99": x["overshoot_timeouts_ms"]["p99"],
             "timeout max": x["overshoot_timeouts_ms"]["max"],
             "platform max": meta["platform_lateness_ms"][name].get("max_ms")}
            for name, x in runs.items()]),
        table("fallbacks by reason (fraction of requests)", [
            {"run": name, "fallback": x["fallback_rate"],
             **x["fallback_by_reason"], "llm choices": _choices(x["llm_choices"])}
            for name, x in runs.items()]),
        table("latency and overhead excluding the LLM (ms, llm decisions; service = in "
              "decide, hand-over = the keeper's, both ways)", [
            {"run": name, "latency p50": x["latency_ms"]["p50"],
             "latency p95": x["latency_ms"]["p95"], "latency p99": x["latency_ms"]["p99"],
             "backend p50": x["backend_ms"]["p50"], "calls": x["backend_calls"],
             "service p50": x["overhead_service_ms"]["p50"],
             "service p99": x["overhead_service_ms"]["p99"],
             "hand-over p50": x["overhead_handover_ms"]["p50"],
             "hand-over p99": x["overhead_handover_ms"]["p99"],
             "both p99": x["overhead_ms"]["p99"], "both max": x["overhead_ms"]["max"],
             "round trip p99": x["round_trip_ms"]["p99"],
             "round trip max": x["round_trip_ms"]["max"],
             "loop lag p99": meta["loop_lag_ms"][name]["p99"]} for name, x in runs.items()]),
        table(f"hedging (second backend after {h['hedge_after_s'] * 1e3:.0f} ms = "
               f"{h['hedge_after_rule']}; ratio = hedged / single)", [
            {"metric": "p95 latency (ms)", "single": h["p95_latency_ms"]["single"],
             "hedged": h["p95_latency_ms"]["hedged"], "ratio": h["p95_latency_ratio"]},
            {"metric": "fallback rate", "single": h["fallback_rate"]["single"],
             "hedged": h["fallback_rate"]["hedged"], "ratio": h["fallback_rate_ratio"]}]),
        table("targets", [
            {"target": "deadline misses = 0 (both runs)",
             "met": r["targets"]["deadline_misses_zero"]},
            {"target": f"overshoot p99 <= {TARGET_OVERSHOOT_P99_MS:g} ms (both runs)",
             "met": r["targets"]["overshoot_p99_le_20ms"]},
            {"target": f"overhead in the service p99 <= {TARGET_OVERHEAD_P99_MS:g} ms "
                       "(single run)",
             "met": r["targets"]["overhead_p99_le_5ms"]}]),
        f"total wall time {meta['wall_s']:.1f} s, load average "
        f"{meta['load_average_start'][0]:.1f} -> {meta['load_average_end'][0]:.1f}",
    ]
    return "\n".join(parts)


def _choices(counts: Mapping[Any, int]) -> str:
    return " ".join(f"{k}:{v}" for k, v in counts.items()) or "-"
