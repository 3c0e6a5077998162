"""What every service's FastAPI app shares (``service_app``): errors, the guard, limits, ops routes.

- errors: JSON ``{"error": {"code", "message", "field"}}`` (``ErrorBody``) with a 4xx/5xx
  status, documented in ``/openapi.json`` with ``errors(...)``;
- ``Guard``: with ``AESOP_ADMIN_TOKEN`` set, every route but the ops and docs ones needs
  ``Authorization: Bearer <token>``, checked before the body is read; without it, only
  loopback ``Host`` names; no cross-site requests; bodies counted as they stream in, each
  part due within ``BODY_IDLE_S``, at most twice the body limit being read at once;
- ``ops_router``: ``/healthz``, ``/readyz`` and ``/metrics`` (Prometheus, per-app registry);
- ``docs_pages``: ``/docs`` (Swagger UI) and ``/redoc`` with their JavaScript and CSS served
  by the app itself (an offline robot reaches no CDN); they and ``/openapi.json`` are public.

Running an app (connection limits, the header timeout) is :mod:`shared.serving`.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any, TypeVar
from urllib.parse import urlsplit

import fastapi_offline
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse, PlainTextResponse, Response
from fastapi.routing import APIRouter
from fastapi.staticfiles import StaticFiles
from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Histogram,
    generate_latest,
)
from pydantic import BaseModel, ConfigDict, SecretStr
from starlette.datastructures import Headers
from starlette.exceptions import HTTPException
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

Next = Callable[[Request], Awaitable[Response]]
T = TypeVar("T")


class ApiError(Exception):
    """An error to answer as JSON: ``status``, machine ``code``, human ``message``, ``field``."""

    def __init__(self, status: int, code: str, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.status, self.code, self.message, self.field = status, code, message, field


class ErrorDetail(BaseModel):
    model_config = ConfigDict(extra="ignore")

    code: str  # machine-readable: invalid, not_found, conflict, unauthorized, too_large, ...
    message: str  # for a person
    field: str | None = None  # the request field at fault, e.g. "items[3].text"


class ErrorBody(BaseModel):
    """Every error answer of every service."""

    model_config = ConfigDict(extra="ignore")

    error: ErrorDetail


METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})
REASONS = {
    400: "the body is not valid JSON",
    401: "a valid 'Authorization: Bearer <token>' header is missing",
    403: "a cross-site request: its Origin is not the service's own",
    404: "no such resource (error.field names which)",
    405: "method not allowed (the Allow header lists those that are)",
    408: "no part of the body came for a while: send it again",
    409: "the request conflicts with the stored state",
    413: "the body or one of its lists is larger than the limit",
    415: "the body is not declared as JSON",
    422: "a field is invalid (error.field names it)",
    429: "too busy: retry later",
    502: "an upstream server failed",
    503: "not ready, or storage failed: retry later",
    507: "the disk (or the configured size limit) is full; nothing was stored",
}
REQUEST_ERRORS = (400, 413, 415, 422)  # what any route with a JSON body may answer
GUARD_ERRORS = (400, 401, 403, 408, 413, 415, 422, 503)  # what any route of a service may answer


def errors(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` for a route (or an app) that may answer these error statuses."""
    return {s: {"model": ErrorBody, "description": REASONS[s]} for s in statuses}


def document_limits(app: FastAPI, limits: dict[str, dict[str, dict[str, Any]]]) -> None:
    """Write limits that come from settings into the app's ``/openapi.json``, so the
    schema says what the service enforces: ``{model: {property: {keyword: value}}}``;
    a nested dict (e.g. ``{"items": {"maxLength": 4000}}``) is merged into the nested
    schema, and a nullable property gets the keywords on its non-null branch."""
    build = app.openapi

    def merge(target: dict[str, Any], keywords: dict[str, Any]) -> None:
        for branch in [b for b in target.get("anyOf", [target]) if b.get("type") != "null"]:
            for key, value in keywords.items():
                if isinstance(value, dict):
                    merge(branch.setdefault(key, {}), value)
                else:
                    branch[key] = value

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = build()
            models = schema["components"]["schemas"]
            for model, properties in limits.items():
                for name in (model, f"{model}-Input"):  # pydantic's name for a request model
                    if name in models:  # also used in an answer
                        for prop, keywords in properties.items():
                            merge(models[name]["properties"][prop], keywords)
        return app.openapi_schema or {}

    app.openapi = openapi  # type: ignore[method-assign]


