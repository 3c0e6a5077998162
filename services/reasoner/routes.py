"""The slow-reasoner service's routes (shapes in docs/architecture.md). Each takes what it
needs as ``Annotated`` dependencies from ``app.state`` (set by :func:`.api.create_app`):
the decider, the settings, the metrics, the background work. The app's guard checks the
token (every route needs it when the service has one)."""

from __future__ import annotations

import asyncio
import logging
import uuid
from dataclasses import dataclass, field
from typing import Annotated, Any

from fastapi import APIRouter, Depends

from shared.http import ApiError, errors, from_state
from shared.jobs import Job, JobAccepted, JobInfo, Jobs, TooManyJobs, UnknownJob
from shared.messages import Observation, Option, ReasonerDecision, ReasonerRequest

from . import limits
from .calibrating import CalibrationPlan, measure
from .deciding import Decider
from .latency import LatencyError, min_samples
from .metrics import ReasonerMetrics
from .prompts import PromptError, build_messages, load_template
from .schemas import BackendInfo, Backends, CalibrateBody, ReasonBody
from .settings import ReasonerSettings

log = logging.getLogger(__name__)

DEFAULT_SCENE = Observation(
    seq=0, task="landing on the red box",
    text="a red box on the ground\na blue box on the ground\na quadrotor on the red box")
DEFAULT_OPTIONS = (Option(index=0, label="continue"),
                   Option(index=1, label="alternative landing site", description="the blue box"),
                   Option(index=2, label="holding zone", description="hover and wait"))


@dataclass
class Work:
    """The latency calibrations running in the background, and their jobs."""

    jobs: Jobs = field(default_factory=Jobs)
    tasks: set[asyncio.Task[None]] = field(default_factory=set)


DeciderDep = Annotated[Decider, Depends(from_state("decider"))]
SettingsDep = Annotated[ReasonerSettings, Depends(from_state("settings"))]
MetricsDep = Annotated[ReasonerMetrics, Depends(from_state("metrics"))]
WorkDep = Annotated[Work, Depends(from_state("work"))]

router = APIRouter()


@router.post("/v1/reason", responses=errors(401))
async def reason(body: ReasonBody, decider: DeciderDep, settings: SettingsDep,
                 metrics: MetricsDep) -> ReasonerDecision:
    check_request(body, settings)
    request = ReasonerRequest(
        robot=body.observation.robot, request_id=body.request_id or uuid.uuid4().hex,
        observation=body.observation, options=tuple(body.options),
        deadline_s=body.deadline_s, unusual=tuple(body.unusual),
        unusual_pair=body.unusual_pair)
    decision = await decider.decide(request)
    metrics.observe(decision)
    return decision


@router.post("/v1/latency/calibrate", status_code=202,
             responses=errors(401, 409, 429))
async def calibrate(body: CalibrateBody, decider: DeciderDep, settings: SettingsDep,
                    work: WorkDep) -> JobAccepted:
    check_request(body, settings)
    needed = min_samples(body.quantile, body.confidence)
    if body.n < needed:
        raise ApiError(422, "invalid", f"n = {body.n} is too small to bound the "
                       f"{body.quantile:g} quantile with confidence {body.confidence:g}: "
                       f"at least {needed} queries are needed", "n")
    names = [b.name for b in decider.backends]
    if body.backend not in names:
        raise ApiError(409, "conflict", f"no {body.backend} backend is configured "
                       f"(configured: {', '.join(names)})", "backend")
    backend = decider.backends[names.index(body.backend)]
    scene = body.observation or DEFAULT_SCENE
    try:
        messages = build_messages(load_template(settings.domain),
                                  task=scene.task or "its task", observation=scene.text,
                                  options=body.options or DEFAULT_OPTIONS,
                                  variant=settings.variant)
    except PromptError as exc:
        raise ApiError(422, "invalid", str(exc), exc.field) from None
    plan = CalibrationPlan(n=body.n, warmup=body.warmup, quantile=body.quantile,
                           confidence=body.confidence, timeout_s=body.timeout_s)
    try:
        job = work.jobs.create("latency_calibration", body.backend, body.warmup + body.n)
    except TooManyJobs as exc:
        raise ApiError(429, "busy", str(exc), "backend") from None
    task = asyncio.create_task(_calibrate(job, backend, messages, plan))
    work.tasks.add(task)
    task.add_done_callback(work.tasks.discard)
    return JobAccepted.of(job)


@router.get("/v1/jobs/{job_id}", responses=errors(404))
async def get_job(job_id: str, work: WorkDep) -> JobInfo:
    try:
        return JobInfo.of(work.jobs.get(job_id))
    except UnknownJob:
        raise ApiError(404, "not_found", f"no job {job_id!r}", "id") from None


@router.get("/v1/backends")
async def backends(settings: SettingsDep) -> Backends:
    return Backends(
        backends=[BackendInfo(name=c.name, base_url=c.public_url, model=c.model,
                              stream=c.stream, json_schema=c.json_schema,
                              response_format=c.response_format)
                  for c in settings.backends()],
        hedge_after_s=settings.hedge.after_s, domain=settings.domain,
        variant=settings.variant, fallback=settings.fallback)


async def _calibrate(job: Job, backend: Any, messages: list[dict[str, str]],
                     plan: CalibrationPlan) -> None:
    try:
        report = await measure(backend, messages, plan, job.progress)
    except LatencyError as exc:
        job.fail("invalid", str(exc), exc.field)
    except Exception as exc:  # recorded in the job; the service keeps running
        log.exception("latency calibration failed")
        job.fail("internal", f"{type(exc).__name__} (the details are in the service log: "
                 "a job record may be read by anyone with the token)")
    else:
        job.succeed(report.to_dict())


def check_request(body: ReasonBody | CalibrateBody, settings: ReasonerSettings) -> None:
    """The limits that depend on settings, as the Zenoh worker checks them (the shape is
    checked by pydantic; the same limits are written into ``/openapi.json``)."""
    try:
        limits.check_request(settings, observation=body.observation, options=body.options,
                             deadline_s=body.deadline_s if isinstance(body, ReasonBody) else None)
    except limits.LimitError as exc:
        raise ApiError(422, "invalid", exc.problem, exc.field) from None
