"""The dashboard as a service: the robot's bus stream folded into the model and fanned out.

It follows the robot's topics and the services' liveliness (``feed.follow``),
and asks the control service for the recovery regions every
``dashboard_regions_poll_s`` seconds and whenever an event says they changed.
The bus declares ``aesop/health/dashboard``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections.abc import Callable

import httpx
import zenoh
from prometheus_client import CollectorRegistry, Counter, Gauge

from .feed import Update, follow
from .hub import Hub
from .model import FlightModel, Limits, regions_message
from .settings import DashboardSettings

log = logging.getLogger(__name__)

SERVICE = "dashboard"


class DashboardMetrics:
    def __init__(self, registry: CollectorRegistry) -> None:
        self.updates = Counter("aesop_dashboard_updates", "Updates received, by kind",
                               ["kind"], registry=registry)
        self.clients = Gauge("aesop_dashboard_clients", "Pages connected to /ws",
                             registry=registry)
        self.dropped = Gauge("aesop_dashboard_dropped_items", "Items dropped for slow pages "
                             "since start", registry=registry)
        self.region_errors = Counter("aesop_dashboard_region_fetch_errors", "Failed fetches of "
                                     "the control service's regions", registry=registry)


class DashboardService:
    """Model + hub fed from a Zenoh session; ``run`` until cancelled."""

    def __init__(self, settings: DashboardSettings, session: zenoh.Session,
                 metrics: DashboardMetrics, *, clock: Callable[[], float] = time.time) -> None:
        self.settings, self.session, self.metrics, self.clock = settings, session, metrics, clock
        limits = Limits(settings.dashboard_trail, settings.dashboard_scores,
                        settings.dashboard_log)
        goal = None if settings.dashboard_goal is None else list(settings.dashboard_goal)
        self.model = FlightModel(settings.robot, limits, goal)
        self.hub = Hub(settings.dashboard_client_queue)
        self._regions_changed = asyncio.Event()

    def on_update(self, update: Update) -> None:
        item = self.model.apply(update)
        self.metrics.updates.labels(update.kind).inc()
        self.hub.publish(json.dumps(item, allow_nan=False))
        if update.kind == "event" and update.message.get("kind") == "regions_updated":
            self._regions_changed.set()

    async def run(self) -> None:
        async with asyncio.TaskGroup() as group:
            group.create_task(follow(self.session, self.settings.robot, self.on_update,
                                     clock=self.clock))
            if self.settings.dashboard_control_url:
                group.create_task(self._poll_regions())

    def refresh_metrics(self) -> None:
        self.metrics.clients.set(len(self.hub.clients))
        self.metrics.dropped.set(self.hub.dropped)

    def close(self) -> None:
        self.hub.close()

    async def _poll_regions(self) -> None:
        url = self.settings.dashboard_control_url.rstrip("/") + "/v1/regions"
        async with httpx.AsyncClient(timeout=2.0) as client:
            while True:
                message = await self._fetch_regions(client, url)
                if message is not None and (message["regions"] != self.model.regions
                                            or message["goal"] != self.model.goal):
                    self.on_update(Update("regions", url, message, self.clock()))
                self._regions_changed.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._regions_changed.wait(),
                                           self.settings.dashboard_regions_poll_s)

    async def _fetch_regions(self, client: httpx.AsyncClient, url: str) -> dict | None:
        try:
            response = await client.get(url)
            response.raise_for_status()
            message = regions_message(response.json(), self.model.goal)
        except (httpx.HTTPError, ValueError) as exc:
            self.metrics.region_errors.inc()
            log.debug("regions from %s: %s", url, exc)
            return None
        if message is None:
            self.metrics.region_errors.inc()
            log.warning("regions from %s: not a {'regions': [...]} answer", url)
        return message
