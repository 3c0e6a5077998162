"""The vector-cache service's app: its lifespan (caches, the Zenoh worker), metrics, errors.

It maps the service's errors to HTTP; the routes are in :mod:`.routes` (shapes in
docs/architecture.md)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse
from prometheus_client import CollectorRegistry

from shared.http import error_response, service_app

from .detector.errors import (
    Busy,
    Conflict,
    DetectorError,
    InvalidInput,
    NotCalibrated,
    NotFound,
    StorageCorrupt,
    StorageError,
    StorageFull,
)
from .detector.scoring import ScoringError
from .metrics import EmbeddingMetrics
from .models.base import EmbedderError
from .routes import router
from .service import CacheService
from .settings import EmbeddingSettings
from .worker import DetectorWorker

log = logging.getLogger(__name__)

STATUS = {InvalidInput: 422, NotFound: 404, Conflict: 409, NotCalibrated: 409, Busy: 429}


def served_app(settings: EmbeddingSettings) -> FastAPI:
    """The app ``aesop serve embedding`` runs: with its bus worker unless ``zenoh_worker``
    is off."""
    factory = DetectorWorker.factory(settings) if settings.zenoh_worker else None
    return create_app(settings, worker_factory=factory)


def create_app(
    settings: EmbeddingSettings,
    service: CacheService | None = None,
    worker_factory: Callable[[CacheService, EmbeddingMetrics], Any] | None = None,
) -> FastAPI:
    """The service's FastAPI app. ``worker_factory`` starts the Zenoh worker in the
    lifespan (``aesop serve embedding`` passes one; tests may not)."""
    registry = CollectorRegistry()
    state: dict[str, Any] = {"started": False, "worker": None}

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        svc = service or CacheService(settings, on_batch=lambda n: metrics.batch_size.observe(n),
                                      on_follow=lambda s: metrics.follow_lag.observe(s))
        app.state.service = svc
        metrics.service = svc
        try:
            await svc.start()
        except StorageCorrupt as exc:
            log.error("refusing to start: %s. The file was left untouched: restore it from a "
                      "backup or move it aside.", exc)
            raise
        worker = state["worker"] = worker_factory(svc, metrics) if worker_factory else None
        task = asyncio.create_task(worker.run()) if worker else None
        if task is not None:
            task.add_done_callback(_report_worker_exit)
        state["started"] = True
        try:
            yield
        finally:
            state["started"] = False
            if worker is not None and task is not None:
                await worker.stop()
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
            await svc.close()

    metrics = EmbeddingMetrics(registry, service)  # type: ignore[arg-type]

    def ready() -> dict[str, Any] | None:
        if not state["started"]:
            return {"reason": "starting"}
        if getattr(state["worker"], "warming", False):
            return {"reason": "warming up the detector's model before taking robots"}
        return None

    def refresh() -> None:
        if state["started"]:
            metrics.refresh()

    limits = settings.limits
    most, chars = {"maxItems": limits.max_items}, {"maxLength": limits.max_text_chars}
    app = service_app(
        "AESOP vector-cache service", service="embedding", lifespan=lifespan,
        registry=registry, ready=ready, refresh=refresh, admin_token=settings.admin_token,
        max_body_bytes=settings.max_body_bytes,
        limits={"AddExperiences": {"items": most, "vectors": most, "ids": most},
                "Score": {"texts": {**most, "items": chars}, "vectors": most},
                "ItemIn": {"text": chars}, "LabelledIn": {"text": chars},
                "Calibrate": {"calibration": most}})

    @app.exception_handler(DetectorError)
    async def domain_error(_: Request, exc: DetectorError) -> JSONResponse:
        status = next((s for cls, s in STATUS.items() if isinstance(exc, cls)), 400)
        return error_response(status, exc.code, exc.message, exc.field)

    @app.exception_handler(StorageError)
    async def storage_error(_: Request, exc: StorageError) -> JSONResponse:
        # the write was rolled back: nothing of it is stored or applied, retry later
        if isinstance(exc, StorageFull):
            return error_response(507, "storage_full", str(exc))
        return error_response(503, "storage_error", str(exc), headers={"Retry-After": "1"})

    @app.exception_handler(ScoringError)
    async def scoring_error(_: Request, exc: ScoringError) -> JSONResponse:
        return error_response(422, "invalid", str(exc), exc.field)

    @app.exception_handler(EmbedderError)
    async def embedder_error(_: Request, exc: EmbedderError) -> JSONResponse:
        return error_response(502, "embedder_error", str(exc))

    app.include_router(router)
    app.state.settings = settings
    app.state.metrics = metrics
    return app


def _report_worker_exit(task: asyncio.Task[None]) -> None:
    if not task.cancelled() and task.exception() is not None:
        log.error("the Zenoh worker stopped: no more verdicts will be published",
                  exc_info=task.exception())
