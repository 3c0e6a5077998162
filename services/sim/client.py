"""The simulator's typed client (the demo, the benchmarks, the tests)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from shared.client import ServiceClient

from .schemas import SimState, TraceAnswer


class SimClient(ServiceClient):
    async def state(self) -> SimState:
        return await self.request("GET", "/v1/state", SimState)

    async def trace(self) -> TraceAnswer:
        return await self.request("GET", "/v1/trace", TraceAnswer)

    async def reset(self, start: Sequence[float] | None = None) -> SimState:
        """At rest at ``start`` (m), or a fresh draw from the start box."""
        body = {} if start is None else {"start": [float(v) for v in start]}
        return await self.request("POST", "/v1/reset", SimState, json=body)

    async def reporting(self, **changes: float) -> SimState:
        return await self.request("PUT", "/v1/reporting", SimState, json=changes)

    async def faults(self, **faults: Any) -> SimState:
        return await self.request("POST", "/v1/faults", SimState, json=faults)
