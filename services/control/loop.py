"""The fixed-rate control loop: a real-time deadline scheduler and the per-tick runtime.

Nothing here touches Zenoh or HTTP; the service (:mod:`.service`) feeds each
tick the newest verdict, decision and observation and publishes what it
returns.

* :class:`FixedRateScheduler` runs a tick at ``start + k * period`` (never
  ``previous + period``, so it cannot drift) on the thread that calls
  :meth:`~FixedRateScheduler.run`, the service's tick thread: it sleeps until
  ``spin_s`` before the deadline and spins the rest, so a tick starts within
  tens of microseconds of its deadline (asyncio's timer woke about 1 ms late,
  measured with ``aesop bench loop`` before the loop had a thread of its own).
  It records each tick's jitter (start minus deadline) and, when a tick's work
  ends after the next deadline, counts an overrun and skips to the first
  deadline still in the future, counting the ticks missed. Clock and sleep are injectable.
* :class:`ControlRuntime` is one robot's closed loop: the vehicle's newest state
  read by :mod:`.contract`'s rules (fresh by arrival, refused when it cannot be
  right, carried forward to the tick's time by the controller), the detector read by
  :mod:`.detector`'s rules, reasoner decisions routed by ``request_id``, the
  controller's ``make_step``, and the messages of the tick, the vehicle's set-point
  among them. No vehicle is simulated here: whatever publishes the state is flown
  (``aesop serve sim`` is one such vehicle). A tick holds its ``lock``; a reset or a
  change of regions builds the new controller off the tick and swaps it in under the
  lock, between two ticks.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from shared.bus import Received
from shared.messages import (
    AnomalyVerdict,
    ControlState,
    Event,
    Mode,
    Observation,
    PlanSnapshot,
    ReasonerDecision,
    ReasonerRequest,
    Severity,
    VehicleSetpoint,
    VehicleState,
)

from .contract import StateInput, StateReading, setpoint
from .core import handshake, outbox
from .core.aesop import ControlOutput
from .core.controllers import Controller, make_controller, mpc_config
from .core.dynamics import POS, rest_at
from .core.handshake import Asked, Handshake
from .core.mpc import SolveStatus
from .core.regions import Region
from .core.scenario import Scenario, ScenarioError
from .core.verdicts import Cause, Sightings, verdict_age
from .settings import ControlSettings

log = logging.getLogger(__name__)

SPIN_S = 0.0005  # s: the scheduler spins, rather than sleeps, this close to a deadline
WARM_M = 0.05  # m: a waiting flight's controller is warmed up again if the vehicle is farther
Clock = Callable[[], float]
Sleep = Callable[[float], Any]

# --------------------------------------------------------------------------- scheduling


@dataclass(frozen=True)
class TickTiming:
    """When one tick ran, on the scheduler's clock (s)."""

    index: int  # k: the tick's deadline is start + k * period
    deadline: float
    started: float
    ended: float
    overrun: bool  # the work ended after the next deadline
    missed: int  # deadlines skipped because of that overrun

    @property
    def jitter_s(self) -> float:
        return self.started - self.deadline

    @property
    def work_s(self) -> float:
        return self.ended - self.started


def next_index(start: float, period: float, index: int, ended: float) -> tuple[int, int]:
    """``(next k, ticks missed)`` after tick ``index`` ended at ``ended``.

    The next tick is ``index + 1`` unless its deadline has already passed; then
    it is the first deadline strictly after ``ended``.
    """
    following = index + 1
    if ended <= start + following * period:
        return following, 0
    future = max(following, math.floor((ended - start) / period) + 1)
    return future, future - following


