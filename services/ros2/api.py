"""The bridge's app: the bridge run on the bus, and ``GET /v1/bridge``, what each topic did.

Its lifespan opens the bus and runs :class:`.bridge.Bridge`; ``/healthz``, ``/readyz``,
``/metrics`` from ``service_app``."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import asdict
from typing import Annotated

from fastapi import APIRouter, Depends, FastAPI
from prometheus_client import CollectorRegistry

from shared.bus import Bus
from shared.http import from_state, service_app

from .bridge import SERVICE, Bridge, BridgeMetrics
from .config import BridgeConfig
from .schemas import BridgeAnswer, QueueAnswer, TopicAnswer
from .settings import Ros2Settings

BridgeDep = Annotated[Bridge, Depends(from_state("bridge"))]
router = APIRouter()


@router.get("/v1/bridge")
async def bridge_status(bridge: BridgeDep) -> BridgeAnswer:
    return BridgeAnswer(
        robot=bridge.robot, domain_id=bridge.config.domain_id, node=bridge.config.node,
        zid=bridge.zid, node_token=bridge.node.token(),
        topics=[TopicAnswer(**asdict(s)) for s in bridge.topics()],
        queue_dropped=bridge.queue_dropped,
        queues=[QueueAnswer(**q) for q in bridge.queues()])


def create_app(settings: Ros2Settings, config: BridgeConfig,
               bus_factory: Callable[[], Bus]) -> FastAPI:
    registry = CollectorRegistry()
    metrics = BridgeMetrics(registry)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        bus = bus_factory()
        bridge = Bridge(config, bus, metrics)
        try:
            bridge.start()
            app.state.bridge = bridge
            yield
        finally:
            await asyncio.to_thread(bridge.stop)
            bus.close()

    app = service_app(
        "AESOP ROS 2 bridge", service=SERVICE, lifespan=lifespan, registry=registry,
        ready=lambda: None if getattr(app.state, "bridge", None) is not None
        else {"reason": "the bridge has not started"},
        admin_token=settings.admin_token, max_body_bytes=settings.max_body_bytes)
    app.state.settings = settings
    app.include_router(router)
    return app
