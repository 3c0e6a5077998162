"""Two real Zenoh peers on loopback for tests: free ports, routing waits, fixtures.

Nothing is timed: every wait polls a condition under a generous deadline.
"""

from __future__ import annotations

import asyncio
import time
import uuid
from collections.abc import Callable, Iterator

import pytest

from shared import topics
from shared.bus import Bus
from shared.messages import Event
from shared.process import free_port
from shared.settings import BusSettings

DEADLINE_S = 10.0


def wait_until(cond: Callable[[], bool], what: str, timeout: float = DEADLINE_S) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


async def async_wait_until(
    cond: Callable[[], bool], what: str, timeout: float = DEADLINE_S
) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.01)


def wait_routed(pub: Bus, sub: Bus, timeout: float = DEADLINE_S) -> None:
    """Publish probes on a fresh key until ``sub`` gets one.

    Declarations travel in order on the link, so once a probe subscriber
    declared now is reached, every subscriber ``sub`` declared before it is too.
    """
    key = f"{topics.PREFIX}/probe-{uuid.uuid4().hex}/event"
    with sub.latest(key, Event) as probe:
        deadline = time.monotonic() + timeout
        while probe.get() is None:
            if time.monotonic() > deadline:
                raise AssertionError(f"no route from {pub.service} to {sub.service}")
            pub.publish(key, Event(source="test", kind="probe"))
            time.sleep(0.02)


async def routed(pub: Bus, sub: Bus) -> None:
    await asyncio.to_thread(wait_routed, pub, sub)


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def listener(endpoint: str) -> Iterator[Bus]:
    with Bus.open(BusSettings(zenoh_listen=[endpoint]), "listener") as bus:
        yield bus


@pytest.fixture
def connector(endpoint: str, listener: Bus) -> Iterator[Bus]:
    with Bus.open(BusSettings(zenoh_connect=[endpoint]), "connector") as bus:
        yield bus
