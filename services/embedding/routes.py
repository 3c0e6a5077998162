"""The vector-cache service's routes (shapes in docs/architecture.md). Each takes what it
needs as ``Annotated`` dependencies: the service, the settings, the metrics (all on
``app.state``, set by :func:`.api.create_app`). The app's guard checks the token (every route
needs it when the service has one)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Sequence
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse

from shared.http import ApiError, errors, from_state, unless_client_leaves
from shared.jobs import Job, JobAccepted, JobInfo, TooManyJobs, UnknownJob

from .detector.cache import Labelled
from .detector.errors import DetectorError, InvalidInput, NotFound
from .detector.proposals import State
from .metrics import EmbeddingMetrics
from .review import Decided
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
    Item,
    ProposalInfo,
    ProposalList,
    Reviewed,
    ReviewMany,
    Score,
    ScoreResult,
    Scores,
)
from .scorer import ScoreBatch
from .service import CacheService
from .settings import EmbeddingSettings

ServiceDep = Annotated[CacheService, Depends(from_state("service"))]
SettingsDep = Annotated[EmbeddingSettings, Depends(from_state("settings"))]
MetricsDep = Annotated[EmbeddingMetrics, Depends(from_state("metrics"))]

router = APIRouter()


@router.put("/v1/caches/{name}", response_model=CacheInfo,
            responses={201: {"model": CacheInfo, "description": "created"},
                       **errors(401, 409, 502, 503, 507)})
async def put_cache(name: str, body: CreateCache, service: ServiceDep,
                    settings: SettingsDep) -> JSONResponse:
    # what the body names, and only that: an existing cache keeps every setting the
    # request leaves out (a new one takes the defaults)
    named = body.model_fields_set
    desc, created = await service.create(
        name, model=body.model if "model" in named else settings.model, dim=body.dim,
        k=body.k, score=body.score if "score" in named else None,
        index=body.index if "index" in named else None, proposals=body.proposals,
        model_is_default="model" not in named)
    return JSONResponse(desc.model_dump(mode="json"), status_code=201 if created else 200)


@router.get("/v1/caches")
async def list_caches(service: ServiceDep) -> CacheList:
    return CacheList(caches=[service.describe(n) for n in service.names()])


@router.get("/v1/caches/{name}", responses=errors(404))
async def get_cache(name: str, service: ServiceDep) -> CacheInfo:
    return service.describe(name)


@router.post("/v1/caches/{name}/experiences", response_model=Added,
             responses={202: {"model": JobAccepted, "description": "?wait=false"},
                        **errors(401, 404, 409, 429, 502, 503, 507)})
async def add_experiences(
    name: str, body: AddExperiences, service: ServiceDep, settings: SettingsDep,
    wait: Annotated[bool, Query(description="false: answer 202 with a job id")] = True,
) -> JSONResponse:
    service.entry(name)
    items = _items(body, settings)
    try:
        job = service.jobs.create("add_experiences", name, len(items))
    except TooManyJobs as exc:
        raise ApiError(429, "busy", str(exc), "wait") from None
    if wait:
        added = await _run_job(job, service.add(name, items, job))
        return JSONResponse(added.model_dump(mode="json"))
    task = asyncio.create_task(_run_job(job, service.add(name, items, job)))
    task.add_done_callback(lambda t: t.exception())  # the job records the error
    accepted = JobAccepted.of(job)
    return JSONResponse(accepted.model_dump(mode="json"), status_code=202)


@router.get("/v1/caches/{name}/experiences/{ident}", responses=errors(404))
async def get_experience(name: str, ident: str, service: ServiceDep) -> Experience:
    return service.experience(name, ident)


@router.delete("/v1/caches/{name}/experiences/{ident}", responses=errors(401, 404, 503, 507))
async def delete_experience(name: str, ident: str, service: ServiceDep) -> Deleted:
    return await service.delete(name, ident)


@router.post("/v1/caches/{name}/calibrate", responses=errors(401, 404, 409, 502, 503, 507))
async def calibrate(name: str, body: Calibrate, service: ServiceDep,
                    settings: SettingsDep) -> Calibrated:
    labelled = [Labelled(x.text, x.label == "anomaly",
                         tuple(d.phrase for d in x.detections)) for x in body.calibration or ()]
    if labelled:
        _check_count(len(labelled), "calibration", settings)
    _check_texts([x.text for x in labelled], "calibration", settings, key="text")
    return await service.calibrate(name, body.method, alpha=body.alpha, tpr=body.tpr,
                                   calibration=labelled, pairs=body.pairs)


@router.post("/v1/caches/{name}/score", responses=errors(404, 409, 429, 502))
async def score(name: str, body: Score, service: ServiceDep, settings: SettingsDep,
                metrics: MetricsDep, request: Request) -> Scores:
    """Score texts or vectors: at most ``max_score_items`` per request (413), behind the
    bus's verdicts, refused while too much is waiting (429), dropped if the client
    leaves before its answer."""
    with metrics.score_seconds.time():
        if body.texts is not None or body.queries is not None:
            field = "texts" if body.texts is not None else "queries"
            texts = body.texts or [q.text for q in body.queries or ()]
            detections = [q.detections for q in body.queries or ()]
            _check_count(len(texts), field, settings, settings.limits.max_score_items,
                         "AESOP_EMBEDDING_LIMITS__MAX_SCORE_ITEMS")
            _check_texts(texts, field, settings, key=None if body.texts else "text")
            batch = await unless_client_leaves(request, service.scorer.score_texts(
                name, texts, body.k, detections=detections))
        else:
            vectors = body.vectors or []
            _check_count(len(vectors), "vectors", settings, settings.limits.max_score_items,
                         "AESOP_EMBEDDING_LIMITS__MAX_SCORE_ITEMS")
            batch = await unless_client_leaves(request,
                                               service.scorer.score_vectors(name, vectors, body.k))
    return _score_response(batch)


@router.get("/v1/caches/{name}/proposals", responses=errors(404))
async def list_proposals(name: str, service: ServiceDep,
                         state: Annotated[State | None, Query()] = None) -> ProposalList:
    """Scenes the slow reasoner answered "continue" for, oldest first."""
    return ProposalList(cache=name, policy=service.entry(name).cache.config.proposals,
                        proposals=[ProposalInfo.of(p) for p in service.review.list(name, state)])


@router.post("/v1/caches/{name}/proposals/{decision}",
             responses=errors(400, 401, 404, 409, 422, 502, 503, 507))
async def review_proposals(name: str, decision: Literal["accept", "reject"], body: ReviewMany,
                           service: ServiceDep) -> Reviewed:
    """A batch review: accept (or reject) the pending proposals ``ids`` in order. Any id
    unknown (404) or already decided (409) and nothing changes."""
    state: Decided = "accepted" if decision == "accept" else "rejected"
    done = await service.review.decide_many(name, body.ids, state, now=time.time())
    return Reviewed(proposals=[ProposalInfo.of(p) for p in done],
                    cache=CacheInfo.of(service.entry(name).cache))


@router.post("/v1/caches/{name}/proposals/{ident}/accept",
             responses=errors(401, 404, 409, 502, 503, 507))
async def accept_proposal(name: str, ident: str, service: ServiceDep) -> ProposalInfo:
    """Add the scene as a nominal experience (its id is the scene's)."""
    return ProposalInfo.of(await service.review.accept(name, ident, now=time.time()))


@router.post("/v1/caches/{name}/proposals/{ident}/reject",
             responses=errors(401, 404, 409, 503, 507))
async def reject_proposal(name: str, ident: str, service: ServiceDep) -> ProposalInfo:
    return ProposalInfo.of(await service.review.reject(name, ident, now=time.time()))


@router.get("/v1/jobs/{job_id}", responses=errors(404))
async def get_job(job_id: str, service: ServiceDep) -> JobInfo:
    try:
        return JobInfo.of(service.jobs.get(job_id))
    except UnknownJob:
        raise NotFound(f"no job {job_id!r}", field="id") from None


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
        return [Item(text=it.text, id=it.id, metadata=it.metadata,
                     detections=tuple(it.detections)) for it in body.items]
    vectors = body.vectors or []
    _check_count(len(vectors), "vectors", settings)
    ids: Sequence[str | None] = body.ids or [None] * len(vectors)
    return [Item(vector=v, id=i) for v, i in zip(vectors, ids, strict=True)]


def _check_count(n: int, field: str, settings: EmbeddingSettings, limit: int | None = None,
                 variable: str = "AESOP_EMBEDDING_LIMITS__MAX_ITEMS") -> None:
    limit = settings.limits.max_items if limit is None else limit
    if n == 0:
        raise InvalidInput(f"'{field}' is empty", field=field)
    if n > limit:
        raise ApiError(413, "too_large", f"{n} {field} in one request; the limit is "
                       f"{limit} ({variable})", field)


def _check_texts(texts: list[str], field: str, settings: EmbeddingSettings,
                 key: str | None = None) -> None:
    for i, text in enumerate(texts):  # blank texts are refused by the schema (Text)
        where = f"{field}[{i}]" + (f".{key}" if key else "")
        if len(text) > settings.limits.max_text_chars:
            raise InvalidInput(f"text has {len(text)} characters; the limit is "
                               f"{settings.limits.max_text_chars} "
                               "(AESOP_EMBEDDING_LIMITS__MAX_TEXT_CHARS)", field=where)


def _score_response(batch: ScoreBatch) -> Scores:
    return Scores(
        results=[ScoreResult(score=r.score, is_anomaly=r.is_anomaly, neighbors=list(r.neighbors),
                             detection_score=r.detection_score, p_value=r.p_value,
                             detections=list(r.matches), pair_score=r.pair_score,
                             pair=r.pair)
                 for r in batch.results],
        threshold=batch.threshold, stale=batch.stale, k=batch.k, model=batch.model,
        version=batch.version)
