"""The dashboard's routes: ``GET /`` (the page), ``GET /ws`` (the live stream),
``GET /v1/snapshot`` (the aggregated state), ``GET /v1/fleet`` (every robot, a line each), all
read-only, and one write:
``POST /v1/proposals/accept|reject``, a batch review of the detector's proposals forwarded
to the embedding service. With a token configured the page is public and the flight is
not: a browser opened with ``/?token=`` keeps a read-only session cookie derived from the
token (never the token), good for the reads only; the review needs the token itself in
``Authorization: Bearer`` (the page asks for it), so no cookie can make a write.

On ``/ws`` a page first receives ``{"kind": "snapshot", "message": <snapshot>}``,
then one JSON item per update (``FlightModel.apply``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from importlib.resources import files
from pathlib import Path
from typing import Annotated, Literal

import httpx
from fastapi import APIRouter, Depends, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, JSONResponse, RedirectResponse, Response
from pydantic import BaseModel, ConfigDict, Field, SecretStr

from shared.http import (
    SECURE_SESSION_COOKIE,
    SESSION_COOKIE,
    ApiError,
    errors,
    same_token,
    session_value,
)

from .fleet import FleetSnapshot
from .hub import ClientQueue
from .model import Snapshot
from .service import DashboardService
from .settings import DashboardSettings

STATIC = Path(str(files("services.dashboard") / "static"))


def _running(request: Request) -> DashboardService:
    service: DashboardService | None = request.app.state.service
    if service is None:
        raise ApiError(503, "not_ready", "the dashboard is not following the bus")
    return service


RunningDep = Annotated[DashboardService, Depends(_running)]

router = APIRouter()


PUBLIC = ("/", "/static/")  # the page itself; the flight (/ws, /v1/snapshot) needs the token


@router.get("/", include_in_schema=False, response_model=None)
async def page(request: Request, token: str | None = None) -> Response:
    """The page. With a token configured, open it once as ``/?token=<token>``: the browser
    gets an HttpOnly, SameSite=Strict cookie holding a read-only session derived from the
    token (``__Host-`` and Secure over TLS), which it then sends on ``/ws`` and
    ``/v1/snapshot``; the address bar loses the token. No other service and no other
    route takes that cookie."""
    admin_token: SecretStr | None = request.app.state.admin_token
    if token is not None:
        if admin_token is None or not same_token(token, admin_token):
            raise ApiError(401, "unauthorized", "the token in the address is not this "
                           "dashboard's", "token")
        back = RedirectResponse("/", status_code=303)
        secure = request.url.scheme == "https"
        back.set_cookie(SECURE_SESSION_COOKIE if secure else SESSION_COOKIE,
                        session_value(admin_token), httponly=True, samesite="strict",
                        secure=secure, path="/")
        return back
    return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})


@router.get("/v1/snapshot", responses=errors(503))
async def snapshot(service: RunningDep) -> Snapshot:
    return Snapshot.model_validate(service.snapshot())


@router.get("/v1/fleet", responses=errors(503))
async def fleet(service: RunningDep) -> FleetSnapshot:
    """Every robot heard from: mode, newest verdict, the request it waits on, alarms."""
    return service.fleet.snapshot(service.settings.robot)


class Review(BaseModel):
    """``POST /v1/proposals/accept|reject``: the proposals ``ids`` of cache ``cache``."""

    model_config = ConfigDict(extra="forbid")

    cache: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")  # a cache name
    ids: list[str] = Field(min_length=1, max_length=1000)


@router.post("/v1/proposals/{decision}", responses=errors(401, 404, 409, 422, 502))
async def review(decision: Literal["accept", "reject"], body: Review,
                 request: Request) -> JSONResponse:
    """Accept (or reject) the detector's pending proposals ``ids`` in one batch: forwarded
    to the embedding service (``AESOP_DASHBOARD_EMBEDDING_URL``), whose answer (the
    proposals decided and the cache after them, or its error) comes back as it is."""
    settings: DashboardSettings = request.app.state.settings
    token = settings.admin_token
    headers = {"Authorization": f"Bearer {token.get_secret_value()}"} if token else {}
    url = f"{settings.embedding_url.rstrip('/')}/v1/caches/{body.cache}/proposals/{decision}"
    try:
        async with httpx.AsyncClient(timeout=60.0) as client:
            answer = await client.post(url, json={"ids": body.ids}, headers=headers)
    except httpx.HTTPError as exc:
        raise ApiError(502, "bad_gateway", f"the embedding service at "
                       f"{settings.embedding_url} did not answer: {exc}", "embedding") from None
    if answer.status_code >= 500 or "json" not in answer.headers.get("content-type", ""):
        raise ApiError(502, "bad_gateway", f"the embedding service answered "
                       f"{answer.status_code}", "embedding")
    return JSONResponse(answer.json(), status_code=answer.status_code)


@router.websocket("/ws")
async def stream(websocket: WebSocket) -> None:
    service: DashboardService | None = websocket.app.state.service
    if service is None:
        await websocket.close(code=1013)  # try again later
        return
    await websocket.accept()
    client = service.hub.connect()  # before the snapshot, so nothing falls between
    try:
        await websocket.send_text(json.dumps(
            {"kind": "snapshot", "message": service.snapshot()}, allow_nan=False))
        await _pump(websocket, client)
    except (WebSocketDisconnect, RuntimeError, OSError):
        pass  # the page went away mid-send
    finally:
        service.hub.disconnect(client)


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