def document_security(app: FastAPI, public: tuple[str, ...]) -> None:
    """Say in ``/openapi.json`` which operations need the bearer token (when the service
    has one: the :class:`Guard` enforces it, not the routes)."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = build()
            schema.setdefault("components", {}).setdefault("securitySchemes", {})["bearer"] = {
                "type": "http", "scheme": "bearer",
                "description": "AESOP_ADMIN_TOKEN; required when the service has one"}
            for path, operations in schema.get("paths", {}).items():
                if is_public(path, public):
                    continue
                for operation in operations.values():
                    operation["security"] = [{"bearer": []}]
        return app.openapi_schema or {}

    app.openapi = openapi  # type: ignore[method-assign]


def error_response(status: int, code: str, message: str, field: str | None = None,
                   headers: dict[str, str] | None = None) -> JSONResponse:
    body: dict[str, Any] = {"code": code, "message": message}
    if field is not None:
        body["field"] = field
    return JSONResponse({"error": body}, status_code=status, headers=headers)


def field_path(loc: tuple[Any, ...] | list[Any]) -> str:
    """('body', 'items', 3, 'text') -> 'items[3].text'. The union member pydantic tried
    (a part like 'list[constrained-str]', never a field name) is left out."""
    out = ""
    for part in loc:
        if part in ("body", "query", "path", "header") and not out:
            continue
        if isinstance(part, str) and not part.isidentifier():
            continue
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out or "body"


async def _validation_error(_: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = exc.errors()
    first: dict[str, Any] = (errors[0] if errors
                             else {"loc": ("body",), "msg": "invalid request", "type": ""})
    if first.get("type") == "json_invalid":
        return error_response(400, "malformed_json", f"request body is not valid JSON: "
                              f"{first.get('ctx', {}).get('error', first['msg'])}", "body")
    where = field_path(first["loc"])
    message = f"{where}: {first['msg']}"
    if len(errors) > 1:
        message += f" (and {len(errors) - 1} more)"
    return error_response(422, "invalid", message, where)


async def _api_error(_: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ApiError)
    return error_response(exc.status, exc.code, exc.message, exc.field)


def allowed_methods(request: Request) -> list[str]:
    """The methods some route of the app accepts at the request's path (asked of each
    route by matching, so routes of included routers count too)."""
    routes = request.app.router.routes
    return sorted(m for m in METHODS if any(
        route.matches({**request.scope, "method": m})[0] == Match.FULL for route in routes))


async def _http_error(request: Request, exc: Exception) -> Response:
    """Starlette's own errors (unknown path, wrong method, unparsable body) as ErrorBody."""
    assert isinstance(exc, HTTPException)
    headers = dict(exc.headers or {})
    if exc.status_code == 405:
        headers["Allow"] = ", ".join(allowed_methods(request))
    code = {400: "malformed_body", 404: "not_found", 405: "method_not_allowed"}.get(
        exc.status_code, "http_error")
    field = "body" if exc.status_code == 400 else None
    return error_response(exc.status_code, code, str(exc.detail), field, headers=headers)


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(HTTPException, _http_error)


def from_state(name: str, default: Any = ...) -> Callable[[Request], Any]:
    """A dependency giving ``request.app.state.<name>`` (what the app factory put there):
    ``Annotated[Settings, Depends(from_state("settings"))]``."""

    def get(request: Request) -> Any:
        if default is ...:
            return getattr(request.app.state, name)
        return getattr(request.app.state, name, default)

    return get


