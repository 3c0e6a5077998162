"""The dashboard's routes: the page, its live stream, the flight's reads, the review, sessions.

``GET /`` (the page), ``GET /ws`` (the live stream),
``GET /v1/snapshot`` (the aggregated state), ``GET /v1/fleet`` (every robot, a line each), all
read-only, and the writes: ``POST /v1/proposals/accept|reject``, a batch review of the
detector's proposals forwarded to the embedding service; ``POST /logout`` and ``DELETE
/v1/sessions``, which end browser sessions. With a token configured the page is public and
the flight is not: a browser opened with ``/?token=`` keeps a cookie naming a server-side
session (:mod:`.sessions`: random, named for the port, expiring, revocable), good for the
reads only; the review needs the token itself in ``Authorization: Bearer`` (the page asks
for it), so no cookie can make a write.

On ``/ws`` a page first receives ``{"kind": "snapshot", "message": <snapshot>}``,
then one JSON item per update (``FlightModel.apply``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import Coroutine
from importlib.resources import files
from pathlib import Path
from typing import Annotated, Literal

import httpx
from fastapi import APIRouter, Depends, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, JSONResponse, RedirectResponse, Response
from pydantic import BaseModel, ConfigDict, Field, SecretStr

from shared.http import ApiError, errors, same_token, token_of

from .fleet import FleetSnapshot
from .hub import ClientQueue
from .model import Snapshot
from .service import DashboardService
from .sessions import SCOPE_KEY, Sessions, client_of, cookie_name
from .settings import DashboardSettings

STATIC = Path(str(files("services.dashboard") / "static"))


def _running(request: Request) -> DashboardService:
    service: DashboardService | None = request.app.state.service
    if service is None:
        raise ApiError(503, "not_ready", "the dashboard is not following the bus")
    return service


RunningDep = Annotated[DashboardService, Depends(_running)]

router = APIRouter()


# the page itself, and the end of its session; the flight (/ws, /v1/...) needs the token
PUBLIC = ("/", "/static/", "/logout")


@router.get("/", include_in_schema=False, response_model=None)
async def page(request: Request, token: str | None = None) -> Response:
    """The page. With a token configured, open it once as ``/?token=<token>``: the browser
    gets an HttpOnly, SameSite=Strict cookie ``aesop_dashboard_<port>`` (``__Host-`` and
    Secure over TLS) naming a new read-only session that expires with it after
    ``session_s``; it then sends it on ``/ws`` and ``/v1/...``. The address bar loses the
    token. No other service and no other route takes that cookie."""
    admin_token: SecretStr | None = request.app.state.admin_token
    if token is not None:
        if admin_token is None or not same_token(token, admin_token):
            raise ApiError(401, "unauthorized", "the token in the address is not this "
                           "dashboard's", "token")
        settings: DashboardSettings = request.app.state.settings
        sessions: Sessions = request.app.state.sessions
        secure = request.url.scheme == "https"
        back = RedirectResponse("/", status_code=303)
        back.set_cookie(cookie_name(settings.port, secure=secure),
                        sessions.open(client_of(request.scope)), max_age=settings.session_s,
                        httponly=True, samesite="strict", secure=secure, path="/")
        return back
    return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})


class LoggedOut(BaseModel):
    """``POST /logout``: whether the session the request named was live (and has ended)."""

    ended: bool


class Revoked(BaseModel):
    """``DELETE /v1/sessions``: how many browser sessions it ended."""

    revoked: int = Field(ge=0)


@router.post("/logout")
async def logout(request: Request, response: Response) -> LoggedOut:
    """End this browser's session (the one its cookie names, if any) and clear the
    cookie. Public: it ends only the session the request names."""
    settings: DashboardSettings = request.app.state.settings
    sessions: Sessions = request.app.state.sessions
    secure = request.url.scheme == "https"
    ended = False
    for name in (cookie_name(settings.port, secure=False),
                 cookie_name(settings.port, secure=True)):
        if name in request.cookies:
            ended = sessions.close(request.cookies[name]) or ended
    response.delete_cookie(cookie_name(settings.port, secure=secure), httponly=True,
                           samesite="strict", secure=secure, path="/")
    return LoggedOut(ended=ended)


@router.delete("/v1/sessions")
async def revoke_sessions(request: Request) -> Revoked:
    """End every browser session (the token only: a session cannot write). A restart of
    the dashboard ends them too."""
    sessions: Sessions = request.app.state.sessions
    return Revoked(revoked=sessions.revoke_all())


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
    ended = _session_ended(websocket)
    await websocket.accept()
    client = service.hub.connect()  # before the snapshot, so nothing falls between
    try:
        await websocket.send_text(json.dumps(
            {"kind": "snapshot", "message": service.snapshot()}, allow_nan=False))
        await _pump(websocket, client, ended)
    except (WebSocketDisconnect, RuntimeError, OSError):
        pass  # the page went away mid-send
    finally:
        if ended is not None:
            ended.close()  # never awaited when the page left first
        service.hub.disconnect(client)


def _session_ended(websocket: WebSocket) -> Coroutine[None, None, None] | None:
    """What returns once the browser session the WebSocket was let in by ends; None when
    it came with the token itself, or no token is configured."""
    session: str | None = websocket.scope.get(SCOPE_KEY)
    admin_token: SecretStr | None = websocket.app.state.admin_token
    if session is None or admin_token is None \
            or same_token(token_of(websocket.headers), admin_token):
        return None
    sessions: Sessions = websocket.app.state.sessions
    return sessions.until_ended(session, client_of(websocket.scope))


async def _pump(websocket: WebSocket, client: ClientQueue,
                ended: Coroutine[None, None, None] | None = None) -> None:
    """Send queued items until the page leaves, the service stops or the session that let
    the page in ends (closed with 1008, as a refusal)."""
    sender = asyncio.create_task(_send(websocket, client))
    receiver = asyncio.create_task(_until_disconnect(websocket))
    tasks = {sender, receiver}
    watch = asyncio.create_task(ended) if ended is not None else None
    if watch is not None:
        tasks.add(watch)
    done, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    for task in pending:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, RuntimeError):
            await task
    for task in done:
        task.result()
    if watch in done and sender not in done and receiver not in done:
        await websocket.close(code=1008, reason="the session ended: open /?token= again")


async def _send(websocket: WebSocket, client: ClientQueue) -> None:
    while (item := await client.get()) is not None:
        await websocket.send_text(item)
    await websocket.close(code=1001)  # going away: the service is stopping


async def _until_disconnect(websocket: WebSocket) -> None:
    while (await websocket.receive())["type"] != "websocket.disconnect":
        pass
