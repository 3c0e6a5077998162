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
from pydantic import BaseModel, ConfigDict, Field, field_validator

from shared.http import (
    ApiError,
    HttpMetrics,
    bearer_auth,
    install_error_handlers,
    ops_router,
    require_json,
)
from shared.messages import Observation, Option, ReasonerDecision, ReasonerRequest

from .backends import BackendConfig, OpenAIChatBackend
from .deciding import Decider, DeciderConfig, FallbackPolicy
from .settings import ReasonerSettings

log = logging.getLogger(__name__)


class ReasonBody(BaseModel):
    model_config = ConfigDict(extra="forbid")

    request_id: str | None = Field(default=None, min_length=1, max_length=128)
    observation: Observation
    options: list[Option] = Field(min_length=1)
    deadline_s: float = Field(gt=0.0)

    @field_validator("options")
    @classmethod
    def _unique_indices(cls, options: list[Option]) -> list[Option]:
        indices = [o.index for o in options]
        if len(set(indices)) != len(indices):
            raise ValueError("option indices must be unique")
        return options


class Metrics:
    def __init__(self, registry: CollectorRegistry) -> None:
        self.latency = Histogram(
            "aesop_reasoner_decision_seconds", "Time from request to decision",
            ["source"], registry=registry,
            buckets=(.05, .1, .25, .5, 1, 1.5, 2, 3, 4, 5, 7.5, 10, 20))
        self.decisions = Counter("aesop_reasoner_decisions", "Decisions by source",
                                 ["source"], registry=registry)

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


def build_decider(settings: ReasonerSettings) -> Decider:
    backends = [OpenAIChatBackend(c) for c in backend_configs(settings)]
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

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.decider = decider or build_decider(settings)
        worker = worker_factory(app.state.decider, metrics) if worker_factory else None
        task = asyncio.create_task(worker.run()) if worker else None
        state["started"] = True
        try:
            yield
        finally:
            state["started"] = False
            if worker is not None and task is not None:
                await worker.stop()
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
            await app.state.decider.aclose()

    app = FastAPI(title="AESOP slow-reasoner service", version="1", lifespan=lifespan)
    install_error_handlers(app)
    require_json(app)
    HttpMetrics(registry, "reasoner").install(app)
    app.include_router(ops_router(
        registry, lambda: None if state["started"] else {"reason": "starting"}))
    auth = [Depends(bearer_auth(settings.admin_token))]

    @app.post("/v1/reason", dependencies=auth)
    async def reason(body: ReasonBody, decider: DeciderDep) -> dict[str, Any]:
        check_request(body, settings)
        request = ReasonerRequest(
            robot=body.observation.robot, request_id=body.request_id or uuid.uuid4().hex,
            observation=body.observation, options=tuple(body.options),
            deadline_s=body.deadline_s)
        decision = await decider.decide(request)
        metrics.observe(decision)
        return decision.model_dump()

    @app.get("/v1/backends")
    async def backends() -> dict[str, Any]:
        return {"backends": [
            {"name": c.name, "base_url": c.base_url, "model": c.model, "stream": c.stream,
             "json_schema": c.json_schema} for c in backend_configs(settings)],
            "hedge_after_s": settings.hedge_after_s, "domain": settings.domain,
            "variant": settings.variant, "fallback": settings.fallback}

    return app


def check_request(body: ReasonBody, settings: ReasonerSettings) -> None:
    """The limits that depend on settings (the shape is checked by pydantic)."""
    if len(body.observation.text) > settings.max_observation_chars:
        raise ApiError(422, "invalid", f"observation has {len(body.observation.text)} "
                       f"characters; the limit is {settings.max_observation_chars}",
                       "observation.text")
    if len(body.options) > settings.max_options:
        raise ApiError(422, "invalid", f"{len(body.options)} options; the limit is "
                       f"{settings.max_options}", "options")
    if body.deadline_s > settings.max_deadline_s:
        raise ApiError(422, "invalid", f"deadline_s {body.deadline_s} is over the limit "
                       f"{settings.max_deadline_s}", "deadline_s")
