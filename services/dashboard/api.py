"""HTTP side of the dashboard: ``GET /`` (the page), ``GET /ws`` (the live stream),
``GET /v1/snapshot`` (the aggregated state), ``/static/*``, and ``/healthz``,
``/readyz``, ``/metrics``. Everything is read-only.

On ``/ws`` a page first receives ``{"kind": "snapshot", "message": <snapshot>}``,
then one JSON item per update (``FlightModel.apply``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from importlib.resources import files
from pathlib import Path

from fastapi import FastAPI, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles
from prometheus_client import CollectorRegistry

from shared.bus import Bus
from shared.http import ApiError, service_app

from .hub import ClientQueue
from .model import Snapshot
from .service import SERVICE, DashboardMetrics, DashboardService
from .settings import DashboardSettings

STATIC = Path(str(files("services.dashboard") / "static"))


def create_app(settings: DashboardSettings, bus_factory: Callable[[], Bus]) -> FastAPI:
    """The app; its lifespan opens the bus (``bus_factory``) and follows the robot."""
    registry = CollectorRegistry()
    metrics = DashboardMetrics(registry)
    holder: dict[str, DashboardService] = {}

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        with bus_factory() as bus:
            service = DashboardService(settings, bus.session, metrics)
            holder["service"] = service
            task = asyncio.create_task(service.run())
            try:
                yield
            finally:
                holder.pop("service")
                service.close()
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task

    def running() -> DashboardService:
        service = holder.get("service")
        if service is None:
            raise ApiError(503, "not_ready", "the dashboard is not following the bus")
        return service

    def refresh() -> None:
        if "service" in holder:
            holder["service"].refresh_metrics()

    app = service_app(
        "AESOP dashboard", service=SERVICE, lifespan=lifespan, registry=registry,
        ready=lambda: None if "service" in holder else {"reason": "bus not open"},
        refresh=refresh)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/", include_in_schema=False)
    async def page() -> FileResponse:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    @app.get("/v1/snapshot")
    async def snapshot() -> Snapshot:
        return Snapshot.model_validate(running().model.snapshot())

    @app.websocket("/ws")
    async def stream(websocket: WebSocket) -> None:
        service = holder.get("service")
        if service is None:
            await websocket.close(code=1013)  # try again later
            return
        await websocket.accept()
        client = service.hub.connect()  # before the snapshot, so nothing falls between
        try:
            await websocket.send_text(json.dumps(
                {"kind": "snapshot", "message": service.model.snapshot()}, allow_nan=False))
            await _pump(websocket, client)
        except (WebSocketDisconnect, RuntimeError, OSError):
            pass  # the page went away mid-send
        finally:
            service.hub.disconnect(client)

    return app


async def _pump(websocket: WebSocket, client: ClientQueue) -> None:
    """Send queued items until the page leaves or the service stops."""
    sender = asyncio.create_task(_send(websocket, client))
    receiver = asyncio.create_task(_until_disconnect(websocket))
    done, pending = await asyncio.wait({sender, receiver},
                                       return_when=asyncio.FIRST_COMPLETED)
    for task in pending:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, RuntimeError):
            await task
    for task in done:
        task.result()


async def _send(websocket: WebSocket, client: ClientQueue) -> None:
    while (item := await client.get()) is not None:
        await websocket.send_text(item)
    await websocket.close(code=1001)  # going away: the service is stopping


async def _until_disconnect(websocket: WebSocket) -> None:
    while (await websocket.receive())["type"] != "websocket.disconnect":
        pass
