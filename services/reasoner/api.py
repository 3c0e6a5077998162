"""HTTP admin API of the slow-reasoner service: ``POST /v1/reason``, ``GET /v1/backends``."""

from __future__ import annotations

import asyncio
import logging
import uuid
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Annotated, Any

from fastapi import Depends, FastAPI, Request
from prometheus_client import CollectorRegistry, Counter, Histogram

from shared.http import ApiError, bearer_auth, errors, service_app
from shared.jobs import Job, JobAccepted, JobInfo, Jobs, UnknownJob
from shared.messages import Observation, Option, ReasonerDecision, ReasonerRequest

from .backends import BackendConfig, ChatBackend, Completion, OpenAIChatBackend
from .calibrating import CalibrationPlan, measure
from .deciding import Decider, DeciderConfig, FallbackPolicy
from .latency import LatencyError, min_samples
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


class Metrics:
    def __init__(self, registry: CollectorRegistry) -> None:
        self.latency = Histogram(
            "aesop_reasoner_decision_seconds", "Time from request to decision",
            ["source"], registry=registry,
            buckets=(.05, .1, .25, .5, 1, 1.5, 2, 3, 4, 5, 7.5, 10, 20))
        self.decisions = Counter("aesop_reasoner_decisions", "Decisions by source",
                                 ["source"], registry=registry)

        self.tokens = Counter("aesop_reasoner_tokens", "LLM tokens, as the server reports them "
                              "in 'usage' (streamed answers count only where it does)",
                              ["kind"], registry=registry)

    def count(self, completion: Completion) -> None:
        if completion.prompt_tokens:
            self.tokens.labels("prompt").inc(completion.prompt_tokens)
        if completion.completion_tokens:
            self.tokens.labels("completion").inc(completion.completion_tokens)

    def observe(self, decision: ReasonerDecision) -> None:
        self.decisions.labels(decision.source).inc()
        self.latency.labels(decision.source).observe(decision.latency_ms / 1000)


def backend_configs(settings: ReasonerSettings) -> list[BackendConfig]:
    key = settings.llm_api_key.get_secret_value() if settings.llm_api_key else None
    configs = [BackendConfig(
        name="primary", base_url=settings.llm_base_url, model=settings.llm_model, api_key=key,
        max_tokens=settings.llm_max_tokens, temperature=settings.llm_temperature,
        stream=settings.llm_stream, json_schema=settings.llm_json_schema)]
    if settings.hedge_model:
        configs.append(BackendConfig(
            name="hedge", base_url=settings.hedge_base_url or settings.llm_base_url,
            model=settings.hedge_model, api_key=key, max_tokens=settings.llm_max_tokens,
            temperature=settings.llm_temperature, stream=settings.llm_stream,
            json_schema=settings.llm_json_schema))
    return configs


class MeteredBackend:
    """A ``ChatBackend`` that reports each completion (for the token counters)."""

    def __init__(self, inner: ChatBackend, on_completion: Callable[[Completion], None]) -> None:
        self.inner, self.on_completion = inner, on_completion
        self.name, self.model = inner.name, inner.model

    async def complete(self, messages: list[dict[str, str]], *,
                       stop_when: Callable[[str], bool] | None = None) -> Completion:
        completion = await self.inner.complete(messages, stop_when=stop_when)
        self.on_completion(completion)
        return completion

    async def aclose(self) -> None:
        await self.inner.aclose()


def build_decider(settings: ReasonerSettings,
                  on_completion: Callable[[Completion], None] | None = None) -> Decider:
    backends: list[ChatBackend] = [OpenAIChatBackend(c) for c in backend_configs(settings)]
    if on_completion is not None:
        backends = [MeteredBackend(b, on_completion) for b in backends]
    config = DeciderConfig(domain=settings.domain, variant=settings.variant,
                           hedge_after_s=settings.hedge_after_s)
    policy = FallbackPolicy(kind=settings.fallback, ranks=settings.fallback_ranks)
    return Decider(backends, config, policy)


def _decider(request: Request) -> Decider:
    return request.app.state.decider


DeciderDep = Annotated[Decider, Depends(_decider)]


