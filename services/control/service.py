"""The control loop as a service: Zenoh in and out around :class:`.loop.ControlRuntime`.

The loop runs on its own thread (the tick thread), not on the event loop, so
that a tick starts on time whatever the HTTP side is doing. Each tick reads
the newest ``VehicleState``, ``AnomalyVerdict``, ``ReasonerDecision`` and
``Observation`` of its robot from ``Latest`` slots (thread-safe; nothing queues up
behind a slow tick), runs the runtime, then publishes the ``VehicleSetpoint`` first,
``ControlState`` (every tick), ``PlanSnapshot`` (when the step produced a plan),
``ReasonerRequest`` (on the detection tick), ``Event``s and ``Regions`` (on start,
when they change and every ``REGIONS_EVERY_S``). A second thread queries the
vehicle's clock every ``clock_sync_s`` (:class:`.contract.ClockMap`). The bus declares
``aesop/health/control``.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections import deque

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from shared import topics
from shared.bus import Bus, Latest
from shared.messages import (
    AnomalyVerdict,
    Mode,
    Observation,
    ReasonerDecision,
    RegionBox,
    Regions,
    VehicleClock,
    VehicleState,
)
from shared.stats import spread

from .contract import ClockMap
from .core import outbox
from .core.scenario import Scenario
from .loop import ControlRuntime, FixedRateScheduler, TickResult, TickTiming
from .settings import ControlSettings

log = logging.getLogger(__name__)

SERVICE = "control"
_ERROR_LOG_INTERVAL_S = 10.0
REGIONS_EVERY_S = 1.0  # s: a dashboard that joins late draws the regions within this


def regions_message(scenario: Scenario, robot: str) -> Regions:
    """The scene's recovery regions and goal, as the dashboard draws them."""
    return Regions(robot=robot, goal=(float(scenario.goal[0]), float(scenario.goal[1]),
                                      float(scenario.goal[2])),
                   regions=tuple(RegionBox.model_validate(r.to_dict()) for r in scenario.regions))


