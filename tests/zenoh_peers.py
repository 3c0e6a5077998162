"""Two real Zenoh peers on loopback for tests: free ports, routing waits, fixtures.

Nothing is timed: every wait polls a condition under a generous deadline.
"""

from __future__ import annotations

import asyncio
import contextlib
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

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


@contextlib.contextmanager
def aesop_router(folder: Path, robot: str = "robot0") -> Iterator[str]:
    """``aesop up``'s router, which lets in only its users (passwords written to
    ``folder``, ``<user>.password`` each), on a free port: its endpoint."""
    from tools.stack.acl import new_passwords, users_of, write_credentials

    write_credentials(folder, new_passwords(users_of((robot,))))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "tools.stack.router", "--listen", endpoint,
                             "--users", str(folder / "users.txt"), "--robot", robot],
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()  # printed once it listens
        assert "listening" in line, line
        yield endpoint
    finally:
        proc.terminate()
        proc.wait(10)


@pytest.fixture
def listener(endpoint: str) -> Iterator[Bus]:
    with Bus.open(BusSettings(zenoh_listen=[endpoint]), "listener") as bus:
        yield bus


@pytest.fixture
def connector(endpoint: str, listener: Bus) -> Iterator[Bus]:
    with Bus.open(BusSettings(zenoh_connect=[endpoint]), "connector") as bus:
        yield bus
