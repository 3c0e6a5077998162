"""``aesop bench fleet``: a fleet's observations on detector replicas sharing one PostgreSQL.

It starts a PostgreSQL server (:mod:`tools.stack.postgres`, in a temporary folder) and
``aesop serve embedding`` replicas on it (``AESOP_EMBEDDING_STORE``, each its own name and
data folder, Zenoh clients of this process's endpoint); the hardware scene's cache is built
and calibrated on the first (as ``aesop bench bus`` builds it) and followed by the others.
Then:

1. **Verdicts**: on one replica, then on two, ``robots`` simulated robots (1, 4, 16 and 64)
   each publish the camera's observations at ``rate_hz`` for ``seconds`` (the hardware
   scene's nominal and anomalous views in turn, each robot at its own phase). Per
   observation: publish to its verdict's arrival here (both on this process's
   ``time.monotonic``); lost: no verdict ``LOST_AFTER_S`` after the last one was
   published. The replicas' CPU (user + system seconds over the run) says what a core
   buys: verdicts per CPU-second.
2. **Replica lag**: ``lags`` single experiences added on the first replica (REST); each one's
   time from its 2xx to the second replica answering with the new version (polled every
   ``POLL_S``): commit, notify, catch up.
3. **Store cost**: in this process, the SQLite store against PostgreSQL (fsync on both, the
   server on this machine): ``adds`` commits of ``batch`` 384-d experiences each (per-commit
   p50 / p99), then a restart: loading the cache with every vector (no index file).

Targets (issue 30): 64 robots at 10 Hz on two replicas with verdict p99 <= 50 ms and none
lost; replica lag p99 <= 1 s. The robots publish from this machine, so they take CPU from
the replicas too.
"""

from __future__ import annotations

import asyncio
import contextlib
import secrets
import shutil
import tempfile
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from services.embedding.client import EmbeddingClient
from services.embedding.settings import SERVICE_MODEL
from shared import topics
from shared.bus import Bus
from shared.messages import AnomalyVerdict
from shared.process import ServiceProcess, free_port
from shared.settings import BusSettings
from shared.tables import table
from tools import progress
from tools.bench.bus import CACHE, WAIT_S, BenchError, embedding_process, say
from tools.scenes import QUADROTOR_SCENARIOS
from tools.scenes.hardware import build_scene_cache, camera_observation, observation_text
from tools.stack.postgres import PostgresServer

LOST_AFTER_S = 5.0  # a verdict later than this after the last observation is lost
POLL_S = 0.002  # how often the second replica is asked for its version
TARGET_P99_MS = 50.0
TARGET_LAG_S = 1.0
FLEETS = (1, 4, 16, 64)


class Fleet:
    """``robots`` robots publishing at ``rate_hz`` on one session; verdicts as they come."""

    def __init__(self, bus: Bus, robots: int, texts: list[str]) -> None:
        self.bus, self.texts = bus, texts
        self.robots = [f"fleet{i}" for i in range(robots)]
        self.sent: dict[tuple[str, int], float] = {}
        self.arrived: dict[tuple[str, int], float] = {}
        self._sub = bus.subscribe(topics.anomaly(topics.ANY_ROBOT), AnomalyVerdict,
                                  maxsize=65536)
        self._task = asyncio.create_task(self._collect())

    async def _collect(self) -> None:
        async for got in self._sub:
            key = (got.message.robot, got.message.seq)
            self.arrived.setdefault(key, got.received_at)

    async def warm_up(self, first_seq: int) -> None:
        """Untimed: one observation per robot, again until each has its verdict (a
        replica that just joined loads its model with its first)."""
        deadline = time.monotonic() + WAIT_S
        seq = first_seq
        while not all((robot, s) in self.arrived for robot in self.robots
                      for s in range(first_seq, seq)) or seq == first_seq:
            if time.monotonic() > deadline:
                raise BenchError("no verdicts for every robot: are the replicas up?")
            for robot in self.robots:
                self.bus.publish(topics.observation(robot),
                                 camera_observation(self.texts[0], seq, robot))
            seq += 1
            await asyncio.sleep(0.5)
        self.arrived.clear()

    async def run(self, seconds: float, rate_hz: float, first_seq: int) -> float:
        """Each robot one observation per period, the robots spread over the period;
        then until the verdicts are in (at most :data:`LOST_AFTER_S`). The seconds it took."""
        period = 1.0 / rate_hz
        start = time.monotonic()
        n = int(seconds * rate_hz)
        for k in range(n):
            for i, robot in enumerate(self.robots):
                due = start + (k + i / len(self.robots)) * period
                delay = due - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                seq = first_seq + k
                text = self.texts[(k + i) % len(self.texts)]
                self.sent[robot, seq] = time.monotonic()
                self.bus.publish(topics.observation(robot),
                                 camera_observation(text, seq, robot))
        deadline = time.monotonic() + LOST_AFTER_S
        while len(self.arrived.keys() & self.sent.keys()) < len(self.sent) and \
                time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        return time.monotonic() - start

    def result(self) -> tuple[list[float], int]:
        ms = [(self.arrived[key] - sent) * 1000.0 for key, sent in self.sent.items()
              if key in self.arrived]
        return ms, len(self.sent) - len(ms)

    async def close(self) -> None:
        self._sub.close()
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)