class LoopStats:
    """Counters and a window of recent jitters and step times, for ``GET /v1/state``."""

    def __init__(self, window: int = 1000) -> None:
        self.ticks = 0
        self.overruns = 0
        self.missed = 0
        self.jitter_ms: deque[float] = deque(maxlen=window)
        self.work_ms: deque[float] = deque(maxlen=window)

    def record(self, timing: TickTiming) -> None:
        self.ticks += 1
        self.overruns += int(timing.overrun)
        self.missed += timing.missed
        self.jitter_ms.append(timing.jitter_s * 1000.0)
        self.work_ms.append(timing.work_s * 1000.0)

    def summary(self) -> dict[str, float | int | None]:
        def pct(values: deque[float], q: float) -> float | None:
            return round(float(np.percentile(values, q)), 3) if values else None

        return {"ticks": self.ticks, "overruns": self.overruns, "missed_ticks": self.missed,
                "jitter_p50_ms": pct(self.jitter_ms, 50), "jitter_p99_ms": pct(self.jitter_ms, 99),
                "jitter_max_ms": round(max(self.jitter_ms), 3) if self.jitter_ms else None,
                "tick_p50_ms": pct(self.work_ms, 50), "tick_p99_ms": pct(self.work_ms, 99)}


class FixedRateScheduler:
    """Calls ``tick(deadline)`` at ``start + k * period`` on the calling thread, until
    ``stop()`` (from any thread) or ``max_ticks``."""

    def __init__(self, period_s: float, *, clock: Clock = time.monotonic,
                 sleep: Sleep = time.sleep, spin_s: float = SPIN_S, window: int = 1000) -> None:
        if not period_s > 0:
            raise ValueError("period_s must be positive")
        if spin_s < 0:
            raise ValueError("spin_s must be >= 0")
        self.period, self.spin_s = period_s, spin_s
        self.clock, self.sleep = clock, sleep
        self.stats = LoopStats(window)
        self._stopping = threading.Event()

    def stop(self) -> None:
        """End the loop after the tick in progress."""
        self._stopping.set()

    def run(self, tick: Callable[[float], object], *,
            on_tick: Callable[[TickTiming], None] | None = None,
            max_ticks: int | None = None) -> None:
        start = self.clock()
        index = 0
        done = 0
        while not self._stopping.is_set() and (max_ticks is None or done < max_ticks):
            deadline = start + index * self.period
            now = self._wait(deadline)
            tick(deadline)
            ended = self.clock()
            following, missed = next_index(start, self.period, index, ended)
            timing = TickTiming(index, deadline, now, ended, missed > 0, missed)
            self.stats.record(timing)
            if on_tick is not None:
                on_tick(timing)
            index = following
            done += 1

    def _wait(self, deadline: float) -> float:
        """Sleep until ``spin_s`` before ``deadline``, spin the rest; the time it starts."""
        now = self.clock()
        while deadline - now > self.spin_s:
            self.sleep(deadline - now - self.spin_s)
            now = self.clock()
        while now < deadline and self.spin_s > 0:
            now = self.clock()
        return now


# --------------------------------------------------------------------------- the runtime


class NotNominal(Exception):
    """The flight is not nominal (or waiting), so its recovery regions cannot change now."""


CALM = (Mode.NOMINAL, Mode.WAITING)  # modes in which the regions may change


@dataclass(frozen=True)
class TickResult:
    """What one tick produced: the messages to publish and how long the step took."""

    state: ControlState
    plan: PlanSnapshot | None
    request: ReasonerRequest | None
    events: tuple[Event, ...]
    output: ControlOutput
    step_ms: float  # make_step, wall time
    anomaly: bool  # the flag make_step was given
    stale: bool  # the verdict was missing or older than verdict_stale_s
    vehicle: StateReading  # the vehicle's state as this tick saw it
    setpoint: VehicleSetpoint | None = None  # for the vehicle; None while waiting


@dataclass
class _Inputs:
    anomaly: bool
    decision: int | None
    stale: bool
    verdict: Received[AnomalyVerdict] | None
    events: list[Event] = field(default_factory=list)
    cause: Cause | None = None  # of the request this tick may raise
    waiting: bool = False  # the flight has not started: nothing is stepped


def scene_key(observation: Observation) -> str:
    """What makes two observations the same scene to the reasoner: the text and every
    detection behind it (a scene it cleared is cleared only with the same detections)."""
    phrases = sorted(d.phrase for d in observation.detections)
    return "\n".join([observation.text, *phrases]) if phrases else observation.text


