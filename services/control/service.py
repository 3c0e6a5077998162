"""The control loop as a service: Zenoh in and out around :class:`.loop.ControlRuntime`.

The loop runs on its own thread (the tick thread), not on the event loop, so
that a tick starts on time whatever the HTTP side is doing. Each tick reads
the newest ``AnomalyVerdict``, ``ReasonerDecision`` and ``Observation`` of its
robot from ``Latest`` slots (thread-safe; nothing queues up behind a slow
tick), runs the runtime, then publishes ``ControlState`` (every tick),
``PlanSnapshot`` (when the step produced a plan), ``ReasonerRequest`` (on the
detection tick), ``Event``s and ``Regions`` (on start, when they change and every
``REGIONS_EVERY_S``). The bus declares ``aesop/health/control``.
"""

from __future__ import annotations

import logging
import sys
import threading
import time

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from shared import topics
from shared.bus import Bus, Latest
from shared.messages import AnomalyVerdict, Mode, Observation, ReasonerDecision, RegionBox, Regions

from .loop import ControlRuntime, FixedRateScheduler, TickResult, TickTiming
from .scenario import Scenario
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
        for event in result.events:
            if event.kind == "verdict_stale":
                self.stale_alarms.inc()
            elif event.kind == "fallback":
                self.fallbacks.inc()


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
        if bus is not None:
            self.verdicts = bus.latest(topics.anomaly(robot), AnomalyVerdict)
            self.decisions = bus.latest(topics.reasoner_decision(robot), ReasonerDecision)
            self.observations = bus.latest(topics.observation(robot), Observation)
        self.scheduler = FixedRateScheduler(runtime.period_s, window=settings.stats_window)
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
        sys.setswitchinterval(self.settings.switch_interval_s)
        self._thread = threading.Thread(target=self.scheduler.run, args=(self._tick,),
                                        kwargs={"on_tick": self.metrics.timing},
                                        name="control-tick", daemon=True)
        self._thread.start()

    def _tick(self, deadline: float) -> None:
        try:
            verdict = self.verdicts.get() if self.verdicts else None
            decision = self.decisions.get() if self.decisions else None
            observation = self.observations.get() if self.observations else None
            result = self.runtime.tick(
                deadline=deadline, verdict=verdict,
                decision=None if decision is None else decision.message, observation=observation)
            self._publish(result)
            self.metrics.result(result)
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
        if result.request is not None:
            self.bus.publish(topics.reasoner_request(robot), result.request)
        self.bus.publish(topics.state(robot), result.state)
        if result.plan is not None:
            self.bus.publish(topics.plan(robot), result.plan)
        for event in result.events:
            self.bus.publish(topics.event(robot), event)
        scenario, now = self.runtime.scenario, time.monotonic()
        if scenario is not self._regions_of or now - self._regions_at >= REGIONS_EVERY_S:
            self.bus.publish(topics.regions(robot), regions_message(scenario, robot))
            self._regions_of, self._regions_at = scenario, now

    def stop(self, timeout_s: float = 5.0) -> None:
        """End the loop after the tick in progress and wait for its thread."""
        self.scheduler.stop()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
            sys.setswitchinterval(self._switch)

    def close(self) -> None:
        """Close the bus if it is ours (after the loop has ended)."""
        if self.owns_bus and self.bus is not None:
            self.bus.close()
