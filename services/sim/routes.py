"""The simulator's routes: ``GET /v1/state``, ``GET /v1/trace``, ``POST /v1/reset``,
``PUT /v1/reporting``, ``POST /v1/faults``. Each takes what it needs as ``Annotated``
dependencies from ``app.state`` (set by :func:`.api.create_app`)."""

from __future__ import annotations

from dataclasses import asdict
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Depends

from shared.http import ApiError, errors, from_state

from .schemas import (
    FaultsBody,
    ReportingBody,
    ResetBody,
    SimState,
    TraceAnswer,
    Truth,
)
from .service import SimService
from .start import StartError, start_state

ServiceDep = Annotated[SimService, Depends(from_state("service"))]

router = APIRouter()


def _point(values: np.ndarray) -> tuple[float, float, float]:
    return (float(values[0]), float(values[1]), float(values[2]))


@router.get("/v1/state")
async def state(service: ServiceDep) -> SimState:
    with service.lock:
        vehicle = service.vehicle
        x = vehicle.truth
        sp = vehicle.setpoint
        faults = vehicle.faults
        now = service.clock()
        return SimState(
            robot=vehicle.robot, scenario=vehicle.scenario.name,
            t=round((now - service.reset_at) * vehicle.time_scale, 4),
            time_scale=vehicle.time_scale,
            truth=Truth(position=_point(x[0:3]), velocity=_point(x[3:6]),
                        attitude=_point(x[6:9]), body_rates=_point(x[9:12])),
            holding=vehicle.holding, setpoint_seq=None if sp is None else sp.seq,
            setpoints=vehicle.ages.summary(), states_published=service.published,
            reporting={k: float(v) for k, v in asdict(vehicle.reporting).items()},
            faults={"stopped": faults.stopped,
                    "dropout_left_s": _left(faults.silent_until, now),
                    "deaf_left_s": _left(faults.deaf_until, now),
                    "jump_left_s": _left(faults.jump_until, now)})


def _left(until: float | None, now: float) -> float | None:
    return None if until is None or until <= now else round(until - now, 3)


@router.get("/v1/trace")
async def trace(service: ServiceDep) -> TraceAnswer:
    with service.lock:
        points = list(service.trace)
    return TraceAnswer(t=[p.t for p in points], x=[list(p.x) for p in points],
                       holding=[p.holding for p in points])


@router.post("/v1/reset", responses=errors(401))
async def reset(service: ServiceDep, body: ResetBody | None = None) -> SimState:
    try:
        x0 = start_state(service.vehicle.scenario, None if body is None else body.start,
                         service.settings.seed)
    except StartError as exc:
        raise ApiError(422, "invalid", str(exc), "start") from None
    service.reset(x0)
    return await state(service)


@router.put("/v1/reporting", responses=errors(401))
async def reporting(body: ReportingBody, service: ServiceDep) -> SimState:
    with service.lock:
        service.vehicle.with_reporting(**body.model_dump(exclude_none=True))
    return await state(service)


@router.post("/v1/faults", responses=errors(401, 422))
async def faults(body: FaultsBody, service: ServiceDep) -> SimState:
    if (body.jump is None) != (body.jump_s is None):
        raise ApiError(422, "invalid", "jump and jump_s go together", "jump_s")
    if body.stop and body.resume:
        raise ApiError(422, "invalid", "stop and resume contradict each other", "resume")
    with service.lock:
        now = service.clock()
        f = service.vehicle.faults
        if body.resume:
            f.stopped, f.silent_until = False, None
        if body.stop:
            f.stopped = True
        if body.dropout_s is not None:
            f.silent_until = now + body.dropout_s
        if body.deaf_s is not None:
            f.deaf_until = now + body.deaf_s
        if body.jump is not None and body.jump_s is not None:
            f.jump, f.jump_until = body.jump, now + body.jump_s
    return await state(service)