def check_fence(scenario: Scenario, regions: Sequence[Region]) -> None:
    """Every region must lie inside the position limits; ``ScenarioError`` names the entry."""
    lo, hi = np.asarray(scenario.limits.position_lo), np.asarray(scenario.limits.position_hi)
    for i, region in enumerate(regions):
        if np.any(np.asarray(region.position_lo) < lo) or \
                np.any(np.asarray(region.position_hi) > hi):
            raise ScenarioError(f"regions[{i}]", f"{region.name!r} lies outside the position "
                                f"limits {list(scenario.limits.position_lo)}.."
                                f"{list(scenario.limits.position_hi)}")


class ControlRuntime:
    """One robot's closed loop: vehicle state, verdict and decision in, messages (the
    vehicle's set-point among them) out, one tick at a time.

    A flight starts ``waiting``: nothing is solved and no set-point is sent (the
    vehicle holds itself) until a fresh verdict shows the detector is watching and a
    fresh state shows the vehicle is there; then it flies (the same after a reset).
    The detector is read by :mod:`.detector`'s rules: freshness from the
    observation a verdict answers, silence as an anomaly that "continue" cannot
    end; a stale or refused vehicle state is such an anomaly too (:mod:`.contract`).
    ``tick`` holds ``lock`` while it runs; ``replace_regions`` and ``reset`` take it
    too, so a controller is only ever swapped between ticks.
    """

    def __init__(self, settings: ControlSettings, scenario: Scenario, *,
                 clock: Clock = time.monotonic) -> None:
        self.settings, self.scenario, self.clock = settings, scenario, clock
        self.lock = threading.Lock()
        x0 = rest_at(scenario.start_center)  # warm-up only: the vehicle says where it is
        self.controller = self.build_controller(scenario, x0)
        self.vehicle = StateInput(
            limit_s=settings.vehicle.state_stale_ticks * self.period_s,
            frame=settings.vehicle.frame, jump_m=settings.vehicle.state_jump_m,
            reset_s=settings.vehicle.state_reset_s, window_s=settings.vehicle.state_window_s,
            max_delay_s=settings.vehicle.state_max_delay_s,
            max_speed=settings.vehicle.state_max_speed)
        self._last_x = x0  # the newest state the loop planned from
        self._warm_at = x0[POS].copy()  # where the controller was warmed up
        self._warming: Future[tuple[Controller, np.ndarray]] | None = None
        self._builder: ThreadPoolExecutor | None = None
        self._setpoints = 0  # set-points sent (their seq)
        self._k = 0  # ticks flown since the flight (re)started, missed ones included
        self._k0 = 0  # tick at which the controller was built
        self._stepped: float | None = None  # the deadline of the last tick that stepped
        self._ahead_sent = 0  # inputs the last set-point carried ahead
        self.mode = Mode.WAITING
        self._queued: list[Event] = [self._waiting_event()]
        self.handshake = Handshake()  # the pending request, silence, cleared scenes
        self._seen: deque[Observation] = deque(maxlen=64)  # recent observations, by seq
        self._sightings = Sightings()
        self.last: TickResult | None = None

    # ----------------------------------------------------------------- building

    def build_controller(self, scenario: Scenario, x0: np.ndarray | None = None) -> Controller:
        """A fresh controller of the configured method for ``scenario`` (pure CPU, no I/O),
        warmed up at ``x0`` so that the first tick is not a cold solve (an overrun)."""
        fallback = self.settings.fallback
        if isinstance(fallback, int) and fallback not in {r.index for r in scenario.regions}:
            raise ValueError(f"fallback: region {fallback} is not one of the "
                             f"scenario's {len(scenario.regions)} recovery regions")
        config = mpc_config(scenario, **self.settings.mpc_overrides())
        controller = make_controller(self.settings.method, scenario, config=config,
                                     fallback=fallback)
        if x0 is not None:
            controller.warm_up(x0)
        return controller

    @property
    def period_s(self) -> float:
        """Wall seconds between ticks: the configured rate's, else the scene's dt."""
        return self.settings.period_s(self.scenario.dt)

    @property
    def time_scale(self) -> float:
        """Model seconds per wall second: 1 when the loop ticks at the scene's 1/dt (a real
        vehicle), more when it flies a simulator faster than real time."""
        return self.scenario.dt / self.period_s

    @property
    def pending(self) -> str | None:
        """The request_id of the request to the reasoner being waited on, if any."""
        return self.handshake.pending

    @property
    def t(self) -> float:
        """Simulated time of the next tick (s)."""
        return self._k * self.scenario.dt

    # ----------------------------------------------------------------- one tick

    def tick(self, *, deadline: float, verdict: Received[AnomalyVerdict] | None,
             decision: ReasonerDecision | None = None,
             observation: Received[Observation] | Observation | None = None,
             state: Received[VehicleState] | None = None) -> TickResult:
        """Run one tick whose deadline was ``deadline`` (scheduler clock, s) with the
        newest vehicle ``state`` on the bus; on the tick thread (it blocks for the
        controller's step)."""
        with self.lock:
            seen = self._see(observation)
            if state is not None:
                self.vehicle.offer(state, gate=self.mode is not Mode.WAITING)
            reading = self.vehicle.read(self.clock())
            ready = self.mode is not Mode.WAITING or self._warm_where(reading)
            inputs = self._read_inputs(verdict, decision, reading, ready)
            if inputs.waiting:
                self._stepped = None
                result = self._finish(self._hold(), inputs, 0.0, deadline, seen, reading)
                self.last = result
                return result
            missed = self._missed(deadline)
            if missed:  # the vehicle flew on through them: they are spent
                self.controller.skip(missed, self._ahead_sent)
                self._k += missed
            x = reading.x if reading.fresh else None
            age = (reading.age or 0.0) * self.time_scale if x is not None else 0.0
            started = time.perf_counter()
            output = self.controller.make_step(x, inputs.anomaly, inputs.decision, age,
                                               reading.acceleration)
            step_ms = (time.perf_counter() - started) * 1000.0
            result = self._finish(output, inputs, step_ms, deadline, seen, reading)
            self.last = result
            return result

    def _missed(self, deadline: float) -> int:
        """How many deadlines passed since the last tick that stepped, without a tick."""
        last, self._stepped = self._stepped, deadline
        return 0 if last is None else max(0, round((deadline - last) / self.period_s) - 1)

    def _see(self, observation: Received[Observation] | Observation | None
             ) -> Observation | None:
        """Remember an observation and when it was first seen (for verdict freshness)."""
        if observation is None:
            return None
        if isinstance(observation, Received):
            message, at = observation.message, observation.received_at
        else:
            message, at = observation, self.clock()
        if not self._seen or self._seen[-1].seq != message.seq:
            self._seen.append(message)
        self._sightings.record(message.seq, at)
        return message

    def _warm_where(self, reading: StateReading) -> bool:
        """While waiting: whether the controller is warm where the vehicle is. When it is
        not (the vehicle was moved, or started elsewhere), a controller warmed up there is
        built off the tick and swapped in by a later tick: the flight starts then, not
        with a cold solve (a few hundred ms at the hardware grid, an overrun)."""
        if not reading.fresh or reading.x is None:
            return True  # nothing to warm up at: waiting anyway
        if self._warming is not None:
            if not self._warming.done():
                return False
            warming, self._warming = self._warming, None
            try:
                self.controller, self._warm_at = warming.result()
            except Exception:  # a build that failed: the next tick tries again
                log.exception("warming the controller up failed")
                return False
        if float(np.linalg.norm(reading.x[POS] - self._warm_at)) <= WARM_M:
            return True
        if self._builder is None:
            self._builder = ThreadPoolExecutor(1, thread_name_prefix="control-warm")
        x, scenario = reading.x.copy(), self.scenario
        self._warming = self._builder.submit(
            lambda: (self.build_controller(scenario, x), x[POS].copy()))
        return False

    def _hold(self) -> ControlOutput:
        """While waiting: nothing is solved and nothing is sent (the vehicle holds)."""
        u = self.controller.model.linear.u_hover.copy()
        return ControlOutput(u=u, mode=Mode.WAITING, status=SolveStatus.SOLVED, plan=None,
                             active_regions=(), t_anom=None, chosen=None)

    def _read_inputs(self, verdict: Received[AnomalyVerdict] | None,
                     decision: ReasonerDecision | None, vehicle: StateReading,
                     ready: bool = True) -> _Inputs:
        events, self._queued = self._queued, []
        events.extend(self._event(n.kind, n.severity, n.message, **n.data)
                      for n in vehicle.notes)
        now = self.clock()
        age = None if verdict is None else verdict_age(
            self._sightings, verdict.message.seq, verdict.received_at, now)
        self.handshake, reading = handshake.step(self.handshake, handshake.Inputs(
            mode=self.mode, age=age, limit=self.settings.verdict_stale_s,
            verdict=None if verdict is None else verdict.message,
            scene=self._scene_of(verdict) if verdict and verdict.message.is_anomaly else None,
            decision=decision, vehicle=vehicle.fresh and ready))
        events.extend(self._event(n.kind, n.severity, n.message, **n.data)
                      for n in reading.notes)
        return _Inputs(reading.anomaly, reading.decision, reading.stale, verdict, events,
                       cause=reading.cause, waiting=reading.waiting)

    def _scene_of(self, verdict: Received[AnomalyVerdict] | None) -> str | None:
        """The scene (:func:`scene_key`) of the observation ``verdict`` judged; the newest
        one seen if that one never reached a tick (a scene changes more slowly than the
        loop runs)."""
        if verdict is None or not self._seen:
            return None
        seq = verdict.message.seq
        judged = next((o for o in reversed(self._seen) if o.seq == seq), self._seen[-1])
        return scene_key(judged)

    def _finish(self, output: ControlOutput, inputs: _Inputs, step_ms: float,
                deadline: float, observation: Observation | None,
                reading: StateReading) -> TickResult:
        robot, dt = self.settings.robot, self.scenario.dt
        t = self._k * dt
        events = inputs.events
        verdict = None if inputs.verdict is None else inputs.verdict.message
        request = None
        if output.request is not None:
            request = outbox.request(
                robot=robot, request_id=uuid.uuid4().hex, cause=inputs.cause, verdict=verdict,
                observation=observation, regions=self.scenario.regions,
                offered=output.request, deadline_s=self._seconds_left(deadline, output))
        asked = None
        if request is not None:
            scene = None if observation is None else scene_key(observation)
            asked = Asked(request.request_id, inputs.cause, scene,
                          None if verdict is None else verdict.seq)
        self.handshake = handshake.conclude(self.handshake, asked)
        events.extend(self._event("non_finite", "alarm", alarm) for alarm in output.alarms)
        events.extend(outbox.mode_events(robot, self.mode, output, request.request_id
                                         if request is not None else self.handshake.pending))
        self.mode = output.mode
        t_anom = None if output.t_anom is None else (self._k0 + output.t_anom) * dt
        if inputs.waiting:
            if reading.x is not None and np.all(np.isfinite(reading.x)):
                self._last_x = reading.x
        elif reading.fresh and np.all(np.isfinite(self.controller.state)):
            self._last_x = self.controller.state  # carried forward to this tick
        sent = None
        if not inputs.waiting:
            valid = self.settings.vehicle.setpoint_valid_ticks
            sent = setpoint(robot=robot, seq=self._setpoints, output=output,
                            model=self.controller.model, reading=reading,
                            valid_s=valid * self.period_s, mode=output.mode,
                            period_s=self.period_s, ahead=math.ceil(valid - 1e-9) - 1)
            self._setpoints += sent is not None
            self._ahead_sent = 0 if sent is None else len(sent.ahead)
            self._k += 1
        fresh = not inputs.waiting and reading.fresh
        state = outbox.control_state(robot=robot, t=t, x=self._last_x, output=output,
                                     t_anom=t_anom, state_age_s=reading.age if fresh else None)
        return TickResult(state, outbox.plan_snapshot(robot, t, output.plan), request,
                          tuple(events), output, step_ms, inputs.anomaly, inputs.stale,
                          reading, sent)

    def _seconds_left(self, deadline: float, output: ControlOutput) -> float:
        """The reasoner's deadline (s from now) for a request raised at the tick whose
        deadline was ``deadline``: the decision must be here by the tick at k = K, and the
        controller says how many ticks are left (fewer than K when a hold had already spent
        some), less the margin for the trip back."""
        left = output.consensus_left
        left = max(self.scenario.consensus if left is None else left, 0)
        due = deadline + left * self.period_s
        return max(due - self.clock() - self.settings.decision_margin_s, 1e-3)

    def _waiting_event(self) -> Event:
        return self._event("waiting", "info", "sending nothing (the vehicle holds itself) "
                           "until the anomaly detector answers a fresh observation and the "
                           "vehicle's state is fresh")

    def _event(self, kind: str, severity: Severity, message: str,
               **data: str | int | float | bool | None) -> Event:
        return outbox.event(self.settings.robot, kind, severity, message, **data)

    # ----------------------------------------------------------------- changes between ticks

    async def replace_regions(self, regions: tuple[Region, ...]) -> None:
        """Swap the recovery regions (and so the controller) between two ticks.

        Raises ``ValueError`` (nothing changed) for regions the scenario cannot
        use and :class:`NotNominal` unless the flight is nominal or waiting (:data:`CALM`).
        """
        check_fence(self.scenario, regions)
        scenario = self.scenario.with_regions(regions)
        if self.mode not in CALM:
            raise NotNominal(self.mode.value)
        controller = await asyncio.to_thread(self.build_controller, scenario, self._last_x)
        await asyncio.to_thread(self._swap_regions, scenario, controller)

    def _swap_regions(self, scenario: Scenario, controller: Any) -> None:
        with self.lock:  # between two ticks
            if self.mode not in CALM:
                raise NotNominal(self.mode.value)
            controller.carry_on(self.controller)
            self.scenario, self.controller, self._k0 = scenario, controller, self._k
            self._warming = None  # one being built has the old regions
            self.handshake = handshake.forget_request(self.handshake)
            regions = scenario.regions
            self._queued.append(self._event(
                "regions_updated", "info", f"{len(regions)} recovery regions: "
                + ", ".join(r.name for r in regions), count=len(regions)))

    async def reset(self) -> tuple[float, float, float] | None:
        """Start the flight again from wherever the vehicle is (it is not moved: a
        simulator has its own reset); returns its newest position, None before any state.
        The new controller is warmed up there, off the tick."""
        newest = self.vehicle.newest
        x0 = self._last_x if newest is None else newest
        controller = await asyncio.to_thread(self.build_controller, self.scenario, x0)
        await asyncio.to_thread(self._swap_flight, controller, x0)
        return None if newest is None else (float(x0[0]), float(x0[1]), float(x0[2]))

    def close(self) -> None:
        """Let the warm-up thread go (after the loop has ended)."""
        if self._builder is not None:
            self._builder.shutdown(wait=False, cancel_futures=True)
            self._builder = None

    def _swap_flight(self, controller: Any, x0: np.ndarray) -> None:
        with self.lock:  # between two ticks
            self.controller, self._warm_at, self._warming = controller, x0[POS].copy(), None
            self.vehicle.forget()
            self._k = self._k0 = 0
            self._stepped, self._ahead_sent = None, 0
            self.mode, self.handshake = Mode.WAITING, Handshake()
            self._queued.append(self._waiting_event())
            self._queued.append(self._event("reset", "info", "flight restarted: waiting for "
                                            "a fresh verdict and a fresh vehicle state"))
