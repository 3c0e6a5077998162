"""HTTP admin API of the vector-cache service (routes and shapes in docs/architecture.md)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from contextlib import asynccontextmanager
from typing import Annotated, Any

from fastapi import Depends, FastAPI, Query, Request
from fastapi.responses import JSONResponse
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from shared.http import ApiError, bearer_auth, error_response, errors, service_app
from shared.jobs import Job, JobAccepted, JobInfo, UnknownJob

from .cache import Labelled
from .embedders import EmbedderError
from .errors import Conflict, DetectorError, InvalidInput, NotCalibrated, NotFound
from .schemas import (
    Added,
    AddExperiences,
    CacheInfo,
    CacheList,
    Calibrate,
    Calibrated,
    CreateCache,
    Deleted,
    Experience,
    Score,
    ScoreResult,
    Scores,
)
from .scoring import ScoringError
from .service import CacheService, Item, ScoreBatch
from .settings import EmbeddingSettings
from .store import StorageCorrupt, StorageError, StorageFull

log = logging.getLogger(__name__)

STATUS = {InvalidInput: 422, NotFound: 404, Conflict: 409, NotCalibrated: 409}


def _service(request: Request) -> CacheService:
    return request.app.state.service


ServiceDep = Annotated[CacheService, Depends(_service)]


class Metrics:
    def __init__(self, registry: CollectorRegistry, service: CacheService) -> None:
        self.score_seconds = Histogram(
            "aesop_embedding_score_seconds", "Score request latency (embed + search + threshold)",
            registry=registry, buckets=(.002, .005, .01, .015, .02, .03, .05, .1, .25, .5, 1, 5))
        self.batch_size = Histogram(
            "aesop_embedding_batch_size", "Texts per micro-batched embedding call",
            registry=registry, buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256))
        self.verdicts = Counter("aesop_embedding_verdicts", "Anomaly verdicts published",
                                ["anomaly"], registry=registry)
        size = Gauge("aesop_embedding_cache_size", "Experiences per cache", ["cache"],
                     registry=registry)
        self.size = size
        self.service = service

    def refresh(self) -> None:
        for name in self.service.names():
            self.size.labels(name).set(self.service.entry(name).cache.size)


def create_app(
    settings: EmbeddingSettings,
    service: CacheService | None = None,
    worker_factory: Callable[[CacheService, Metrics], Any] | None = None,
) -> FastAPI:
    """The service's FastAPI app. ``worker_factory`` starts the Zenoh worker in the
    lifespan (``aesop serve embedding`` passes one; tests may not)."""
    registry = CollectorRegistry()
    state: dict[str, bool] = {"started": False}

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        svc = service or CacheService(settings, on_batch=lambda n: metrics.batch_size.observe(n))
        app.state.service = svc
        metrics.service = svc
        try:
            await svc.start()
        except StorageCorrupt as exc:
            log.error("refusing to start: %s. The file was left untouched: restore it from a "
                      "backup or move it aside.", exc)
            raise
        worker = worker_factory(svc, metrics) if worker_factory else None
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

    metrics = Metrics(registry, service)  # type: ignore[arg-type]

    def ready() -> dict[str, Any] | None:
        return None if state["started"] else {"reason": "starting"}

    def refresh() -> None:
        if state["started"]:
            metrics.refresh()

    most, chars = {"maxItems": settings.max_items}, {"maxLength": settings.max_text_chars}
    app = service_app(
        "AESOP vector-cache service", service="embedding", lifespan=lifespan,
        registry=registry, ready=ready, refresh=refresh, max_body_bytes=settings.max_body_bytes,
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

    auth = [Depends(bearer_auth(settings.admin_token))]

    @app.put("/v1/caches/{name}", dependencies=auth, response_model=CacheInfo,
             responses={201: {"model": CacheInfo, "description": "created"},
                        **errors(401, 409, 502, 503, 507)})
    async def put_cache(name: str, body: CreateCache, service: ServiceDep) -> JSONResponse:
        model = body.model if "model" in body.model_fields_set else settings.model
        desc, created = await service.create(name, model=model, dim=body.dim, k=body.k,
                                             score=body.score, index=body.index)
        return JSONResponse(desc.model_dump(mode="json"), status_code=201 if created else 200)

    @app.get("/v1/caches")
    async def list_caches(service: ServiceDep) -> CacheList:
        return CacheList(caches=[service.describe(n) for n in service.names()])

    @app.get("/v1/caches/{name}", responses=errors(404))
    async def get_cache(name: str, service: ServiceDep) -> CacheInfo:
        return service.describe(name)

    @app.post("/v1/caches/{name}/experiences", dependencies=auth, response_model=Added,
              responses={202: {"model": JobAccepted, "description": "?wait=false"},
                         **errors(401, 404, 409, 502, 503, 507)})
    async def add_experiences(
        name: str, body: AddExperiences, service: ServiceDep,
        wait: Annotated[bool, Query(description="false: answer 202 with a job id")] = True,
    ) -> JSONResponse:
        service.entry(name)
        items = _items(body, settings)
        job = service.jobs.create("add_experiences", name, len(items))
        if wait:
            added = await _run_job(job, service.add(name, items, job))
            return JSONResponse(added.model_dump(mode="json"))
        task = asyncio.create_task(_run_job(job, service.add(name, items, job)))
        task.add_done_callback(lambda t: t.exception())  # the job records the error
        accepted = JobAccepted.of(job)
        return JSONResponse(accepted.model_dump(mode="json"), status_code=202)

    @app.get("/v1/caches/{name}/experiences/{ident}", responses=errors(404))
    async def get_experience(name: str, ident: str, service: ServiceDep) -> Experience:
        return service.experience(name, ident)

    @app.delete("/v1/caches/{name}/experiences/{ident}", dependencies=auth,
                responses=errors(401, 404, 503, 507))
    async def delete_experience(name: str, ident: str, service: ServiceDep) -> Deleted:
        return await service.delete(name, ident)

    @app.post("/v1/caches/{name}/calibrate", dependencies=auth,
              responses=errors(401, 404, 409, 502, 503, 507))
    async def calibrate(name: str, body: Calibrate, service: ServiceDep) -> Calibrated:
        labelled = [Labelled(x.text, x.label == "anomaly") for x in body.calibration or ()]
        if labelled:
            _check_count(len(labelled), "calibration", settings)
        _check_texts([x.text for x in labelled], "calibration", settings, key="text")
        return await service.calibrate(name, body.method, alpha=body.alpha, tpr=body.tpr,
                                       calibration=labelled)

    @app.post("/v1/caches/{name}/score", responses=errors(404, 409, 502))
    async def score(name: str, body: Score, service: ServiceDep) -> Scores:
        with metrics.score_seconds.time():
            if body.texts is not None:
                _check_count(len(body.texts), "texts", settings)
                _check_texts(body.texts, "texts", settings)
                batch = await service.score_texts(name, body.texts, body.k)
            else:
                vectors = body.vectors or []
                _check_count(len(vectors), "vectors", settings)
                batch = await service.score_vectors(name, vectors, body.k)
        return _score_response(batch)

    @app.get("/v1/jobs/{job_id}", responses=errors(404))
    async def get_job(job_id: str, service: ServiceDep) -> JobInfo:
        try:
            return JobInfo.of(service.jobs.get(job_id))
        except UnknownJob:
            raise NotFound(f"no job {job_id!r}", field="id") from None

    return app


def _report_worker_exit(task: asyncio.Task[None]) -> None:
    if not task.cancelled() and task.exception() is not None:
        log.error("the Zenoh worker stopped: no more verdicts will be published",
                  exc_info=task.exception())


async def _run_job(job: Job, work: Awaitable[Added]) -> Added:
    try:
        result = await work
    except DetectorError as exc:
        job.fail(exc.code, exc.message, exc.field)
        raise
    except Exception as exc:
        job.fail("internal", str(exc))
        raise
    job.succeed(result.model_dump(mode="json"))
    return result


def _items(body: AddExperiences, settings: EmbeddingSettings) -> list[Item]:
    if body.items is not None:
        _check_count(len(body.items), "items", settings)
        _check_texts([it.text for it in body.items], "items", settings, key="text")
        return [Item(text=it.text, id=it.id, metadata=it.metadata) for it in body.items]
    vectors = body.vectors or []
    _check_count(len(vectors), "vectors", settings)
    ids: Sequence[str | None] = body.ids or [None] * len(vectors)
    return [Item(vector=v, id=i) for v, i in zip(vectors, ids, strict=True)]


def _check_count(n: int, field: str, settings: EmbeddingSettings) -> None:
    if n == 0:
        raise InvalidInput(f"'{field}' is empty", field=field)
    if n > settings.max_items:
        raise ApiError(413, "too_large", f"{n} {field} in one request; the limit is "
                       f"{settings.max_items} (AESOP_EMBEDDING_MAX_ITEMS)", field)


def _check_texts(texts: list[str], field: str, settings: EmbeddingSettings,
                 key: str | None = None) -> None:
    for i, text in enumerate(texts):  # blank texts are refused by the schema (Text)
        where = f"{field}[{i}]" + (f".{key}" if key else "")
        if len(text) > settings.max_text_chars:
            raise InvalidInput(f"text has {len(text)} characters; the limit is "
                               f"{settings.max_text_chars}", field=where)


def _score_response(batch: ScoreBatch) -> Scores:
    threshold = batch.threshold
    return Scores(
        results=[ScoreResult(score=r.score,
                             is_anomaly=None if threshold is None else r.score > threshold,
                             neighbors=list(r.neighbors))
                 for r in batch.results],
        threshold=threshold, stale=batch.stale, k=batch.k, model=batch.model,
        version=batch.version)