class ControlMetrics:
    """The loop's Prometheus series, in the app's registry."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self.ticks = Counter("aesop_control_ticks", "Control ticks run", registry=registry)
        self.jitter = Histogram(
            "aesop_control_jitter_seconds", "Tick start minus its deadline", registry=registry,
            buckets=(.0002, .0005, .001, .002, .005, .01, .02, .05, .1, .25, .5, 1.0))
        self.overruns = Counter("aesop_control_overruns", "Ticks whose work ended after the "
                                "next deadline", registry=registry)
        self.missed = Counter("aesop_control_missed_ticks", "Deadlines skipped after overruns",
                              registry=registry)
        self.step = Histogram(
            "aesop_control_step_seconds", "Controller step (MPC solves) plus plant step",
            registry=registry,
            buckets=(.001, .002, .005, .01, .02, .05, .1, .2, .5, 1.0, 2.0))
        self.mode = Gauge("aesop_control_mode", "1 for the current Algorithm 1 mode", ["mode"],
                          registry=registry)
        self.stale = Counter("aesop_control_stale_verdict_ticks", "Ticks run with a missing or "
                             "stale anomaly verdict (counted as anomalies)", registry=registry)
        self.stale_alarms = Counter("aesop_control_stale_verdict_alarms", "Transitions to a "
                                    "stale anomaly verdict", registry=registry)
        self.requests = Counter("aesop_control_reasoner_requests", "Reasoner requests sent",
                                registry=registry)
        self.fallbacks = Counter("aesop_control_fallbacks", "Recoveries committed at K without "
                                 "a decision", registry=registry)
        self.errors = Counter("aesop_control_tick_errors", "Ticks that raised",
                              registry=registry)
        self.state_age = Histogram(
            "aesop_control_state_age_seconds", "Age of the vehicle state a tick planned from "
            "(since it was valid, through the vehicle's clock)", registry=registry,
            buckets=(.002, .005, .01, .02, .05, .1, .2, .5, 1.0))
        self.state_stale = Counter("aesop_control_stale_state_ticks", "Ticks without a fresh "
                                   "vehicle state (flown blind, counted as anomalies)",
                                   registry=registry)
        self.state_refused = Counter(
            "aesop_control_state_refusals", "Vehicle states refused, by reason (frame, finite, "
            "attitude, speed, older, seq, future, late, jump)", ["reason"], registry=registry)
        self.clock_refused = Counter("aesop_control_clock_refusals", "Times the vehicle's "
                                     "clock answers were refused (another time base than "
                                     "its states')", registry=registry)
        self.setpoints = Counter("aesop_control_setpoints", "Set-points sent to the vehicle",
                                 registry=registry)
        for mode in Mode:
            self.mode.labels(mode.value).set(1.0 if mode is Mode.WAITING else 0.0)

    def timing(self, timing: TickTiming) -> None:
        self.ticks.inc()
        self.jitter.observe(max(0.0, timing.jitter_s))
        if timing.overrun:
            self.overruns.inc()
            self.missed.inc(timing.missed)

    def result(self, result: TickResult) -> None:
        self.step.observe(result.step_ms / 1000.0)
        for mode in Mode:
            self.mode.labels(mode.value).set(1.0 if mode is result.output.mode else 0.0)
        self.stale.inc(int(result.stale))
        self.requests.inc(int(result.request is not None))
        self.setpoints.inc(int(result.setpoint is not None))
        if result.output.mode is not Mode.WAITING:
            if result.vehicle.fresh and result.vehicle.age is not None:
                self.state_age.observe(result.vehicle.age)
            else:
                self.state_stale.inc()
        for event in result.events:
            if event.kind == "verdict_stale":
                self.stale_alarms.inc()
            elif event.kind == "fallback":
                self.fallbacks.inc()
            elif event.kind == "clock_refused":
                self.clock_refused.inc()
        for reason in result.vehicle.refusals:  # every one, where the alarm says a run once
            self.state_refused.labels(reason).inc()


def sync_clock(bus: Bus, robot: str, clock: ClockMap, period_s: float,
               stop: threading.Event) -> None:
    """Query ``robot``'s vehicle clock every ``period_s`` (a burst of three: the shortest
    round trip wins) into ``clock`` until ``stop`` is set. A vehicle that does not
    answer is no fault: the clock map falls back to arrivals."""
    key = topics.vehicle_clock(robot)
    while True:
        for _ in range(3):
            sent = time.monotonic()
            try:
                answers = bus.ask(key, VehicleClock, timeout=0.5)
            except Exception as exc:  # a closed bus on shutdown, a refused query
                log.debug("clock query failed: %s", exc)
                break
            for got in answers:
                clock.sample(sent, got.received_at, got.message.stamp)
        if stop.wait(period_s):
            return


class VehicleAges:
    """A window of the vehicle state's age at the ticks that flew on a fresh one (ms), and
    the counts behind ``GET /v1/state``'s ``vehicle``."""

    def __init__(self, window: int = 1000) -> None:
        self.ages_ms: deque[float] = deque(maxlen=window)
        self.stale_ticks = 0
        self.setpoints = 0

    def record(self, result: TickResult) -> None:
        self.setpoints += result.setpoint is not None
        if result.output.mode is Mode.WAITING:
            return
        if result.vehicle.fresh and result.vehicle.age is not None:
            self.ages_ms.append(result.vehicle.age * 1000.0)
        else:
            self.stale_ticks += 1

    def summary(self) -> dict[str, float | int | None]:
        return {**spread(self.ages_ms, "age"), "stale_ticks": self.stale_ticks,
                "setpoints": self.setpoints}


