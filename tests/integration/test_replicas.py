"""Detector replicas on one real PostgreSQL server (``AESOP_EMBEDDING_STORE``): each keeps its
own index and follows the others' writes; PostgreSQL going away stops writes (503), not
scoring."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Iterator
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.embedding.api import create_app
from services.embedding.fleet.replicas import Replicas
from services.embedding.fleet.sharding import assignment
from services.embedding.models.loading import EmbedderPool
from services.embedding.schemas import Item
from services.embedding.service import CacheService
from services.embedding.settings import EmbeddingSettings
from services.embedding.worker import DetectorWorker
from shared import topics
from shared.bus import Bus
from shared.messages import AnomalyVerdict, Detection, Observation
from shared.settings import BusSettings
from tests.fakes.hash_embedder import HashEmbedder
from tests.integration.test_api import AUTH, NOMINAL, TOKEN, loader
from tests.zenoh_peers import DEADLINE_S, async_wait_until, routed, wait_until
from tools.stack.postgres import PostgresServer


class Replica:
    """One replica's app on the shared database, and the ages of the changes it followed."""

    def __init__(self, url: str, data_dir: Path) -> None:
        settings = EmbeddingSettings(data_dir=data_dir, admin_token=TOKEN, zenoh_worker=False,
                                     fsync=False, store=url)
        self.lags: list[float] = []
        self.service = CacheService(settings, embedders=EmbedderPool(loader=loader),
                                    on_follow=self.lags.append)
        self.client = TestClient(create_app(settings, service=self.service), headers=AUTH,
                                 base_url="http://127.0.0.1:8001")

    def size(self, name: str = "c") -> int | None:
        r = self.client.get(f"/v1/caches/{name}")
        return r.json()["size"] if r.status_code == 200 else None

    def scores(self, texts: list[str], name: str = "c") -> list[float]:
        r = self.client.post(f"/v1/caches/{name}/score", json={"texts": texts})
        assert r.status_code == 200, r.text
        return [x["score"] for x in r.json()["results"]]


@pytest.fixture
def replicas(postgres_url: str, tmp_path: Path) -> Iterator[tuple[Replica, Replica]]:
    a, b = Replica(postgres_url, tmp_path / "a"), Replica(postgres_url, tmp_path / "b")
    with ExitStack() as stack:
        for replica in (a, b):
            stack.enter_context(replica.client)
        yield a, b


def add(replica: Replica, texts: list[str], name: str = "c") -> dict:
    r = replica.client.post(f"/v1/caches/{name}/experiences",
                            json={"items": [{"text": t} for t in texts]})
    assert r.status_code == 200, r.text
    return r.json()


def test_a_replica_follows_every_write_of_the_other(replicas: tuple[Replica, Replica]) -> None:
    a, b = replicas
    assert a.client.put("/v1/caches/c", json={"model": "m", "k": 2}).status_code == 201
    wait_until(lambda: b.size() == 0, "the new cache on the other replica", 10)
    add(a, NOMINAL[:12])
    wait_until(lambda: b.size() == 12, "the experiences on the other replica", 10)
    probe = ["a flat package on the conveyor belt", "a goat on the conveyor belt"]
    assert b.scores(probe) == a.scores(probe)
    # b writes on top of what it followed; a follows b
    added = add(b, NOMINAL[12:20])
    assert added["version"] == 2 and added["size"] == 20
    r = a.client.post("/v1/caches/c/calibrate", json={"method": "loo-quantile", "alpha": 0.9})
    assert r.status_code == 200, r.text
    assert r.json()["version"] == 3  # a caught up with b's add before it planned
    wait_until(lambda: b.client.get("/v1/caches/c").json()["version"] == 3, "b at version 3",
               10)
    assert b.client.get("/v1/caches/c").json()["threshold"] == r.json()["threshold"]
    assert b.scores(probe) == a.scores(probe)
    assert b.lags and a.lags and max(a.lags + b.lags) < 10


def test_a_proposal_accepted_on_one_replica_is_seen_on_the_other(
        replicas: tuple[Replica, Replica]) -> None:
    a, b = replicas
    assert a.client.put("/v1/caches/c", json={"model": "m", "k": 2}).status_code == 201
    add(a, NOMINAL[:12])
    obs = Observation(robot="r0", seq=7, text="a parcel on the belt next to a forklift",
                      detections=(Detection(label="a forklift"),), task="sorting")
    proposal = a.client.portal.call(  # type: ignore[union-attr]
        lambda: a.service.review.propose("c", obs, request_id="q1", model="m",
                                         rationale="fine", score=0.5, p_value=None,
                                         now=time.time()))
    assert proposal is not None

    def pending_on_b() -> list[str]:
        r = b.client.get("/v1/caches/c/proposals", params={"state": "pending"})
        return [p["id"] for p in r.json()["proposals"]] if r.status_code == 200 else []

    wait_until(lambda: pending_on_b() == [proposal.id], "the proposal on b", 10)
    r = b.client.post("/v1/caches/c/proposals/accept", json={"ids": [proposal.id]})
    assert r.status_code == 200, r.text
    wait_until(lambda: a.size() == 13, "the accepted scene on a", 10)
    r = a.client.get("/v1/caches/c/proposals")
    assert [p["state"] for p in r.json()["proposals"]] == ["accepted"]
    assert a.client.get(f"/v1/caches/c/experiences/{proposal.id}").status_code == 200


