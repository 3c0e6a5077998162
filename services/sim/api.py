"""The simulator's app: its lifespan runs the sim thread and opens the bus.

The routes are in :mod:`.routes`, ``/healthz``, ``/readyz``, ``/metrics`` from ``service_app``."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

from fastapi import FastAPI
from prometheus_client import CollectorRegistry

from services.control.core.scenario import Scenario
from shared.bus import Bus
from shared.http import service_app

from .routes import router
from .service import SERVICE, SimMetrics, SimService, epoch_clock
from .settings import SimSettings
from .start import start_state
from .vehicle import SimVehicle


def create_app(settings: SimSettings, scenario: Scenario,
               bus_factory: Callable[[], Bus] | None = None,
               clock: Callable[[], float] | None = None) -> FastAPI:
    """The app; its lifespan opens the bus (``bus_factory``) and runs the vehicle."""
    registry = CollectorRegistry()
    metrics = SimMetrics(registry)
    now = clock or epoch_clock()
    x0 = start_state(scenario, settings.start_position, settings.seed)  # StartError: at once

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        bus = bus_factory() if bus_factory is not None else None
        vehicle = SimVehicle(scenario, x0, settings.reporting(), now=now(),
                             time_scale=settings.time_scale, robot=settings.robot,
                             frame=settings.frame, seed=settings.seed)
        service = SimService(settings, vehicle, bus, metrics, clock=now,
                             owns_bus=bus is not None)
        app.state.service = service
        service.start()
        try:
            yield
        finally:
            await asyncio.to_thread(service.stop)
            service.close()

    limits = scenario.limits
    inside = {"prefixItems": [{"type": "number", "minimum": lo, "maximum": hi}
                              for lo, hi in zip(limits.position_lo, limits.position_hi,
                                                strict=True)]}
    app = service_app(
        "AESOP simulated vehicle", service=SERVICE, lifespan=lifespan, registry=registry,
        ready=lambda: None if getattr(app.state, "service", None) is not None
        and app.state.service.published > 0 else {"reason": "no state published yet"},
        admin_token=settings.admin_token, max_body_bytes=settings.max_body_bytes,
        limits={"ResetBody": {"start": inside}})
    app.state.settings = settings
    app.include_router(router)
    return app