class ControlService:
    """The runtime driven at its rate (``rate_hz``, else the scene's 1 / dt) with its inputs
    and outputs on the bus.

    ``bus`` may be None (no Zenoh): every tick then sees no verdict, which is
    the fail-safe anomaly, and nothing is published.
    """

    def __init__(self, settings: ControlSettings, runtime: ControlRuntime, bus: Bus | None,
                 metrics: ControlMetrics, *, owns_bus: bool = False) -> None:
        self.settings, self.runtime, self.bus, self.metrics = settings, runtime, bus, metrics
        self.owns_bus = owns_bus
        robot = settings.robot
        self.verdicts: Latest[AnomalyVerdict] | None = None
        self.decisions: Latest[ReasonerDecision] | None = None
        self.observations: Latest[Observation] | None = None
        self.states: Latest[VehicleState] | None = None
        if bus is not None:
            self.verdicts = bus.latest(topics.anomaly(robot), AnomalyVerdict)
            self.decisions = bus.latest(topics.reasoner_decision(robot), ReasonerDecision)
            self.observations = bus.latest(topics.observation(robot), Observation)
            self.states = bus.latest(topics.vehicle_state(robot), VehicleState)
        self.scheduler = FixedRateScheduler(runtime.period_s, window=settings.tuning.stats_window)
        self.ages = VehicleAges(settings.tuning.stats_window)
        self._sync_stop = threading.Event()
        self._sync_thread: threading.Thread | None = None
        self._last_error_log: float | None = None
        self._thread: threading.Thread | None = None
        self._regions_of: Scenario | None = None  # the scene whose regions went out last
        self._regions_at = 0.0  # monotonic s when they did
        self._switch = sys.getswitchinterval()

    def start(self) -> None:
        """Run the loop on its own thread (the tick thread); Python hands that thread the
        GIL within ``switch_interval_s`` of its wake-up (the default, 5 ms, is a tenth of a
        20 Hz period)."""
        self._switch = sys.getswitchinterval()
        sys.setswitchinterval(self.settings.tuning.switch_interval_s)
        self._thread = threading.Thread(target=self.scheduler.run, args=(self._tick,),
                                        kwargs={"on_tick": self.metrics.timing},
                                        name="control-tick", daemon=True)
        self._thread.start()
        if self.bus is not None and self.settings.vehicle.clock_sync_s > 0:
            self._sync_stop.clear()
            self._sync_thread = threading.Thread(target=self._sync_clock, name="control-clock",
                                                 daemon=True)
            self._sync_thread.start()

    def _sync_clock(self) -> None:
        assert self.bus is not None
        sync_clock(self.bus, self.settings.robot, self.runtime.vehicle.clock,
                   self.settings.vehicle.clock_sync_s, self._sync_stop)

    def _tick(self, deadline: float) -> None:
        try:
            verdict = self.verdicts.get() if self.verdicts else None
            decision = self.decisions.get() if self.decisions else None
            observation = self.observations.get() if self.observations else None
            state = self.states.get() if self.states else None
            result = self.runtime.tick(
                deadline=deadline, verdict=verdict,
                decision=None if decision is None else decision.message, observation=observation,
                state=state)
            self._publish(result)
            self.metrics.result(result)
            self.ages.record(result)
        except Exception:  # one bad tick must not stop the loop; it is counted and logged
            self.metrics.errors.inc()
            now = time.monotonic()
            if self._last_error_log is None or now - self._last_error_log > _ERROR_LOG_INTERVAL_S:
                self._last_error_log = now
                log.exception("control tick failed")

    def _publish(self, result: TickResult) -> None:
        if self.bus is None:
            return
        robot = self.settings.robot
        if result.setpoint is not None:  # first: the vehicle is waiting for it
            self.bus.publish(topics.vehicle_setpoint(robot), result.setpoint)
        if result.request is not None:
            self.bus.publish(topics.reasoner_request(robot), result.request)
        self.bus.publish(topics.state(robot), result.state)
        if result.plan is not None:
            self.bus.publish(topics.plan(robot), result.plan)
        for event in result.events:
            self.bus.publish(topics.event(robot, outbox.SOURCE), event)
        scenario, now = self.runtime.scenario, time.monotonic()
        if scenario is not self._regions_of or now - self._regions_at >= REGIONS_EVERY_S:
            self.bus.publish(topics.regions(robot), regions_message(scenario, robot))
            self._regions_of, self._regions_at = scenario, now

    def stop(self, timeout_s: float = 5.0) -> None:
        """End the loop after the tick in progress and wait for its thread."""
        self.scheduler.stop()
        self._sync_stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
            sys.setswitchinterval(self._switch)
        if self._sync_thread is not None:
            self._sync_thread.join(timeout_s)
            self._sync_thread = None

    def close(self) -> None:
        """Close the bus if it is ours (after the loop has ended)."""
        self.runtime.close()
        if self.owns_bus and self.bus is not None:
            self.bus.close()
