"""The slow-reasoner service's app: the decider and its backends, the lifespan (the Zenoh
worker, background calibrations); the routes are in :mod:`.routes`."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from prometheus_client import CollectorRegistry

from shared.http import service_app
from shared.jobs import Jobs

from .backends import ChatBackend, Completion, OpenAIChatBackend
from .deciding import Decider, DeciderConfig, FallbackPolicy
from .metrics import ReasonerMetrics
from .routes import Work, router
from .settings import ReasonerSettings


class MeteredBackend:
    """A ``ChatBackend`` that reports each completion (for the token counters)."""

    def __init__(self, inner: ChatBackend, on_completion: Callable[[Completion], None]) -> None:
        self.inner, self.on_completion = inner, on_completion
        self.name, self.model = inner.name, inner.model

    async def complete(self, messages: list[dict[str, str]], *,
                       stop_when: Callable[[str], bool] | None = None,
                       answers: Sequence[int] | None = None) -> Completion:
        completion = await self.inner.complete(messages, stop_when=stop_when, answers=answers)
        self.on_completion(completion)
        return completion

    async def aclose(self) -> None:
        await self.inner.aclose()


def build_decider(settings: ReasonerSettings,
                  on_completion: Callable[[Completion], None] | None = None) -> Decider:
    backends: list[ChatBackend] = [OpenAIChatBackend(c) for c in settings.backends()]
    if on_completion is not None:
        backends = [MeteredBackend(b, on_completion) for b in backends]
    config = DeciderConfig(domain=settings.domain, variant=settings.variant,
                           hedge_after_s=settings.hedge.after_s)
    policy = FallbackPolicy(kind=settings.fallback, ranks=settings.fallback_ranks)
    return Decider(backends, config, policy)


def ready(started: bool, worker: Any) -> dict[str, str] | None:
    """Why the service is not ready (None: it is): starting, or no deadline keeper on the
    bus (it is started again within a second of dying)."""
    if not started:
        return {"reason": "starting"}
    if worker is not None and not getattr(worker, "listening", True):
        return {"reason": "the deadline keeper is not listening on the bus yet"}
    return None


def worker_of(app: FastAPI) -> Any:
    return getattr(app.state, "worker", None)


def create_app(
    settings: ReasonerSettings,
    decider: Decider | None = None,
    worker_factory: Callable[[Decider, ReasonerMetrics], Any] | None = None,
    on_started: Callable[[], None] | None = None,
) -> FastAPI:
    registry = CollectorRegistry()
    metrics = ReasonerMetrics(registry)
    state = {"started": False}
    work = Work(Jobs(max_running=settings.limits.max_calibration_jobs,
                     setting="AESOP_REASONER_LIMITS__MAX_CALIBRATION_JOBS"))

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.decider = decider or build_decider(settings, metrics.count)
        worker = worker_factory(app.state.decider, metrics) if worker_factory else None
        app.state.worker = worker
        task = asyncio.create_task(worker.run()) if worker else None
        state["started"] = True
        if on_started is not None:  # the entry point's process tuning (deciding.settle)
            on_started()
        try:
            yield
        finally:
            state["started"] = False
            for pending in list(work.tasks):
                pending.cancel()
            await asyncio.gather(*work.tasks, return_exceptions=True)
            if worker is not None and task is not None:
                await worker.stop()
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
            await app.state.decider.aclose()

    app = service_app(
        "AESOP slow-reasoner service", service="reasoner", lifespan=lifespan, registry=registry,
        ready=lambda: ready(state["started"], worker_of(app)),
        admin_token=settings.admin_token,
        max_body_bytes=settings.max_body_bytes,
        limits={"ReasonBody": {"options": {"maxItems": settings.limits.max_options},
                               "deadline_s": {"maximum": settings.limits.max_deadline_s}},
                "CalibrateBody": {"options": {"maxItems": settings.limits.max_options}},
                "Observation": {"text": {"maxLength": settings.limits.max_observation_chars}}})
    app.state.settings, app.state.metrics, app.state.work = settings, metrics, work
    app.include_router(router)

    return app
