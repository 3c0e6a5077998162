"""The vehicle a demo flight is flown with: the simulator over HTTP, or any vehicle on the bus.

The simulator over its HTTP API, or any vehicle over the vehicle contract alone
(docs/architecture.md, section 3a).

A flight needs three things of its vehicle: to start at rest at the scenario's start
(:meth:`reset`), where it really flew (:meth:`flown`: 12-state rows, the layout of
:mod:`services.control.core.dynamics`, judged by :func:`services.sim.judge.count_violations`)
and, where the vehicle says, how old the set-points were when they reached it.

- :class:`SimVehicle`: ``aesop serve sim``'s ``/v1/reset``, its truth trace and its
  set-point ages (``/v1/state``).
- :class:`BusVehicle`: any vehicle on the bus. It is reset by a query on
  ``aesop/{robot}/vehicle/reset`` when it answers one (a simulator; a real vehicle need
  not: the demo then waits for an operator to bring it to the start); a flight is judged
  on the vehicle's truth (``aesop/{robot}/vehicle/truth``) where it publishes one, else on
  the states it reports. It knows no set-point ages.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Mapping, Sequence
from typing import Protocol

import numpy as np

from services.sim.client import SimClient
from shared import topics
from shared.bus import Bus, Received
from shared.frames import euler_from_quaternion
from shared.messages import VehicleReset, VehicleState

log = logging.getLogger(__name__)

RESET_TIMEOUT_S = 5.0  # for the vehicle's answer to a reset query
MAX_ROWS = 200_000  # states kept per flight (about 30 min at 100 Hz)


class FlightVehicle(Protocol):
    async def reset(self, start: Sequence[float]) -> None:
        """At rest at ``start`` (m) before a flight, where the vehicle can be moved there."""

    async def flown(self) -> tuple[np.ndarray, Mapping[str, float | int | None]]:
        """Where it flew since :meth:`reset` (12-state rows) and its set-points' ages
        (``age_p50_ms``, ``age_p99_ms``, ``age_max_ms``; empty when it does not say)."""

    async def rate_hz(self) -> float | None:
        """How often it reports its state (None: not known)."""


class SimVehicle:
    """``aesop serve sim`` over HTTP."""

    def __init__(self, sim: SimClient) -> None:
        self.sim = sim

    async def reset(self, start: Sequence[float]) -> None:
        await self.sim.reset(start)

    async def flown(self) -> tuple[np.ndarray, Mapping[str, float | int | None]]:
        vehicle, trace = await self.sim.state(), await self.sim.trace()
        # judged where the vehicle is now, on its own clock: it counts from its reset,
        # which came before the loop's first tick (the loop waits for a verdict and warms
        # up), so the loop's t lags it (by seconds on a loaded machine)
        truth = np.array([x for t, x in zip(trace.t, trace.x, strict=True)
                          if t <= vehicle.t + 1e-9])
        return truth, vehicle.setpoints

    async def rate_hz(self) -> float | None:
        return float((await self.sim.state()).reporting["rate_hz"])


def state_row(state: VehicleState) -> np.ndarray:
    """A contract state as a 12-state row: position, velocity, Z-Y-X Euler angles, body
    rates."""
    return np.array([*state.position, *state.velocity,
                     *euler_from_quaternion(state.attitude), *state.body_rates], dtype=float)


class BusVehicle:
    """Any vehicle on the bus ``bus`` (the robot's session): see the module docstring."""

    def __init__(self, bus: Bus, robot: str) -> None:
        self.bus, self.robot = bus, robot
        self._lock = threading.Lock()
        self._states: list[VehicleState] = []
        self._truth: list[VehicleState] = []
        self._arrivals: list[float] = []
        self._asked = False  # whether the vehicle has been asked to reset yet
        self._answers = True  # whether it answered the last reset query
        bus.each(topics.vehicle_state(robot), VehicleState, self._on_state)
        bus.each(topics.vehicle_truth(robot), VehicleState, self._on_truth)

    def _on_state(self, got: Received[VehicleState]) -> None:
        with self._lock:
            self._arrivals.append(got.received_at)
            del self._arrivals[:-1000]
            if len(self._states) < MAX_ROWS:
                self._states.append(got.message)

    def _on_truth(self, got: Received[VehicleState]) -> None:
        with self._lock:
            if len(self._truth) < MAX_ROWS:
                self._truth.append(got.message)

    async def reset(self, start: Sequence[float]) -> None:
        ask = VehicleReset(robot=self.robot, position=tuple(float(v) for v in start))
        answers = await asyncio.to_thread(self.bus.ask, topics.vehicle_reset(self.robot),
                                          VehicleState, timeout=RESET_TIMEOUT_S, payload=ask)
        with self._lock:  # what came before the reset is not this flight's
            self._states, self._truth = [], []
        if not answers and (self._answers or not self._asked):
            log.warning("the vehicle answers no reset query on %s: bring it to rest at %s "
                        "(m) by hand; the flight starts once the control loop sees it "
                        "there", topics.vehicle_reset(self.robot), list(ask.position))
        self._asked, self._answers = True, bool(answers)

    async def flown(self) -> tuple[np.ndarray, Mapping[str, float | int | None]]:
        with self._lock:
            states = list(self._truth or self._states)
        states.sort(key=lambda s: s.seq)  # in the order the vehicle measured them
        rows = np.array([state_row(s) for s in states]) if states else np.empty((0, 12))
        return rows, {}

    async def rate_hz(self) -> float | None:
        with self._lock:
            arrivals = list(self._arrivals)
        if len(arrivals) < 2 or arrivals[-1] <= arrivals[0]:
            return None
        return (len(arrivals) - 1) / (arrivals[-1] - arrivals[0])
