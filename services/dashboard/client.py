"""The dashboard's typed client: the flight so far, as the page first draws it."""

from __future__ import annotations

from shared.client import ServiceClient

from .model import Snapshot


class DashboardClient(ServiceClient):
    async def snapshot(self) -> Snapshot:
        return await self.request("GET", "/v1/snapshot", Snapshot)