def spread(ms: list[float]) -> dict[str, float | None]:
    if not ms:
        return {"p50": None, "p99": None, "max": None}
    return {"p50": round(float(np.percentile(ms, 50)), 2),
            "p99": round(float(np.percentile(ms, 99)), 2), "max": round(max(ms), 2)}


def cpu_seconds(processes: list[ServiceProcess]) -> float:
    import psutil

    total = 0.0
    for p in processes:
        times = psutil.Process(p.pid).cpu_times()
        total += times.user + times.system
    return total


async def verdicts(bus: Bus, replicas: list[ServiceProcess], texts: list[str],
                   seconds: float, rate_hz: float, first_seq: int) -> list[dict[str, Any]]:
    rows = []
    for n, robots in enumerate(FLEETS):
        progress.step(f"{robots} robots on {len(replicas)} replica(s)",
                      len(FLEETS) * (len(replicas) - 1) + n + 1, 2 * len(FLEETS))
        fleet = Fleet(bus, robots, texts)
        base = first_seq + 100_000 * n  # no verdict of an earlier run counts in this one
        try:
            await fleet.warm_up(base)
            cpu = cpu_seconds(replicas)
            took = await fleet.run(seconds, rate_hz, base + 1000)
            used = cpu_seconds(replicas) - cpu
        finally:
            await fleet.close()
        ms, lost = fleet.result()
        rows.append({"replicas": len(replicas), "robots": robots,
                     "observations": len(fleet.sent), **spread(ms), "lost": lost,
                     "replica_cpu_percent": round(100 * used / took, 1),
                     "verdicts_per_cpu_s": round(len(ms) / used, 1) if used > 0 else None})
        say(f"  {len(replicas)} replica(s), {robots} robots: p99 {rows[-1]['p99']} ms, "
            f"{lost} lost")
    return rows


async def replica_lag(first: EmbeddingClient, second: EmbeddingClient, n: int) -> list[float]:
    """Seconds from each add's 2xx on ``first`` to ``second`` holding its version."""
    out = []
    for i in range(n):
        added = await first.add_items(CACHE, [{"text": f"a lag probe {i} on the ground",
                                               "id": f"lag-{i}-{secrets.token_hex(4)}"}])
        done = time.monotonic()
        deadline = done + WAIT_S
        while (await second.cache(CACHE)).version < added.version:
            if time.monotonic() > deadline:
                raise BenchError(f"the second replica never reached version {added.version}")
            await asyncio.sleep(POLL_S)
        out.append(time.monotonic() - done)
    return out


def store_cost(pg_url: str, tmp: Path, adds: int, batch: int) -> dict[str, Any]:
    """Commit ``adds`` batches into each store, then load the cache again (no index file)."""
    from services.embedding.detector.cache import Cache, CacheConfig
    from services.embedding.storage.pgstore import PostgresStore
    from services.embedding.storage.store import Store

    rng = np.random.default_rng(0)
    out: dict[str, Any] = {"adds": adds, "batch": batch}
    for kind in ("sqlite", "postgresql"):
        folder = tmp / f"store-{kind}"
        store = (Store(folder) if kind == "sqlite" else PostgresStore(pg_url, folder))
        with store:
            cache = Cache(CacheConfig("cost", None, 384, k=1))
            store.create(cache.config)
            times = []
            for b in range(adds):
                op = cache.plan_add(rng.standard_normal((batch, 384)),
                                    ids=[f"{b}-{i}" for i in range(batch)],
                                    texts=[f"experience {b}-{i}" for i in range(batch)],
                                    metadata=[{}] * batch)
                start = time.perf_counter()
                store.commit("cost", op, cache.header.after(op))
                times.append((time.perf_counter() - start) * 1000.0)
                cache.apply(op)
        with (Store(folder) if kind == "sqlite" else PostgresStore(pg_url, folder)) as again:
            start = time.perf_counter()
            loaded = again.load("cost")
            load_s = time.perf_counter() - start
        assert loaded.size == adds * batch
        out[kind] = {"add_ms": spread(times), "restart_s": round(load_s, 3)}
    return out


@contextlib.contextmanager
def postgres() -> Iterator[PostgresServer]:
    root = Path(tempfile.mkdtemp(prefix="aesop-bench-pg-"))
    root.chmod(0o711)
    server = PostgresServer(root / "pg", free_port())
    server.init()
    server.start()
    try:
        yield server
    finally:
        server.stop()
        shutil.rmtree(root, ignore_errors=True)


