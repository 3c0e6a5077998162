"""The control-loop service's routes (shapes in docs/architecture.md): ``GET /v1/state``,
``GET``/``POST /v1/regions``, ``POST /v1/reset``. Each takes what it needs as
``Annotated`` dependencies from ``app.state`` (set by :func:`.api.create_app`): the
runtime, the settings, the running service. The app's guard checks the token (every route
needs it when the service has one)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends

from shared.http import ApiError, errors, from_state

from .core.scenario import ScenarioError, regions_from_list
from .loop import ControlRuntime, NotNominal
from .schemas import RegionsAnswer, RegionsBody, ResetAnswer, ResetBody, State
from .service import ControlService, regions_message
from .settings import ControlSettings

RuntimeDep = Annotated[ControlRuntime, Depends(from_state("runtime"))]
SettingsDep = Annotated[ControlSettings, Depends(from_state("settings"))]
# the running service; None outside the lifespan
ServiceDep = Annotated[ControlService | None, Depends(from_state("service", None))]

router = APIRouter()


@router.get("/v1/state")
async def state(runtime: RuntimeDep, settings: SettingsDep, service: ServiceDep) -> State:
    last = runtime.last
    plan = None if last is None else last.output.plan
    return State(
        robot=settings.robot, state=None if last is None else last.state,
        mode=runtime.mode, status=None if last is None else last.output.status.value,
        method=settings.method, scenario=runtime.scenario.name,
        verdict_stale=None if last is None else last.stale,
        pending_request=runtime.pending,
        vehicle=vehicle_summary(runtime, service),
        loop={
            "rate_hz": 1.0 / runtime.period_s,
            **(service.scheduler.stats.summary() if service else {}),
            "last_step_ms": None if last is None else round(last.step_ms, 3),
            "last_solve_ms": None if plan is None else round(float(plan.solve_ms), 3),
        })


@router.get("/v1/regions")
async def get_regions(runtime: RuntimeDep, settings: SettingsDep) -> RegionsAnswer:
    return regions_answer(runtime, settings)


@router.post("/v1/regions", responses=errors(401, 409))
async def post_regions(body: RegionsBody, runtime: RuntimeDep, settings: SettingsDep
                       ) -> RegionsAnswer:
    try:
        regions = regions_from_list([r.model_dump(exclude_none=True) for r in body.regions])
        await runtime.replace_regions(regions)
    except ScenarioError as exc:
        raise ApiError(422, "invalid", str(exc), exc.field) from None
    except NotNominal as exc:
        raise ApiError(409, "conflict", f"the flight is in mode {exc}: recovery regions "
                       "change only while nominal or waiting (POST /v1/reset first)",
                       "mode") from None
    return regions_answer(runtime, settings)


@router.post("/v1/reset", responses=errors(401))
async def reset(runtime: RuntimeDep, body: ResetBody | None = None) -> ResetAnswer:
    position = await runtime.reset()
    return ResetAnswer(position=position, mode=runtime.mode)


def vehicle_summary(runtime: ControlRuntime, service: ControlService | None
                    ) -> dict[str, float | int | bool | str | None]:
    """The vehicle as the last tick saw it, and the service's window of state ages."""
    last = runtime.last
    reading = None if last is None else last.vehicle
    trip = runtime.vehicle.clock.round_trip_s(runtime.clock())
    return {
        "fresh": None if reading is None else reading.fresh,
        "seq": None if reading is None else reading.seq,
        "age_ms": None if reading is None or reading.age is None
        else round(reading.age * 1000.0, 3),
        "clock": None if reading is None else reading.clock,
        "clock_round_trip_ms": None if trip is None else round(trip * 1000.0, 3),
        "accepted": runtime.vehicle.accepted, "refused": runtime.vehicle.refused,
        **(service.ages.summary() if service else {}),
    }


def regions_answer(runtime: ControlRuntime, settings: ControlSettings) -> RegionsAnswer:
    message = regions_message(runtime.scenario, settings.robot)
    return RegionsAnswer(regions=list(message.regions), goal=message.goal, mode=runtime.mode)
