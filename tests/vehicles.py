"""A simulated vehicle in process for the control loop's tests: the simulator's own
:class:`~services.sim.vehicle.SimVehicle` on the test's clock, its states handed to the
runtime as the bus's slot would hand them, the runtime's set-points handed back."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from services.control.dynamics import N_STATE
from services.control.loop import ControlRuntime, TickResult
from services.control.scenario import Scenario
from services.sim.vehicle import Reporting, SimVehicle
from shared.bus import Received
from shared.messages import VehicleState


def rest(position: Sequence[float]) -> np.ndarray:
    x = np.zeros(N_STATE)
    x[0:3] = position
    return x


class Vehicle:
    """The vehicle a test flies: its newest published state, the set-points it follows.
    ``latency_s``: from a state's publication to its arrival at the loop."""

    def __init__(self, scenario: Scenario, start: Sequence[float], now: float,
                 reporting: Reporting | None = None, latency_s: float = 0.0,
                 robot: str = "drone1") -> None:
        self.sim = SimVehicle(scenario, rest(start), reporting or Reporting(), now=now,
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
        self.sim.reset(rest(position), now)


def fly_tick(rt: ControlRuntime, vehicle: Vehicle, now: float, **inputs: object) -> TickResult:
    """One tick at ``now`` with the vehicle's newest state; the set-point goes back to it."""
    result = rt.tick(deadline=now, state=vehicle.advance(now), **inputs)  # type: ignore[arg-type]
    vehicle.follow(result, now)
    return result
