"""The simulated vehicle as a process on the bus: :class:`.vehicle.SimVehicle` in real time.

One thread (the sim thread) keeps the truth at the wall clock: it sleeps until the
next state is due or a set-point arrives (the subscription's callback wakes it, so a
set-point is applied within a fraction of a millisecond of its arrival), integrates
to now, applies the newest set-point and publishes the states due on
``aesop/{robot}/vehicle/state``, and its truth (exact, at the trace's rate) on
``aesop/{robot}/vehicle/truth``. It answers clock queries on
``aesop/{robot}/vehicle/clock`` with what its clock reads, and reset queries on
``aesop/{robot}/vehicle/reset`` (:class:`~shared.messages.VehicleReset`: at rest there,
as ``POST /v1/reset`` does). The HTTP routes reset, teleport and inject faults under the
same lock. The bus declares ``aesop/health/sim``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from shared import topics
from shared.bus import Bus, Latest, Received
from shared.messages import VehicleClock, VehicleReset, VehicleSetpoint, VehicleState

from .settings import SimSettings
from .start import StartError, start_state
from .vehicle import Faults, SetpointAges, SimVehicle, state_message

log = logging.getLogger(__name__)

SERVICE = "sim"
_ERROR_LOG_INTERVAL_S = 10.0


def epoch_clock() -> Callable[[], float]:
    """Seconds since the epoch that never jump: the monotonic clock, shifted once."""
    shift = time.time() - time.monotonic()
    return lambda: time.monotonic() + shift


class SimMetrics:
    def __init__(self, registry: CollectorRegistry) -> None:
        self.states = Counter("aesop_sim_states", "Vehicle states published", registry=registry)
        self.setpoints = Counter("aesop_sim_setpoints", "Set-points taken", registry=registry)
        self.setpoint_age = Histogram(
            "aesop_sim_setpoint_age_seconds", "A set-point's age when it arrived (the "
            "vehicle's clock minus its t)", registry=registry,
            buckets=(.002, .005, .01, .02, .05, .1, .2, .5, 1.0))
        self.holding = Gauge("aesop_sim_holding", "1 while the vehicle holds on its own",
                             registry=registry)


@dataclass(frozen=True)
class TracePoint:
    t: float  # simulated s since the last reset
    x: tuple[float, ...]  # the truth
    holding: bool


class SimService:
    """The sim thread, the bus and the lock the routes share (module docstring)."""

    def __init__(self, settings: SimSettings, vehicle: SimVehicle, bus: Bus | None,
                 metrics: SimMetrics, *, clock: Callable[[], float], owns_bus: bool = False
                 ) -> None:
        self.settings, self.vehicle, self.bus, self.metrics = settings, vehicle, bus, metrics
        self.clock, self.owns_bus = clock, owns_bus
        self.lock = threading.Lock()
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self.setpoints: Latest[VehicleSetpoint] | None = None
        self._taken: Received[VehicleSetpoint] | None = None
        self.trace: deque[TracePoint] = deque(maxlen=settings.trace.points)
        self._traced_at = -np.inf
        self.reset_at = vehicle.now  # when the current flight began (the clock's time)
        self.published = 0
        self._last_error_log: float | None = None
        if bus is not None:
            robot = settings.robot
            self.setpoints = bus.latest(topics.vehicle_setpoint(robot), VehicleSetpoint,
                                        on_update=self._wake.set)
            self._states_key = topics.vehicle_state(robot)
            self._truth_key = topics.vehicle_truth(robot)
            bus.answer(topics.vehicle_clock(robot),
                       lambda: VehicleClock(robot=robot, stamp=self.vehicle.clock(self.clock())))
            bus.serve(topics.vehicle_reset(robot), VehicleReset, self._reset_asked)

    # ----------------------------------------------------------------- the thread

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="sim", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        shift = self.clock() - time.monotonic()  # Received.received_at is monotonic
        while not self._stopping.is_set():
            try:
                self._once(shift)
            except Exception:  # one bad step must not stop the vehicle; logged, rate-limited
                now = time.monotonic()
                if self._last_error_log is None or \
                        now - self._last_error_log > _ERROR_LOG_INTERVAL_S:
                    self._last_error_log = now
                    log.exception("simulation step failed")
                time.sleep(0.01)

    def _say_refused(self, before: dict[str, int], seq: int) -> None:
        """Log the first set-point refused for a reason no loop should give (a far-future
        instant, a validity past the bound): a forged or broken sender."""
        for reason in ("future", "validity"):
            count = self.vehicle.ages.refusals.get(reason, 0)
            if count > before.get(reason, 0) and count == 1:
                log.warning("set-point %d refused (%s): counted in /v1/state's setpoints", seq,
                            "for an instant past the vehicle's clock" if reason == "future"
                            else "valid for too long")

    def _once(self, shift: float) -> None:
        with self.lock:
            due = self.vehicle.next_event()
        self._wake.wait(max(0.0, min(due - self.clock(), 0.05)))
        self._wake.clear()
        with self.lock:
            got = self.setpoints.get() if self.setpoints is not None else None
            if got is not None and got is not self._taken:
                self._taken = got
                refusals = dict(self.vehicle.ages.refusals)
                if self.vehicle.receive(got.message, got.received_at + shift):
                    self.metrics.setpoints.inc()
                    self.metrics.setpoint_age.observe(max(0.0, self.vehicle.ages.ages_s[-1]))
                else:
                    self._say_refused(refusals, got.message.seq)
            now = self.clock()
            reports = self.vehicle.advance(now)
            self.metrics.holding.set(1.0 if self.vehicle.holding else 0.0)
            truth: VehicleState | None = None
            if now - self._traced_at >= 1.0 / self.settings.trace.hz:
                self._traced_at = now
                self.trace.append(TracePoint(
                    round((now - self.reset_at) * self.vehicle.time_scale, 4),
                    tuple(float(v) for v in self.vehicle.truth), self.vehicle.holding))
                truth = self._truth_now()
        if self.bus is not None:
            for report in reports:
                self.bus.publish(self._states_key, report.state)
            if truth is not None:
                self.bus.publish(self._truth_key, truth)
        self.published += len(reports)
        self.metrics.states.inc(len(reports))

    # ----------------------------------------------------------------- the routes' side

    def reset(self, x0: np.ndarray) -> None:
        """At rest at ``x0`` from now on, the trace started again (faults cleared)."""
        with self.lock:
            now = self.clock()
            self.vehicle.reset(x0, now)
            self.vehicle.faults = Faults()
            self.vehicle.ages = SetpointAges()
            self.trace.clear()
            self._traced_at, self.reset_at = -np.inf, now
        self._wake.set()

    def _truth_now(self) -> VehicleState:
        """The truth as a state message (under the lock), stamped on the vehicle's clock."""
        x, vehicle = self.vehicle.truth, self.vehicle
        return state_message(x, x[0:3], x[3:6], seq=vehicle.seq,
                             stamp=vehicle.clock(self.clock()), robot=vehicle.robot,
                             frame=vehicle.frame)

    def _reset_asked(self, asked: VehicleReset) -> VehicleState | None:
        """A reset query (on a Zenoh thread): at rest at its position, answered with the
        truth there; one outside the fence is refused (logged, no answer)."""
        try:
            x0 = start_state(self.vehicle.scenario, asked.position, self.settings.seed)
        except StartError as exc:
            log.warning("reset query refused: %s", exc)
            return None
        self.reset(x0)
        with self.lock:
            return self._truth_now()

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stopping.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def close(self) -> None:
        if self.owns_bus and self.bus is not None:
            self.bus.close()
