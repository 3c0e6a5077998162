"""A simulated vehicle in process for the control loop's tests: the simulator's own
:class:`~services.sim.vehicle.SimVehicle` on the test's clock, its states handed to the
runtime as the bus's slot would hand them, the runtime's set-points handed back."""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from services.control.core.scenario import Scenario
from services.control.loop import ControlRuntime, TickResult, rest_at
from services.control.settings import ControlSettings
from services.sim.vehicle import Reporting, SimVehicle
from shared import topics
from shared.bus import Bus, Received
from shared.messages import AnomalyVerdict, Observation, ReasonerDecision, VehicleState


class Vehicle:
    """The vehicle a test flies: its newest published state, the set-points it follows.
    ``latency_s``: from a state's publication to its arrival at the loop."""

    def __init__(self, scenario: Scenario, start: Sequence[float], now: float,
                 reporting: Reporting | None = None, latency_s: float = 0.0,
                 robot: str = "drone1") -> None:
        self.sim = SimVehicle(scenario, rest_at(start), reporting or Reporting(), now=now,
                              robot=robot)
        self.latency_s = latency_s
        self.slot: Received[VehicleState] | None = None  # the bus's Latest slot
        self._in_flight: list[tuple[float, VehicleState]] = []
        self.setpoints = 0

    def advance(self, now: float) -> Received[VehicleState] | None:
        """The truth to ``now``; the newest state arrived by then (the slot's content)."""
        for report in self.sim.advance(now):
            self._in_flight.append((report.at + self.latency_s, report.state))
        while self._in_flight and self._in_flight[0][0] <= now + 1e-12:
            at, state = self._in_flight.pop(0)
            self.slot = Received("aesop/drone1/vehicle/state", state, at)
        return self.slot

    def follow(self, result: TickResult, now: float) -> None:
        if result.setpoint is not None:
            self.setpoints += 1
            self.sim.receive(result.setpoint, now)

    def teleport(self, position: Sequence[float], now: float) -> None:
        self.sim.reset(rest_at(position), now)


def fly_tick(rt: ControlRuntime, vehicle: Vehicle, now: float, deadline: float | None = None,
             work_s: float = 0.0, **inputs: object) -> TickResult:
    """One tick at ``now`` (its deadline: ``deadline``, else ``now``) with the vehicle's newest
    state; the set-point goes back to it ``work_s`` later (the tick's work, in wall time)."""
    result = rt.tick(deadline=now if deadline is None else deadline,
                     state=vehicle.advance(now), **inputs)  # type: ignore[arg-type]
    vehicle.follow(result, now + work_s)
    return result


class FakeClock:
    """Monotonic seconds that move only when the test moves them."""

    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


@dataclass
class Flown:
    """What a flight left: the truth at every tick, the inputs, what the loop said."""

    truth: list[np.ndarray] = field(default_factory=list)
    inputs: list[np.ndarray] = field(default_factory=list)
    results: list[TickResult] = field(default_factory=list)
    holding: list[bool] = field(default_factory=list)  # the vehicle held itself
    ticks: list[int] = field(default_factory=list)  # the index of each tick run

    def kinds(self) -> list[str]:
        return [e.kind for r in self.results for e in r.events]

    def modes(self) -> list[str]:
        return [r.state.mode.value for r in self.results]


Fault = Callable[[Vehicle, float, float], None]  # (vehicle, flight time, clock) each tick
# tick -> how late it starts and how long its work takes (s), None: it does not run at all
Starved = Callable[[int], tuple[float, float] | None]


def fly(scenario: Scenario, seconds: float, *, reporting: Reporting | None = None,
        latency_s: float = 0.0, fault: Fault | None = None, sync_every_s: float | None = 1.0,
        decide: Callable[[TickResult], int | None] | None = None,
        start: Sequence[float] | None = None, anomaly_at_s: float | None = None,
        starved: Starved | None = None) -> Flown:
    """The control runtime flying the simulated vehicle for ``seconds`` of simulated time
    at the scene's rate, the detector answering every tick with a nominal verdict.

    ``fault`` is called before each tick; ``sync_every_s``: how often the vehicle's clock
    is read as a clock query would (None: never, the arrivals are all the loop has);
    ``decide``: the reasoner, given each tick's result with a request (None: it never
    answers and the loop commits its fallback at K); ``anomaly_at_s``: from then on the
    verdicts are anomalies; ``starved``: a loop that cannot keep its rate (its ticks late, or
    missed while the vehicle flies on; the results and truths are those of the ticks run)."""
    clock = FakeClock()
    rt = ControlRuntime(ControlSettings(robot="drone1"), scenario, clock=clock)
    vehicle = Vehicle(scenario, start or scenario.start_center, clock.now, reporting,
                      latency_s)
    flown = Flown()
    decision: ReasonerDecision | None = None
    synced = -math.inf
    for k in range(round(seconds / scenario.dt)):
        deadline, t = clock.now, k * scenario.dt
        late = (0.0, 0.0) if starved is None else starved(k)
        clock.now = deadline + (late[0] if late is not None else 0.0)
        now = clock.now
        if late is None:
            vehicle.advance(now)
            clock.now = deadline + scenario.dt
            continue
        if fault is not None:
            fault(vehicle, t, now)
        if sync_every_s is not None and now - synced >= sync_every_s:
            rt.vehicle.clock.sample(now, now, vehicle.sim.clock(now))
            synced = now
        seen = Received("aesop/drone1/observation",
                        Observation(robot="drone1", seq=k, text="the red box"), now)
        anomalous = anomaly_at_s is not None and t >= anomaly_at_s - 1e-9
        verdict = Received("aesop/drone1/anomaly", AnomalyVerdict(
            robot="drone1", seq=k, score=-0.5 if anomalous else -0.9, threshold=-0.7,
            is_anomaly=anomalous, k=1,
            model="m", cache="c", cache_version=1, latency_ms=1.0), now)
        result = fly_tick(rt, vehicle, now, deadline, late[1], verdict=verdict,
                          observation=seen, decision=decision)
        if result.request is not None and decide is not None:
            choice = decide(result)
            if choice is not None:
                decision = ReasonerDecision(robot="drone1", request_id=result.request.request_id,
                                            choice=choice, source="llm", latency_ms=1.0)
        flown.truth.append(vehicle.sim.truth)
        flown.inputs.append(result.output.u)
        flown.results.append(result)
        flown.holding.append(vehicle.sim.holding)
        flown.ticks.append(k)
        clock.now = deadline + scenario.dt
    return flown


class NominalDetector:
    """A nominal observation of ``robot`` and its verdict every 50 ms, as its camera and the
    detector would publish them over ``bus``."""

    def __init__(self, bus: Bus, robot: str) -> None:
        self.bus, self.robot, self._stop, self._seq = bus, robot, threading.Event(), 0
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            self._seq += 1
            self.bus.publish(topics.observation(self.robot), Observation(
                robot=self.robot, seq=self._seq, text="the red box"))
            self.bus.publish(topics.anomaly(self.robot), AnomalyVerdict(
                robot=self.robot, seq=self._seq, score=-0.9, threshold=-0.7,
                is_anomaly=False, k=1, model="fake", cache="scene", cache_version=1,
                latency_ms=1.0))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