def test_postgresql_down_stops_writes_with_503_not_scoring_and_writes_resume(
        postgres_server: PostgresServer, replicas: tuple[Replica, Replica]) -> None:
    a, b = replicas
    assert a.client.put("/v1/caches/c", json={"model": "m", "k": 2}).status_code == 201
    add(a, NOMINAL[:12])
    wait_until(lambda: b.size() == 12, "b caught up", 10)
    probe = ["a flat package on the conveyor belt"]
    before = a.scores(probe)
    postgres_server.stop(immediate=True)
    try:
        r = a.client.post("/v1/caches/c/experiences", json={"items": [{"text": "x"}]})
        assert r.status_code == 503, r.text
        assert r.json()["error"]["code"] == "storage_error" and r.headers["Retry-After"] == "1"
        assert a.scores(probe) == before and b.scores(probe) == before
        assert a.size() == b.size() == 12  # nothing of the refused write anywhere
    finally:
        postgres_server.start()
    add(a, NOMINAL[12:14])  # the replica connects again by itself
    wait_until(lambda: b.size() == 14, "b following again after the restart", 15)


class Recording(HashEmbedder):
    """The hash embedder, keeping every text it embedded."""

    def __init__(self) -> None:
        super().__init__(name="test/hash")
        self.texts: list[str] = []

    def _encode(self, batch: list[str]) -> np.ndarray:
        self.texts += batch
        return super()._encode(batch)


@pytest.fixture
async def two_replicas(postgres_url: str, tmp_path: Path
                       ) -> AsyncIterator[list[tuple[CacheService, Recording]]]:
    made = []
    for name in ("a", "b"):
        embedder = Recording()
        settings = EmbeddingSettings(data_dir=tmp_path / name, fsync=False, store=postgres_url,
                                     zenoh_worker=False)
        svc = CacheService(settings, embedders=EmbedderPool(loader=lambda _, e=embedder: e))
        await svc.start()
        made.append((svc, embedder))
    a = made[0][0]
    await a.create("scene", model="hash", k=1)
    await a.add("scene", [Item(text=t) for t in NOMINAL])
    await a.calibrate("scene", "loo-quantile", alpha=0.9)
    await made[1][0].follow("scene")
    yield made
    for svc, _ in made:
        await svc.close()


async def test_robots_are_shared_among_live_replicas_and_move_when_one_dies(
        two_replicas: list[tuple[CacheService, Recording]], endpoint: str, listener: Bus,
        connector: Bus) -> None:
    (svc_a, seen_a), (svc_b, seen_b) = two_replicas
    bus_b = Bus.open(BusSettings(zenoh_connect=[endpoint]), "replica-b")
    workers = [DetectorWorker(svc_a, listener, cache="scene", replicas=Replicas("a")),
               DetectorWorker(svc_b, bus_b, cache="scene", replicas=Replicas("b"),
                              owns_bus=True)]
    tasks = [asyncio.create_task(w.run()) for w in workers]
    sub = connector.subscribe(topics.anomaly(topics.ANY_ROBOT), AnomalyVerdict, maxsize=256)
    for bus in (listener, bus_b):
        await routed(connector, bus)
        await routed(bus, connector)
    await async_wait_until(lambda: all(w.replicas is not None and w.replicas.live == {"a", "b"}
                                       for w in workers), "each replica seeing the other")
    robots = [f"r{i}" for i in range(8)]
    shares = assignment(robots, ["a", "b"])
    assert shares["a"] and shares["b"]  # both score some of the 8

    async def one_round(seq: int) -> list[tuple[str, int]]:
        seen_a.texts.clear()
        seen_b.texts.clear()
        for robot in robots:
            connector.publish(topics.observation(robot), Observation(
                robot=robot, seq=seq, text=f"{NOMINAL[0]} frame {seq} seen by {robot}"))
        got = []
        for _ in robots:
            received = await asyncio.wait_for(anext(sub), DEADLINE_S)
            got.append((received.message.robot, received.message.seq))
        return sorted(got)

    assert await one_round(0) == sorted((r, 0) for r in robots)
    # each observation was scored by its robot's replica alone
    assert {t.rsplit(" ", 1)[-1] for t in seen_a.texts} == set(shares["a"])
    assert {t.rsplit(" ", 1)[-1] for t in seen_b.texts} == set(shares["b"])

    await workers[1].stop()  # b goes away: its token with its session
    await async_wait_until(lambda: workers[0].replicas is not None
                           and workers[0].replicas.live == {"a"}, "a alone")
    assert await one_round(1) == sorted((r, 1) for r in robots)
    assert {t.rsplit(" ", 1)[-1] for t in seen_a.texts} == set(robots)
    assert seen_b.texts == []
    await workers[0].stop()
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