async def unless_client_leaves(request: Request, work: Awaitable[T]) -> T:
    """Await ``work`` (a route's heavy part) and cancel it if the client disconnects
    first: nobody would read the answer. Answers 499 to nobody in that case."""
    task = asyncio.ensure_future(work)
    watch = asyncio.ensure_future(_client_left(request))
    try:
        await asyncio.wait({task, watch}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        watch.cancel()
    if not task.done():
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        raise ApiError(499, "client_closed_request", "the client disconnected")
    return task.result()


async def _client_left(request: Request) -> None:
    while (await request.receive())["type"] != "http.disconnect":
        pass


def method_label(method: str) -> str:
    """A request's method as a metrics label: any other is ``other``, so made-up methods
    cannot grow the label set."""
    return method if method in METHODS else "other"


class HttpMetrics:
    """Request counters and latencies, in a registry owned by the app (no globals). Every
    label is bounded: the method (:func:`method_label`), the route's template (or
    ``unmatched``) and the status."""

    def __init__(self, registry: CollectorRegistry, service: str) -> None:
        self.requests = Counter("aesop_http_requests", "HTTP requests",
                                ["service", "method", "route", "status"], registry=registry)
        self.latency = Histogram("aesop_http_request_seconds", "HTTP request latency",
                                 ["service", "method", "route"], registry=registry)
        self.service = service

    def install(self, app: FastAPI) -> None:
        @app.middleware("http")
        async def measure(request: Request, call_next: Next) -> Response:
            start = time.perf_counter()
            response = await call_next(request)
            route = request.scope.get("route")
            path = getattr(route, "path", "unmatched")
            method = method_label(request.method)
            self.latency.labels(self.service, method, path).observe(time.perf_counter() - start)
            self.requests.labels(self.service, method, path, str(response.status_code)).inc()
            return response


def ops_router(
    registry: CollectorRegistry,
    ready: Callable[[], dict[str, Any] | None],
    refresh: Callable[[], None] | None = None,
) -> APIRouter:
    """``/healthz`` (the process answers), ``/readyz`` (``ready()`` returns None when ready,
    or a dict saying what is missing), ``/metrics`` (Prometheus text; ``refresh`` updates
    gauges first, on the loop; the text is rendered on a worker thread, so a scrape does
    not hold up the loop that also serves the bus)."""
    router = APIRouter()

    @router.get("/healthz")
    async def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @router.get("/readyz", responses={503: {"description": "not ready yet: says what is "
                                            "missing", "content": {"application/json": {}}}})
    async def readyz() -> Response:
        missing = ready()
        if missing:
            return JSONResponse({"status": "not_ready", **missing}, status_code=503)
        return JSONResponse({"status": "ready"})

    @router.get("/metrics", response_class=PlainTextResponse, responses={
        200: {"description": "Prometheus text format", "content": {"text/plain": {}}}})
    async def metrics() -> Response:
        if refresh is not None:
            refresh()
        text = await asyncio.to_thread(generate_latest, registry)
        return Response(text, media_type=CONTENT_TYPE_LATEST)

    return router


OPS_PATHS = ("/healthz", "/readyz", "/metrics")
# The API's description: read-only, no data, public so that an operator can read it (and use
# Swagger's Authorize button) without putting the admin token in a URL. The operations it
# describes still need the token.
DOCS_PATHS = ("/openapi.json", "/docs", "/redoc")
DOCS_ASSETS = "/docs/assets"  # the pages' JavaScript, CSS and icon, served by the app itself
# Swagger UI's and ReDoc's dist files as fastapi-offline ships them (a PyPI package, so
# nothing is vendored here and nothing is fetched at run time)
DOCS_STATIC = Path(fastapi_offline.__file__).parent / "static"
LOOPBACK_HOSTS = frozenset({"localhost", "127.0.0.1", "::1"})


class Refusal(Exception):
    """Why the guard turns a request away before any route runs."""

    def __init__(self, status: int, code: str, message: str, field: str | None,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.status, self.code, self.message, self.field = status, code, message, field
        self.headers = headers or {}


def _unrouted(scope: Scope) -> Refusal | None:
    """404 or 405 (with ``Allow``) when no route takes the request's path and method, as
    the router would say once the body was read; None when one does."""
    if "app" not in scope:
        return None
    allowed = allowed_methods(Request(scope))
    if not allowed:
        return Refusal(404, "not_found", "Not Found", None)
    if scope.get("method", "GET") not in allowed:
        return Refusal(405, "method_not_allowed", "Method Not Allowed", None,
                       {"Allow": ", ".join(allowed)})
    return None


def host_name(authority: str) -> str:
    """'127.0.0.1:8001' -> '127.0.0.1', '[::1]:80' -> '::1', 'Example.org' -> 'example.org'."""
    authority = authority.strip().lower()
    if authority.startswith("["):
        return authority[1:authority.find("]")] if "]" in authority else authority
    return authority.rsplit(":", 1)[0] if authority.count(":") == 1 else authority


# A browser's read-only session (the dashboard sets it, HttpOnly, SameSite=Strict): a
# value derived from the admin token, never the token. The __Host- name is used over TLS.
SESSION_COOKIE = "aesop_session"
SECURE_SESSION_COOKIE = "__Host-aesop_session"
_SESSION_CONTEXT = b"aesop read-only dashboard session v1"


def session_value(token: SecretStr) -> str:
    """The dashboard session a token gives: HMAC-SHA256 of a fixed context under the
    token. It opens the dashboard's reads and nothing else, and tells nothing of the
    token."""
    return hmac.new(token.get_secret_value().encode(), _SESSION_CONTEXT,
                    hashlib.sha256).hexdigest()


def token_of(headers: Headers) -> str:
    """The token a request carries: ``Authorization: Bearer <token>`` (never a cookie)."""
    scheme, _, credentials = headers.get("authorization", "").partition(" ")
    return credentials.strip() if scheme.lower() == "bearer" else ""


def session_of(headers: Headers) -> str:
    """The read-only session cookie a request carries, if any."""
    for part in headers.get("cookie", "").split(";"):
        name, _, value = part.strip().partition("=")
        if name in (SESSION_COOKIE, SECURE_SESSION_COOKIE):
            return value
    return ""


def is_public(path: str, public: tuple[str, ...]) -> bool:
    """An ops path, the API's description (:data:`DOCS_PATHS` and their assets), or one of
    ``public``: a path, or every path under one ending in '/'."""
    return path in OPS_PATHS or path in DOCS_PATHS or path.startswith(DOCS_ASSETS + "/") \
        or any(path == p or (len(p) > 1 and p.endswith("/") and path.startswith(p))
               for p in public)


def same_token(given: str, token: SecretStr) -> bool:
    return hmac.compare_digest(given.encode(), token.get_secret_value().encode())


def check_request(headers: Headers, path: str, method: str, *, token: SecretStr | None,
                  public: tuple[str, ...], session_reads: bool = False) -> None:
    """The checks made on the headers alone, in order; raises :class:`Refusal`.

    - without a token the service listens on loopback only (``check_exposure``), so a
      ``Host`` that is not a loopback name is DNS rebinding: 400;
    - an ``Origin`` that is not the service's own is a cross-site request from a web
      page (a browser always sends it there): 403;
    - with a token, every path but the :func:`is_public` ones needs it in the bearer
      header: 401; where ``session_reads`` (the dashboard), a GET, HEAD or WebSocket may
      bring the read-only session cookie (:func:`session_value`) instead;
    - a body where none belongs (a GET or HEAD, or any request to a public path) is
      refused before a byte of it is read: 400;
    - a POST/PUT/PATCH body must be declared as JSON: 415.
    """
    host = headers.get("host", "")
    if token is None and host_name(host) not in LOOPBACK_HOSTS:
        raise Refusal(400, "untrusted_host", f"Host {host!r} is not a loopback name; this "
                      "service has no token and serves loopback only", "Host")
    origin = headers.get("origin")
    if origin is not None and urlsplit(origin).netloc.lower() != host.lower():
        raise Refusal(403, "cross_origin", f"a request from {origin!r} to {host!r} is "
                      "cross-site and refused", "Origin")
    if token is not None and not is_public(path, public) \
            and not same_token(token_of(headers), token) \
            and not (session_reads and method in ("GET", "HEAD")
                     and hmac.compare_digest(session_of(headers).encode(),
                                             session_value(token).encode())):
        raise Refusal(401, "unauthorized", "a valid 'Authorization: Bearer <token>' "
                      "header is required", "Authorization")
    has_body = headers.get("content-length", "0") != "0" or "transfer-encoding" in headers
    if has_body and (method in ("GET", "HEAD") or is_public(path, public)):
        raise Refusal(400, "body_not_allowed", f"a {method} to {path} carries no body",
                      "body")
    kind = headers.get("content-type", "")
    if method in ("POST", "PUT", "PATCH") and has_body and "json" not in kind:
        raise Refusal(415, "unsupported_media_type", "send the body as JSON with "
                      f"'Content-Type: application/json' (got {kind or 'no Content-Type'})",
                      "Content-Type")


BODY_IDLE_S = 10.0  # s a client may leave between two parts of a body (408 past it)


class Guard:
    """ASGI middleware in front of every route: :func:`check_request` on the headers,
    then the body read as it streams in and refused (413) once past ``max_body_bytes``
    whatever ``Content-Length`` said or did not say, (408) when no part of it came for
    ``body_idle_s``, or (503) when the bodies being read at once would hold more than
    twice ``max_body_bytes``; the 413 names ``body_setting``, the variable that raises the
    limit. A refused body closes its connection. The route then reads
    the body from memory; later ``receive`` calls go to the client (so a disconnect is
    still seen). A refused WebSocket is closed with 1008 (policy violation) before it is
    accepted."""

    def __init__(self, app: ASGIApp, *, token: SecretStr | None, max_body_bytes: int,
                 public: tuple[str, ...] = (), body_idle_s: float = BODY_IDLE_S,
                 session_reads: bool = False, body_setting: str | None = None) -> None:
        self.app, self.token, self.max_body_bytes, self.public = app, token, max_body_bytes, public
        self.body_setting = body_setting
        self.body_idle_s, self.session_reads = body_idle_s, session_reads
        self.reading = 0  # bytes of bodies being read now, over all requests

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        try:
            check_request(Headers(scope=scope), scope["path"], scope.get("method", "GET"),
                          token=self.token, public=self.public,
                          session_reads=self.session_reads)
            if scope["type"] == "http":
                receive = await self._read_body(receive)
        except Refusal as refused:
            unread = refused.field == "body"  # a body, or the rest of it, is left unread
            if refused.code == "body_not_allowed":  # a method the path has not: say that
                refused = _unrouted(scope) or refused
            if scope["type"] == "websocket":
                await send({"type": "websocket.close", "code": 1008, "reason": refused.message})
            else:
                response = error_response(refused.status, refused.code, refused.message,
                                          refused.field, headers=refused.headers)
                if unread:  # the connection cannot carry another request: end it
                    response.headers["Connection"] = "close"
                await response(scope, receive, send)
            return
        await self.app(scope, receive, send)

    async def _read_body(self, receive: Receive) -> Receive:
        parts: list[bytes] = []
        counted = 0  # what this body adds to self.reading
        try:
            while True:
                try:
                    async with asyncio.timeout(self.body_idle_s):  # no task per chunk
                        message = await receive()
                except TimeoutError:
                    raise Refusal(408, "body_timeout", "no part of the request body came for "
                                  f"{self.body_idle_s:g} s", "body") from None
                if message["type"] != "http.request":  # the client left before sending it all
                    first: Message = message
                    break
                part = message.get("body", b"")
                if counted + len(part) > self.max_body_bytes:
                    setting = f" ({self.body_setting})" if self.body_setting else ""
                    raise Refusal(413, "too_large", "request body is over the limit of "
                                  f"{self.max_body_bytes} bytes{setting}", "body")
                if self.reading + len(part) > 2 * self.max_body_bytes:
                    raise Refusal(503, "busy", "the service is reading other large bodies "
                                  "now: retry later", "body")
                parts.append(part)
                self.reading += len(part)
                counted += len(part)
                if not message.get("more_body", False):
                    first = {"type": "http.request", "body": b"".join(parts),
                             "more_body": False}
                    break
        finally:
            self.reading -= counted
        sent = False

        async def replay() -> Message:
            nonlocal sent
            if not sent:
                sent = True
                return first
            return await receive()

        return replay


def docs_pages(app: FastAPI) -> None:
    """``/docs`` (Swagger UI) and ``/redoc`` for an app made with ``docs_url=None,
    redoc_url=None``: FastAPI's pages, but their JavaScript, CSS and icon come from the app
    itself (:data:`DOCS_ASSETS`) instead of a CDN and Google Fonts, and Swagger UI's
    validator badge (an image from validator.swagger.io) is off: an offline robot shows
    them all. "Try it out" sends the bearer token once it is given to the Authorize button
    (the schema declares the scheme: :func:`document_security`)."""
    app.mount(DOCS_ASSETS, StaticFiles(directory=DOCS_STATIC), name="docs-assets")

    def root(request: Request) -> str:
        return str(request.scope.get("root_path", "")).rstrip("/")

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        at = root(request)
        return get_swagger_ui_html(
            openapi_url=f"{at}{app.openapi_url}", title=f"{app.title} - Swagger UI",
            swagger_js_url=f"{at}{DOCS_ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{at}{DOCS_ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{at}{DOCS_ASSETS}/favicon.png",
            oauth2_redirect_url=None, swagger_ui_parameters={"validatorUrl": None})

    @app.get("/redoc", include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        at = root(request)
        return get_redoc_html(
            openapi_url=f"{at}{app.openapi_url}", title=f"{app.title} - ReDoc",
            redoc_js_url=f"{at}{DOCS_ASSETS}/redoc.standalone.js",
            redoc_favicon_url=f"{at}{DOCS_ASSETS}/favicon.png", with_google_fonts=False)


def service_app(
    title: str,
    *,
    service: str,
    lifespan: Any,
    registry: CollectorRegistry,
    ready: Callable[[], dict[str, Any] | None],
    refresh: Callable[[], None] | None = None,
    admin_token: SecretStr | None = None,
    limits: dict[str, dict[str, dict[str, Any]]] | None = None,
    max_body_bytes: int,
    public: tuple[str, ...] = (),
    body_idle_s: float = BODY_IDLE_S,
    session_reads: bool = False,
) -> FastAPI:
    """A service's app with what every service has: the :class:`Guard` (host, origin,
    ``admin_token`` on every path but the ops ones and ``public``, JSON bodies of at most
    ``max_body_bytes``: a 413 past it names ``AESOP_<SERVICE>_MAX_BODY_BYTES``, ``service``
    in capitals), documented errors, the error body, the settings ``limits`` in its schema,
    request metrics, ``/healthz`` ``/readyz`` ``/metrics``, and the public ``/openapi.json``,
    ``/docs`` and ``/redoc`` (:func:`docs_pages`: no CDN)."""
    app = FastAPI(title=title, version="1", lifespan=lifespan, responses=errors(*GUARD_ERRORS),
                  docs_url=None, redoc_url=None)
    app.state.admin_token = admin_token
    install_error_handlers(app)
    if limits:
        document_limits(app, limits)
    document_security(app, public)
    app.add_middleware(Guard, token=admin_token, max_body_bytes=max_body_bytes, public=public,
                       body_idle_s=body_idle_s, session_reads=session_reads,
                       body_setting=f"AESOP_{service.upper()}_MAX_BODY_BYTES")
    HttpMetrics(registry, service).install(app)  # outside the guard: refusals are counted
    app.include_router(ops_router(registry, ready, refresh))
    docs_pages(app)
    return app
