"""The control service's typed client (the demo, ``aesop bench bus``, the tests)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from shared.client import ServiceClient
from shared.messages import RegionBox

from .schemas import RegionsAnswer, ResetAnswer, State


class ControlClient(ServiceClient):
    async def state(self) -> State:
        return await self.request("GET", "/v1/state", State)

    async def regions(self) -> RegionsAnswer:
        return await self.request("GET", "/v1/regions", RegionsAnswer)

    async def set_regions(self, regions: Sequence[RegionBox | dict[str, Any]]) -> RegionsAnswer:
        """Replace the recovery regions (only while the flight is nominal or waiting)."""
        body = [r.model_dump(mode="json") if isinstance(r, RegionBox) else r for r in regions]
        return await self.request("POST", "/v1/regions", RegionsAnswer, json={"regions": body})

    async def reset(self) -> ResetAnswer:
        """Start the flight again from wherever the vehicle is (it is not moved)."""
        return await self.request("POST", "/v1/reset", ResetAnswer, json={})