@contextlib.asynccontextmanager
async def replica(tmp: Path, name: str, endpoint: str, token: str, url: str
                  ) -> AsyncIterator[tuple[ServiceProcess, EmbeddingClient]]:
    process = embedding_process(tmp / name, endpoint, token, AESOP_EMBEDDING_STORE=url,
                                AESOP_EMBEDDING_REPLICA=name)
    with process:
        async with EmbeddingClient(process.url, token=token, timeout_s=WAIT_S * 5) as client:
            yield process, client


async def _bench(seconds: float, rate_hz: float, lags: int, adds: int, batch: int,
                 model: str) -> dict[str, Any]:
    token = secrets.token_urlsafe(24)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    texts = [observation_text(s.detections) for s in QUADROTOR_SCENARIOS.values()]
    with tempfile.TemporaryDirectory(prefix="aesop-bench-fleet-") as name, \
            postgres() as server, \
            Bus.open(BusSettings(zenoh_listen=[endpoint]), "bench") as bus:
        tmp = Path(name)
        url = server.url
        progress.step(f"PostgreSQL on port {server.port}; replicas on Zenoh {endpoint}")
        async with replica(tmp, "replica-1", endpoint, token, url) as (one, first):
            await build_scene_cache(first, CACHE, model=model, say=say)
            await _settle(bus, 1)
            rows = await verdicts(bus, [one], texts, seconds, rate_hz, 1)
            async with replica(tmp, "replica-2", endpoint, token, url) as (two, second):
                await _settle(bus, 2)
                rows += await verdicts(bus, [one, two], texts, seconds, rate_hz, 1_000_000)
                progress.step(f"the replica lag: {lags} adds")
                lag = await replica_lag(first, second, lags)
        progress.step(f"the stores' cost: {adds} commits of {batch} on PostgreSQL and SQLite")
        cost = await asyncio.to_thread(store_cost, url, tmp, adds, batch)
    lag_ms = [s * 1000.0 for s in lag]
    return {"rate_hz": rate_hz, "seconds": seconds, "model": model, "verdicts": rows,
            "lag_ms": spread(lag_ms), "lag_n": len(lag), "store": cost,
            "targets": {"p99_ms": TARGET_P99_MS, "lag_s": TARGET_LAG_S}}


async def _settle(bus: Bus, replicas: int) -> None:
    """Until the replicas' tokens are all seen, then a second for each to see the others."""
    deadline = time.monotonic() + WAIT_S
    while True:
        found = await asyncio.to_thread(
            lambda: list(bus.session.liveliness().get("aesop/health/embedding/*",
                                                      timeout=2.0)))
        if len([r for r in found if r.ok is not None]) >= replicas:
            break
        if time.monotonic() > deadline:
            raise BenchError(f"fewer than {replicas} detector replicas are alive")
        await asyncio.sleep(0.2)
    await asyncio.sleep(1.0)


def run_fleet_bench(seconds: float = 15.0, rate_hz: float = 10.0, lags: int = 100,
                    adds: int = 50, batch: int = 100, model: str | None = None,
                    table_out: bool = True) -> dict[str, Any]:
    result = asyncio.run(_bench(seconds, rate_hz, lags, adds, batch, model or SERVICE_MODEL))
    if table_out:
        print_table(result)
    return result


def print_table(result: dict[str, Any]) -> None:
    rows = [{"replicas": r["replicas"], "robots": r["robots"],
             "observations": r["observations"], "p50 [ms]": r["p50"], "p99 [ms]": r["p99"],
             "max [ms]": r["max"], "lost": r["lost"],
             "replicas' CPU %": r["replica_cpu_percent"],
             "verdicts per CPU-s": r["verdicts_per_cpu_s"]} for r in result["verdicts"]]
    print(table(f"\nobservation -> verdict, each robot at {result['rate_hz']:g} Hz for "
                f"{result['seconds']:g} s", rows))
    lag, cost = result["lag_ms"], result["store"]
    print(f"replica lag (a 2xx on one to the other's new version), {result['lag_n']} adds: "
          f"p50 {lag['p50']} / p99 {lag['p99']} / max {lag['max']} ms\n")
    print(table(f"stores: {cost['adds']} commits of {cost['batch']} experiences, then a "
                "restart", [{"store": k, "add p50 [ms]": cost[k]["add_ms"]["p50"],
                             "add p99 [ms]": cost[k]["add_ms"]["p99"],
                             "restart [s]": cost[k]["restart_s"]}
                            for k in ("sqlite", "postgresql")]))
    two = [r for r in result["verdicts"] if r["replicas"] == 2 and r["robots"] == 64]
    if two:
        met = two[0]["p99"] is not None and two[0]["p99"] <= TARGET_P99_MS and not two[0]["lost"]
        lag_met = lag["p99"] is not None and lag["p99"] <= TARGET_LAG_S * 1000
        print(f"64 robots on two replicas: p99 {two[0]['p99']} ms, {two[0]['lost']} lost "
              f"(target <= {TARGET_P99_MS:g} ms, none lost: {'met' if met else 'MISSED'}); "
              f"replica lag p99 {lag['p99']} ms (target <= {TARGET_LAG_S * 1000:g} ms: "
              f"{'met' if lag_met else 'MISSED'})")
