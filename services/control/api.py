"""HTTP admin API of the control-loop service.

``GET /v1/state`` (the newest ControlState and the loop's timing),
``GET /v1/regions``, ``POST /v1/regions`` (replace the recovery regions while the
flight is nominal or waiting; admin token), ``POST /v1/reset`` (restart the flight;
admin token), and ``/healthz``, ``/readyz``, ``/metrics``.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI
from prometheus_client import CollectorRegistry

from shared.bus import Bus
from shared.http import ApiError, bearer_auth, errors, service_app

from .loop import ControlRuntime, NotNominal
from .scenario import ScenarioError, regions_from_list
from .schemas import RegionsAnswer, RegionsBody, ResetAnswer, ResetBody, State
from .service import SERVICE, ControlMetrics, ControlService, regions_message
from .settings import ControlSettings


def create_app(settings: ControlSettings, runtime: ControlRuntime,
               bus_factory: Callable[[], Bus] | None = None) -> FastAPI:
    """The app; its lifespan opens the bus (``bus_factory``) and runs the loop."""
    registry = CollectorRegistry()
    metrics = ControlMetrics(registry)
    holder: dict[str, ControlService] = {}

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        bus = bus_factory() if bus_factory is not None else None
        service = ControlService(settings, runtime, bus, metrics, owns_bus=bus is not None)
        holder["service"] = service
        service.start()
        try:
            yield
        finally:
            await asyncio.to_thread(service.stop)
            service.close()

    limits = runtime.scenario.limits  # the fence: positions outside it are refused
    inside = {"prefixItems": [{"type": "number", "minimum": lo, "maximum": hi}
                              for lo, hi in zip(limits.position_lo, limits.position_hi,
                                                strict=True)]}
    app = service_app(
        "AESOP control-loop service", service=SERVICE, lifespan=lifespan, registry=registry,
        ready=lambda: None if runtime.last is not None else {"reason": "no tick yet"},
        limits={"ResetBody": {"start": inside},
                "RegionIn": {"position_lo": inside, "position_hi": inside}})
    auth = [Depends(bearer_auth(settings.admin_token))]

    @app.get("/v1/state")
    async def state() -> State:
        last = runtime.last
        service = holder.get("service")
        plan = None if last is None else last.output.plan
        return State(
            robot=settings.robot, state=None if last is None else last.state,
            mode=runtime.mode, status=None if last is None else last.output.status.value,
            method=settings.method, scenario=runtime.scenario.name,
            verdict_stale=None if last is None else last.stale,
            pending_request=runtime.pending,
            loop={
                "rate_hz": 1.0 / runtime.period_s,
                **(service.scheduler.stats.summary() if service else {}),
                "last_step_ms": None if last is None else round(last.step_ms, 3),
                "last_solve_ms": None if plan is None else round(float(plan.solve_ms), 3),
            })

    def regions_body() -> RegionsAnswer:
        message = regions_message(runtime.scenario, settings.robot)
        return RegionsAnswer(regions=list(message.regions), goal=message.goal, mode=runtime.mode)

    @app.get("/v1/regions")
    async def get_regions() -> RegionsAnswer:
        return regions_body()

    @app.post("/v1/regions", dependencies=auth, responses=errors(401, 409))
    async def post_regions(body: RegionsBody) -> RegionsAnswer:
        try:
            regions = regions_from_list([r.model_dump(exclude_none=True) for r in body.regions])
            await runtime.replace_regions(regions)
        except ScenarioError as exc:
            raise ApiError(422, "invalid", str(exc), exc.field) from None
        except NotNominal as exc:
            raise ApiError(409, "conflict", f"the flight is in mode {exc}: recovery regions "
                           "change only while nominal or waiting (POST /v1/reset first)",
                           "mode") from None
        return regions_body()

    @app.post("/v1/reset", dependencies=auth, responses=errors(401))
    async def reset(body: ResetBody | None = None) -> ResetAnswer:
        try:
            x0 = await runtime.reset(None if body is None else body.start)
        except ValueError as exc:
            raise ApiError(422, "invalid", str(exc), "start") from None
        return ResetAnswer(start=(float(x0[0]), float(x0[1]), float(x0[2])), mode=runtime.mode)

    return app
