"""Issue 14: REST scoring cannot stall the bus verdicts.

A gated embedder holds the one compute thread while work queues behind it; what it
embeds next shows the order. Before: one FIFO micro-batcher shared by the bus and REST,
no cap on texts per request or pending work, and work kept running for callers that
had gone.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.embedding.api import create_app
from services.embedding.detector.errors import Busy
from services.embedding.models.loading import EmbedderPool
from services.embedding.schemas import Item
from services.embedding.service import CacheService
from services.embedding.settings import EmbeddingLimits, EmbeddingSettings, EmbeddingTuning
from tests.fakes.hash_embedder import HashEmbedder

pytestmark = pytest.mark.timeout(60)

NOMINAL = [f"a {c} box on the ground near a {t}" for c in ("red", "blue", "green")
           for t in ("drill", "chair")]
TOKEN = "lanes-token-0123456789"


class GatedEmbedder(HashEmbedder):
    """Records every text it embeds; while ``gate`` is shut, the first batch waits."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[str] = []
        self.gate = threading.Event()
        self.gate.set()
        self.waiting = threading.Event()

    def _encode(self, batch: list[str]) -> np.ndarray:
        if not self.gate.is_set():
            self.waiting.set()
            self.gate.wait(30)
        self.seen.extend(batch)
        return super()._encode(batch)


def settings_for(tmp_path: Path, **kw: object) -> EmbeddingSettings:
    return EmbeddingSettings(data_dir=tmp_path, fsync=False, zenoh_worker=False,
                             admin_token=TOKEN, **kw)


@pytest.fixture
async def gated(tmp_path: Path) -> AsyncIterator[tuple[CacheService, GatedEmbedder]]:
    embedder = GatedEmbedder()
    svc = CacheService(settings_for(tmp_path, tuning=EmbeddingTuning(score_chunk=2),
                                    limits=EmbeddingLimits(max_pending_texts=64)),
                       embedders=EmbedderPool(loader=lambda _: embedder))
    await svc.start()
    await svc.create("scene", model="hash", k=1)
    await svc.add("scene", [Item(text=t) for t in NOMINAL])
    embedder.seen.clear()
    yield svc, embedder
    embedder.gate.set()
    await svc.close()


async def hold_compute(embedder: GatedEmbedder, svc: CacheService) -> asyncio.Task[object]:
    """A REST request whose first chunk holds the compute thread until the gate opens."""
    embedder.gate.clear()
    task = asyncio.create_task(svc.scorer.score_texts("scene", ["holder one", "holder two"]))
    await asyncio.to_thread(embedder.waiting.wait, 10)
    return task


async def test_bus_verdicts_go_before_queued_rest_work(
        gated: tuple[CacheService, GatedEmbedder]) -> None:
    svc, embedder = gated
    holder = await hold_compute(embedder, svc)
    rest = [asyncio.create_task(svc.scorer.score_texts("scene", [f"rest {i} a", f"rest {i} b"]))
            for i in range(3)]
    await asyncio.sleep(0.05)  # the REST chunks are queued on the compute thread
    bus = asyncio.create_task(svc.scorer.score_texts("scene", ["bus observation"], urgent=True))
    await asyncio.sleep(0.05)
    embedder.gate.set()
    await asyncio.gather(holder, bus, *rest)
    after_holder = embedder.seen[2:]
    assert after_holder[0] == "bus observation", embedder.seen


async def test_a_long_rest_request_is_cut_into_chunks_the_bus_can_pass(
        gated: tuple[CacheService, GatedEmbedder]) -> None:
    svc, embedder = gated
    holder = await hold_compute(embedder, svc)
    long = asyncio.create_task(svc.scorer.score_texts("scene", [f"long {i}" for i in range(10)]))
    await asyncio.sleep(0.05)
    bus = asyncio.create_task(svc.scorer.score_texts("scene", ["bus observation"], urgent=True))
    await asyncio.sleep(0.05)
    embedder.gate.set()
    results = await long
    await asyncio.gather(holder, bus)
    assert len(results.results) == 10
    assert embedder.seen.index("bus observation") < embedder.seen.index("long 2")


async def test_pending_rest_work_past_the_cap_is_refused(tmp_path: Path) -> None:
    embedder = GatedEmbedder()
    svc = CacheService(settings_for(tmp_path, tuning=EmbeddingTuning(score_chunk=2),
                                    limits=EmbeddingLimits(max_pending_texts=4)),
                       embedders=EmbedderPool(loader=lambda _: embedder))
    await svc.start()
    try:
        await svc.create("scene", model="hash", k=1)
        await svc.add("scene", [Item(text=t) for t in NOMINAL])
        holder = await hold_compute(embedder, svc)  # 2 pending
        with pytest.raises(Busy) as busy:
            await svc.scorer.score_texts("scene", ["one", "two", "three"])  # 5 > 4
        assert busy.value.field == "texts"
        assert "AESOP_EMBEDDING_LIMITS__MAX_PENDING_TEXTS" in busy.value.message
        bus = await asyncio.wait_for(
            asyncio.gather(asyncio.to_thread(embedder.gate.set),
                           svc.scorer.score_texts("scene", ["bus"], urgent=True)), 10)
        assert len(bus[1].results) == 1  # the bus is never refused for REST's load
        await holder
        assert len((await svc.scorer.score_texts("scene", ["one", "two", "three"])).results) == 3
    finally:
        embedder.gate.set()
        await svc.close()


