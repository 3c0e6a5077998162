"""The dashboard as a service: the robot's bus stream folded into the model and fanned out.

It follows the robot's topics (the recovery regions and the goal included) and
the services' liveliness (``feed.follow``), and every robot's state, verdicts, requests,
decisions and events for the fleet overview (:mod:`.fleet`). The bus declares
``aesop/health/dashboard``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Callable

import zenoh
from prometheus_client import CollectorRegistry, Counter, Gauge

from shared import topics

from .feed import Update, follow
from .fleet import KINDS, FleetModel
from .hub import Hub
from .model import FlightModel, Limits
from .settings import DashboardSettings

log = logging.getLogger(__name__)

SERVICE = "dashboard"
OWN_ONLY = ("plan", "regions")  # followed for the dashboard's own robot only


class DashboardMetrics:
    def __init__(self, registry: CollectorRegistry) -> None:
        self.updates = Counter("aesop_dashboard_updates", "Updates received, by kind",
                               ["kind"], registry=registry)
        self.clients = Gauge("aesop_dashboard_clients", "Pages connected to /ws",
                             registry=registry)
        self.dropped = Gauge("aesop_dashboard_dropped_items", "Items dropped for slow pages "
                             "since start", registry=registry)


class DashboardService:
    """Model + hub fed from a Zenoh session; ``run`` until cancelled."""

    def __init__(self, settings: DashboardSettings, session: zenoh.Session,
                 metrics: DashboardMetrics, *, clock: Callable[[], float] = time.time) -> None:
        self.settings, self.session, self.metrics, self.clock = settings, session, metrics, clock
        kept = settings.limits
        limits = Limits(kept.trail, kept.scores, kept.log)
        self.model = FlightModel(settings.robot, limits)
        self.fleet = FleetModel()
        self.hub = Hub(kept.client_queue)

    def on_update(self, update: Update) -> None:
        item = self.model.apply(update)
        self.metrics.updates.labels(update.kind).inc()
        self.hub.publish(json.dumps(item, allow_nan=False))

    def snapshot(self) -> dict[str, object]:
        """The flight so far (:meth:`.FlightModel.snapshot`), and whether a batch review
        needs the admin token (the page then asks for it before it sends one)."""
        return {**self.model.snapshot(), "review_token": self.settings.admin_token is not None}

    async def run(self) -> None:
        """Every robot's state, verdicts, requests, decisions and events once (the fleet
        table; its own robot's also into the model), and the services' liveliness; its own
        robot's plans and regions."""
        async with asyncio.TaskGroup() as group:
            group.create_task(follow(self.session, topics.ANY_ROBOT, self._on_any,
                                     clock=self.clock, kinds=KINDS))
            group.create_task(follow(self.session, self.settings.robot, self.on_update,
                                     clock=self.clock, kinds=OWN_ONLY, health=False))

    def _on_any(self, update: Update) -> None:
        self.fleet.apply(update)
        if update.kind == "health" or topics.robot_of(update.topic) == self.settings.robot:
            self.on_update(update)

    def refresh_metrics(self) -> None:
        self.metrics.clients.set(len(self.hub.clients))
        self.metrics.dropped.set(self.hub.dropped)

    def close(self) -> None:
        self.hub.close()
