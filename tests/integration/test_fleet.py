"""A fleet on one machine, as `aesop up --robots 3 --replicas 2` runs it: three robots fly
the demo's scenarios at once while the detector replica scoring two of them is killed with
SIGKILL and the replicas' PostgreSQL is killed and started again.

What must hold: the dead replica's robots see their verdicts go stale (each loop's own
anomaly: ``verdict_stale``), move to the surviving replica and get verdicts again; a write
acknowledged by the dead replica is on the survivor; with PostgreSQL down a write answers
503 while scoring goes on from memory, and writes resume once it is back; every flight
ends safely (in a region, no constraint violated)."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import tempfile
import threading
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from services.control.core.scenario import load_scenario
from services.embedding.client import EmbeddingClient
from services.embedding.fleet.sharding import assignment
from shared import topics
from shared.bus import Bus
from shared.client import ServiceError
from shared.messages import AnomalyVerdict, Observation
from tests.demo_stack import running_stack
from tests.zenoh_peers import wait_until
from tools.demo.flights import FLEET_ORDER, fly_fleet
from tools.stack.acl import MONITOR
from tools.stack.up import DETECTOR_CACHE, POSTGRES, StackPlan

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(600)]

TOKEN = "fleet-test-token-0123456789"
REPLICAS = ["embedding", "embedding-2"]
# a verdict gap the loop must have seen: verdict_stale_s (0.5 s), a tick at the fleet's 10 Hz
# and the verdict's own way
STALE_SEEN_S = 0.8


async def _write(url: str, ident: str) -> int:
    """A one-experience add on the replica at ``url``: its status."""
    async with EmbeddingClient(url, token=TOKEN, timeout_s=30) as client:
        try:
            await client.add_items(DETECTOR_CACHE, [{"text": f"a {ident} on the ground",
                                                     "id": ident}])
        except ServiceError as exc:
            return exc.status
    return 200


async def _scores(url: str) -> bool:
    async with EmbeddingClient(url, token=TOKEN, timeout_s=30) as client:
        scored = await client.score(DETECTOR_CACHE, ["a red box. a blue box."])
    return len(scored.results) == 1


def test_three_robots_fly_through_a_killed_replica_and_a_postgresql_restart(
        tmp_path: Path) -> None:
    root = Path(tempfile.mkdtemp(prefix="aesop-fleet-"))
    root.chmod(0o711)  # the postgres user reaches the stack's PostgreSQL folder in it
    try:
        _fly_three(tmp_path, root)
    finally:
        shutil.rmtree(root, ignore_errors=True)  # its PostgreSQL cluster: 220 MB


def _fly_three(tmp_path: Path, root: Path) -> None:
    with running_stack(tmp_path, TOKEN, robots=3, replicas=2, data_dir=root / "data") as up:
        plan, stack = up.plan, up.stack
        owners = assignment(plan.robots, REPLICAS)
        victim = max(REPLICAS, key=lambda r: len(owners[r]))
        survivor = next(r for r in REPLICAS if r != victim)
        moved = owners[victim]
        assert moved, owners
        urls = {name: plan.url(name) for name in REPLICAS}
        airborne = threading.Event()
        with ThreadPoolExecutor(1) as pool:
            flying = pool.submit(fly_fleet, plan, scenario=load_scenario(plan.scenario),
                                 airborne=airborne)
            assert airborne.wait(240), "the robots' flights did not all start"
            assert asyncio.run(_write(str(urls[victim]), "acknowledged-before-the-kill")) == 200
            with Arrivals(plan, moved) as arrivals:
                wait_until(lambda: all(arrivals.times.values()), "their verdicts watched", 30)
                killed = time.monotonic()
                os.kill(stack.pids[victim], signal.SIGKILL)
                verdicts_return(plan, moved)
            gaps = arrivals.gaps_around(killed)
            # PostgreSQL killed mid-flight: writes 503, scoring on; started again: writes
            postgres = next(c for c in stack.children if c.name == POSTGRES)
            postgres.signal(signal.SIGKILL)
            postgres.wait(10)
            assert asyncio.run(_write(str(urls[survivor]), "while-postgresql-is-down")) == 503
            assert asyncio.run(_scores(str(urls[survivor])))  # from memory
            verdicts_return(plan, plan.robots)
            postgres.start()
            wait_until(lambda: asyncio.run(_write(str(urls[survivor]),
                                                  f"after-{time.monotonic_ns()}")) == 200,
                       "writes again once PostgreSQL is back", 60)
            result, _ = flying.result(timeout=400)
        with_rows = {row["robot"]: row for row in result["scenarios"]}
        assert set(with_rows) == set(plan.robots)
        for row in with_rows.values():
            said = json.dumps(row)
            assert row["constraint_violations"] == 0, said
            assert row["ended_in"] is not None, said  # at rest in a region, not in the air
        for robot in moved:
            # their detector fell silent until the survivor took them: when that outlasted
            # the loop's verdict_stale_s (0.5 s) and a tick, the loop raised it as an anomaly
            # (a handover faster than that leaves the loop nothing to see)
            assert gaps[robot] < 10.0, gaps
            if gaps[robot] > STALE_SEEN_S:
                assert with_rows[robot]["stale_verdict_alarms"] >= 1, (gaps, with_rows[robot])
        assert [with_rows[r]["name"].split("-")[0] for r in plan.robots] == \
            list(FLEET_ORDER[:3])
        # the write the killed replica acknowledged is on the survivor
        async def kept() -> None:
            async with EmbeddingClient(str(urls[survivor]), token=TOKEN) as client:
                got = await client.experience(DETECTOR_CACHE, "acknowledged-before-the-kill")
                assert got.text == "a acknowledged-before-the-kill on the ground"

        asyncio.run(kept())


class Arrivals:
    """When each of ``robots``' verdicts arrived here (``time.monotonic``)."""

    def __init__(self, plan: StackPlan, robots: Sequence[str]) -> None:
        self.times: dict[str, list[float]] = {r: [] for r in robots}
        self._bus = Bus.open(plan.bus_settings(MONITOR), "fleet-arrivals")
        for robot in robots:
            self._bus.each(topics.anomaly(robot), AnomalyVerdict,
                           lambda got, r=robot: self.times[r].append(got.received_at))

    def __enter__(self) -> Arrivals:
        return self

    def __exit__(self, *exc: object) -> None:
        self._bus.close()

    def gaps_around(self, at: float) -> dict[str, float]:
        """Each robot's wait from its last verdict before ``at`` to its first after."""
        out = {}
        for robot, times in self.times.items():
            before = [t for t in times if t <= at]
            after = [t for t in times if t > at]
            assert before and after, f"{robot}: verdicts before and after the kill"
            out[robot] = round(after[0] - before[-1], 3)
        return out


def verdicts_return(plan: StackPlan, robots: Sequence[str]) -> None:
    """Each of ``robots`` gets a verdict from now on (its camera publishes at 10 Hz)."""
    since = time.monotonic()
    with Bus.open(plan.bus_settings(MONITOR), "fleet-test") as watch:
        slots = {r: watch.latest(topics.anomaly(r), AnomalyVerdict) for r in robots}
        seen = {r: watch.latest(topics.observation(r), Observation) for r in robots}

        def answered() -> bool:
            return all((got := slot.get()) is not None and got.received_at > since
                       for slot in slots.values())

        def ages() -> str:
            newest = {r: (s.get(), seen[r].get()) for r, s in slots.items()}
            return ", ".join(
                f"{r}: {None if g is None else round(g.received_at - since, 2)} (observation "
                f"{None if o is None else round(o.received_at - since, 2)})"
                for r, (g, o) in newest.items())

        try:
            wait_until(answered, f"verdicts for {', '.join(robots)}", 30)
        except AssertionError as exc:
            raise AssertionError(f"{exc} (newest verdict, s after the wait began: {ages()})"
                                 ) from None
