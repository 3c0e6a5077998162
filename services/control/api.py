"""The control-loop service's app: its lifespan runs the loop and opens the bus.

The routes are in :mod:`.routes`, ``/healthz``, ``/readyz``, ``/metrics`` from ``service_app``.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

from fastapi import FastAPI
from prometheus_client import CollectorRegistry

from shared.bus import Bus
from shared.http import service_app

from .loop import ControlRuntime
from .routes import router
from .service import SERVICE, ControlMetrics, ControlService
from .settings import ControlSettings


def create_app(settings: ControlSettings, runtime: ControlRuntime,
               bus_factory: Callable[[], Bus] | None = None) -> FastAPI:
    """The app; its lifespan opens the bus (``bus_factory``) and runs the loop."""
    registry = CollectorRegistry()
    metrics = ControlMetrics(registry)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        bus = bus_factory() if bus_factory is not None else None
        service = ControlService(settings, runtime, bus, metrics, owns_bus=bus is not None)
        app.state.service = service
        service.start()
        try:
            yield
        finally:
            await asyncio.to_thread(service.stop)
            service.close()

    limits = runtime.scenario.limits  # the fence: positions outside it are refused
    inside = {"prefixItems": [{"type": "number", "minimum": lo, "maximum": hi}
                              for lo, hi in zip(limits.position_lo, limits.position_hi,
                                                strict=True)]}
    app = service_app(
        "AESOP control-loop service", service=SERVICE, lifespan=lifespan, registry=registry,
        ready=lambda: None if runtime.last is not None else {"reason": "no tick yet"},
        admin_token=settings.admin_token,
        max_body_bytes=settings.max_body_bytes,
        limits={"RegionIn": {"position_lo": inside, "position_hi": inside}})
    app.state.runtime, app.state.settings = runtime, settings
    app.include_router(router)
    return app
