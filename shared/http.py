"""HTTP admin API pieces every service shares (FastAPI).

- errors: JSON ``{"error": {"code", "message", "field"}}`` (``ErrorBody``) with a 4xx/5xx
  status, documented in ``/openapi.json`` with ``errors(...)``;
- ``TOKEN`` (``require_token``): mutating routes need ``Authorization: Bearer $AESOP_ADMIN_TOKEN``;
- ``ops_router``: ``/healthz``, ``/readyz`` and ``/metrics`` (Prometheus, per-app registry);
- ``serve``: run an app with uvicorn, refusing off-loopback exposure without a token.
"""

from __future__ import annotations

import hmac
import time
from collections.abc import Awaitable, Callable
from typing import Annotated, Any

from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from fastapi.routing import APIRouter
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Histogram,
    generate_latest,
)
from pydantic import BaseModel, ConfigDict, SecretStr
from starlette.exceptions import HTTPException
from starlette.routing import Match

from .settings import ServiceSettings

Next = Callable[[Request], Awaitable[Response]]


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


REASONS = {
    400: "the body is not valid JSON",
    401: "a valid 'Authorization: Bearer <token>' header is missing",
    404: "no such resource (error.field names which)",
    405: "method not allowed (the Allow header lists those that are)",
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
    """The methods some route of the app accepts at the request's path."""
    methods: set[str] = set()
    for route in request.app.router.routes:
        match, _ = route.matches({**request.scope, "method": "GET"})
        if match != Match.NONE:
            methods |= set(getattr(route, "methods", None) or ())
    return sorted(methods)


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


_BEARER = HTTPBearer(auto_error=False)


async def require_token(
    request: Request,
    creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_BEARER)],
) -> None:
    """The dependency of mutating routes: ``Authorization: Bearer <the app's token>``
    (``service_app(admin_token=...)``). Without a configured token the service only
    listens on loopback (``ServiceSettings.check_exposure``) and the check is open."""
    token: SecretStr | None = request.app.state.admin_token
    if token is None:
        return
    given = b"" if creds is None else creds.credentials.encode()
    if not hmac.compare_digest(given, token.get_secret_value().encode()):
        raise ApiError(401, "unauthorized", "a valid 'Authorization: Bearer <token>' "
                       "header is required", "Authorization")


TOKEN = Depends(require_token)  # dependencies=[TOKEN] on a route that needs the token


class HttpMetrics:
    """Request counters and latencies, in a registry owned by the app (no globals)."""

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
            self.latency.labels(self.service, request.method, path).observe(
                time.perf_counter() - start)
            status = str(response.status_code)
            self.requests.labels(self.service, request.method, path, status).inc()
            return response


def ops_router(
    registry: CollectorRegistry,
    ready: Callable[[], dict[str, Any] | None],
    refresh: Callable[[], None] | None = None,
) -> APIRouter:
    """``/healthz`` (the process answers), ``/readyz`` (``ready()`` returns None when ready,
    or a dict saying what is missing), ``/metrics`` (Prometheus text; ``refresh`` updates
    gauges first)."""
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
        return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)

    return router


def body_limit(app: FastAPI, max_bytes: int) -> None:
    """Refuse request bodies larger than ``max_bytes`` (413, field "body")."""

    @app.middleware("http")
    async def limit(request: Request, call_next: Next) -> Response:
        length = request.headers.get("content-length")
        if length is not None and length.isdigit() and int(length) > max_bytes:
            return error_response(
                413, "too_large", f"request body is {length} bytes; the limit is {max_bytes}",
                "body")
        return await call_next(request)


def require_json(app: FastAPI) -> None:
    """Refuse a request body that is not declared as JSON (415, field "Content-Type")."""

    @app.middleware("http")
    async def json_only(request: Request, call_next: Next) -> Response:
        has_body = request.headers.get("content-length", "0") != "0" or \
            "transfer-encoding" in request.headers
        kind = request.headers.get("content-type", "")
        if request.method in ("POST", "PUT", "PATCH") and has_body and "json" not in kind:
            return error_response(
                415, "unsupported_media_type",
                f"send the body as JSON with 'Content-Type: application/json' (got "
                f"{kind or 'no Content-Type'})", "Content-Type")
        return await call_next(request)


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
    max_body_bytes: int | None = None,
) -> FastAPI:
    """A service's app with what every service has: documented request errors, the error
    body, the settings ``limits`` in its schema, a body limit, JSON bodies only, request
    metrics, and ``/healthz`` ``/readyz`` ``/metrics``; ``admin_token`` is what
    ``require_token`` checks."""
    app = FastAPI(title=title, version="1", lifespan=lifespan, responses=errors(*REQUEST_ERRORS))
    app.state.admin_token = admin_token
    install_error_handlers(app)
    if limits:
        document_limits(app, limits)
    if max_body_bytes is not None:
        body_limit(app, max_body_bytes)
    require_json(app)
    HttpMetrics(registry, service).install(app)
    app.include_router(ops_router(registry, ready, refresh))
    return app


def serve(app: FastAPI, settings: ServiceSettings) -> None:
    """Run ``app`` with uvicorn until SIGINT/SIGTERM."""
    import uvicorn

    settings.check_exposure()
    uvicorn.run(app, host=settings.host, port=settings.port, log_level=settings.log_level,
                access_log=False)