async def test_work_of_a_caller_that_left_is_dropped(
        gated: tuple[CacheService, GatedEmbedder]) -> None:
    svc, embedder = gated
    holder = await hold_compute(embedder, svc)
    gone = asyncio.create_task(svc.scorer.score_texts("scene", [f"gone {i}" for i in range(6)]))
    await asyncio.sleep(0.05)
    gone.cancel()
    embedder.gate.set()
    await holder
    await svc.scorer.score_texts("scene", ["after"])  # the compute thread has drained
    assert not [t for t in embedder.seen if t.startswith("gone")], embedder.seen


async def test_a_client_that_disconnects_stops_its_scoring(tmp_path: Path) -> None:
    """Over the app's own ASGI interface: the body arrives, then the client leaves."""
    embedder = GatedEmbedder()
    svc = CacheService(settings_for(tmp_path, tuning=EmbeddingTuning(score_chunk=2)),
                       embedders=EmbedderPool(loader=lambda _: embedder))
    app = create_app(settings_for(tmp_path, tuning=EmbeddingTuning(score_chunk=2)), service=svc)
    with TestClient(app, headers={"Authorization": f"Bearer {TOKEN}"}) as client:
        assert client.put("/v1/caches/scene", json={"model": "hash", "k": 1}).status_code == 201
        client.post("/v1/caches/scene/experiences",
                    json={"items": [{"text": t} for t in NOMINAL]}).raise_for_status()
        embedder.gate.clear()
        body = b'{"texts": [' + b",".join(b'"left %d"' % i for i in range(8)) + b"]}"
        left = threading.Event()

        async def call() -> None:
            sent: list[dict[str, object]] = []
            messages = [{"type": "http.request", "body": body, "more_body": False}]

            async def receive() -> dict[str, object]:
                if messages:
                    return messages.pop(0)
                await asyncio.to_thread(embedder.waiting.wait, 10)
                left.set()
                return {"type": "http.disconnect"}

            async def send(message: dict[str, object]) -> None:
                sent.append(message)

            scope = {"type": "http", "method": "POST", "path": "/v1/caches/scene/score",
                     "raw_path": b"/v1/caches/scene/score", "query_string": b"",
                     "headers": [(b"host", b"127.0.0.1"),
                                 (b"content-type", b"application/json"),
                                 (b"authorization", f"Bearer {TOKEN}".encode())],
                     "http_version": "1.1", "scheme": "http", "server": ("127.0.0.1", 80),
                     "client": ("127.0.0.1", 5), "root_path": "", "app": app}
            await app(scope, receive, send)  # type: ignore[arg-type]

        client.portal.call(call)  # type: ignore[union-attr]
        assert left.is_set()
        embedder.gate.set()
        client.post("/v1/caches/scene/score", json={"texts": ["after"]}).raise_for_status()
    assert [t for t in embedder.seen if t.startswith("left")] == ["left 0", "left 1"], \
        embedder.seen  # the chunk that was running when it left; no more


def test_texts_per_score_request_are_capped(tmp_path: Path) -> None:
    svc = CacheService(settings_for(tmp_path),
                       embedders=EmbedderPool(loader=lambda _: HashEmbedder()))
    with TestClient(create_app(settings_for(tmp_path), service=svc),
                    headers={"Authorization": f"Bearer {TOKEN}"}) as client:
        client.put("/v1/caches/scene", json={"model": "hash", "k": 1}).raise_for_status()
        client.post("/v1/caches/scene/experiences",
                    json={"items": [{"text": t} for t in NOMINAL]}).raise_for_status()
        r = client.post("/v1/caches/scene/score", json={"texts": ["a box"] * 257})
        assert r.status_code == 413, r.text
        assert r.json()["error"]["field"] == "texts"
        assert "256" in r.json()["error"]["message"]
        assert client.post("/v1/caches/scene/score",
                           json={"texts": ["a box"] * 256}).status_code == 200


def test_background_add_jobs_are_capped(tmp_path: Path) -> None:
    embedder = GatedEmbedder()
    settings = settings_for(tmp_path, limits=EmbeddingLimits(max_jobs=1))
    svc = CacheService(settings, embedders=EmbedderPool(loader=lambda _: embedder))
    with TestClient(create_app(settings, service=svc),
                    headers={"Authorization": f"Bearer {TOKEN}"}) as client:
        client.put("/v1/caches/scene", json={"model": "hash", "k": 1}).raise_for_status()
        embedder.gate.clear()
        items = {"items": [{"text": t} for t in NOMINAL]}
        first = client.post("/v1/caches/scene/experiences?wait=false", json=items)
        assert first.status_code == 202
        second = client.post("/v1/caches/scene/experiences?wait=false", json=items)
        assert second.status_code == 429, second.text
        assert "AESOP_EMBEDDING_LIMITS__MAX_JOBS" in second.json()["error"]["message"]
        embedder.gate.set()