def create_app(
    settings: ReasonerSettings,
    decider: Decider | None = None,
    worker_factory: Callable[[Decider, Metrics], Any] | None = None,
) -> FastAPI:
    registry = CollectorRegistry()
    metrics = Metrics(registry)
    state = {"started": False}
    jobs = Jobs()
    tasks: set[asyncio.Task[None]] = set()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.decider = decider or build_decider(settings, metrics.count)
        worker = worker_factory(app.state.decider, metrics) if worker_factory else None
        task = asyncio.create_task(worker.run()) if worker else None
        state["started"] = True
        try:
            yield
        finally:
            state["started"] = False
            for pending in list(tasks):
                pending.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            if worker is not None and task is not None:
                await worker.stop()
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
            await app.state.decider.aclose()

    app = service_app(
        "AESOP slow-reasoner service", service="reasoner", lifespan=lifespan, registry=registry,
        ready=lambda: None if state["started"] else {"reason": "starting"},
        limits={"ReasonBody": {"options": {"maxItems": settings.max_options},
                               "deadline_s": {"maximum": settings.max_deadline_s}},
                "CalibrateBody": {"options": {"maxItems": settings.max_options}},
                "Observation": {"text": {"maxLength": settings.max_observation_chars}}})
    auth = [Depends(bearer_auth(settings.admin_token))]

    @app.post("/v1/reason", dependencies=auth, responses=errors(401))
    async def reason(body: ReasonBody, decider: DeciderDep) -> ReasonerDecision:
        check_request(body, settings)
        request = ReasonerRequest(
            robot=body.observation.robot, request_id=body.request_id or uuid.uuid4().hex,
            observation=body.observation, options=tuple(body.options),
            deadline_s=body.deadline_s)
        decision = await decider.decide(request)
        metrics.observe(decision)
        return decision

    @app.post("/v1/latency/calibrate", dependencies=auth, status_code=202,
              responses=errors(401, 409))
    async def calibrate(body: CalibrateBody, decider: DeciderDep) -> JobAccepted:
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
        job = jobs.create("latency_calibration", body.backend, body.warmup + body.n)
        task = asyncio.create_task(_calibrate(job, backend, messages, plan))
        tasks.add(task)
        task.add_done_callback(tasks.discard)
        return JobAccepted.of(job)

    @app.get("/v1/jobs/{job_id}", responses=errors(404))
    async def get_job(job_id: str) -> JobInfo:
        try:
            return JobInfo.of(jobs.get(job_id))
        except UnknownJob:
            raise ApiError(404, "not_found", f"no job {job_id!r}", "id") from None

    @app.get("/v1/backends")
    async def backends() -> Backends:
        return Backends(
            backends=[BackendInfo(name=c.name, base_url=c.base_url, model=c.model,
                                  stream=c.stream, json_schema=c.json_schema)
                      for c in backend_configs(settings)],
            hedge_after_s=settings.hedge_after_s, domain=settings.domain,
            variant=settings.variant, fallback=settings.fallback)

    return app


async def _calibrate(job: Job, backend: Any, messages: list[dict[str, str]],
                     plan: CalibrationPlan) -> None:
    try:
        report = await measure(backend, messages, plan, job.progress)
    except LatencyError as exc:
        job.fail("invalid", str(exc), exc.field)
    except Exception as exc:  # recorded in the job; the service keeps running
        log.exception("latency calibration failed")
        job.fail("internal", str(exc))
    else:
        job.succeed(report.to_dict())


def check_request(body: ReasonBody | CalibrateBody, settings: ReasonerSettings) -> None:
    """The limits that depend on settings (the shape is checked by pydantic; the same
    limits are written into ``/openapi.json``)."""
    if body.observation is not None and \
            len(body.observation.text) > settings.max_observation_chars:
        raise ApiError(422, "invalid", f"observation has {len(body.observation.text)} "
                       f"characters; the limit is {settings.max_observation_chars}",
                       "observation.text")
    if body.options is not None and len(body.options) > settings.max_options:
        raise ApiError(422, "invalid", f"{len(body.options)} options; the limit is "
                       f"{settings.max_options}", "options")
    if isinstance(body, ReasonBody) and body.deadline_s > settings.max_deadline_s:
        raise ApiError(422, "invalid", f"deadline_s {body.deadline_s} is over the limit "
                       f"{settings.max_deadline_s}", "deadline_s")
