"""The dashboard's app: its lifespan follows the robot on the bus; it serves ``/static/*``.

The routes are in :mod:`.routes`, ``/healthz``, ``/readyz``, ``/metrics`` from ``service_app``.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles
from prometheus_client import CollectorRegistry

from shared.bus import Bus
from shared.http import service_app

from .routes import PUBLIC, STATIC, router
from .service import SERVICE, DashboardMetrics, DashboardService
from .sessions import SessionCookies, Sessions
from .settings import DashboardSettings


def create_app(settings: DashboardSettings, bus_factory: Callable[[], Bus],
               clock: Callable[[], float] = time.monotonic) -> FastAPI:
    """The app; its lifespan opens the bus (``bus_factory``) and follows the robot. The
    browser sessions (:mod:`.sessions`) expire on ``clock``, and live as long as the app."""
    registry = CollectorRegistry()
    metrics = DashboardMetrics(registry)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        with bus_factory() as bus:
            service = DashboardService(settings, bus.session, metrics)
            app.state.service = service
            task = asyncio.create_task(service.run())
            app.state.feed = task
            try:
                yield
            finally:
                app.state.service = None
                service.close()
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task

    def refresh() -> None:
        if app.state.service is not None:
            app.state.service.refresh_metrics()

    app = service_app(
        "AESOP dashboard", service=SERVICE, lifespan=lifespan, registry=registry,
        ready=lambda: _ready(app),
        refresh=refresh, admin_token=settings.admin_token,
        max_body_bytes=settings.max_body_bytes, public=PUBLIC, session_reads=True)
    app.state.service = None
    app.state.feed = None
    app.state.settings = settings
    sessions = Sessions(settings.session_s, settings.limits.sessions, clock)
    app.state.sessions = sessions
    # in front of the guard (added last: outermost), which then lets a live session read
    app.add_middleware(SessionCookies, sessions=sessions, token=settings.admin_token,
                       port=settings.port)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    app.include_router(router)
    return app


def _ready(app: FastAPI) -> dict[str, str] | None:
    """Ready while the bus is open and the feed runs (a feed that ended is not ready)."""
    if app.state.service is None:
        return {"reason": "bus not open"}
    feed: asyncio.Task[None] | None = app.state.feed
    if feed is not None and feed.done():
        return {"reason": "the feed from the bus has stopped: see the log"}
    return None
