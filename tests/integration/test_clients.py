"""The typed clients against real HTTP servers: the vector-cache app served by uvicorn on a
real port (with the bag-of-words embedder), and `aesop serve control`, `reasoner` (with
`aesop serve fake-llm`) and `dashboard` as processes."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import uvicorn

from services.control.client import ControlClient
from services.dashboard.client import DashboardClient
from services.embedding.api import create_app
from services.embedding.client import EmbeddingClient
from services.embedding.models.loading import EmbedderPool
from services.embedding.service import CacheService
from services.embedding.settings import EmbeddingSettings
from services.reasoner.client import ReasonerClient
from services.sim.client import SimClient
from shared.client import ServiceError
from shared.jobs import JobInfo
from shared.messages import Observation, Option
from shared.process import ServiceProcess, free_port
from tests.fakes.hash_embedder import HashEmbedder
from tests.zenoh_peers import wait_until

TOKEN = "client-test-token-0123"
NOMINAL = [f"a {c} package on the belt next to a {t}" for c in ("brown", "white", "taped")
           for t in ("shelf", "pallet", "scanner", "worker")]
ODD = "a smoking lithium battery leaking acid everywhere"


@pytest.fixture(scope="module")
def embedding_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    settings = EmbeddingSettings(data_dir=tmp_path_factory.mktemp("embedding"),
                                 admin_token=TOKEN, zenoh_worker=False, fsync=False)
    service = CacheService(settings, embedders=EmbedderPool(loader=lambda m: HashEmbedder()))
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(create_app(settings, service=service),
                                           host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{port}"
    wait_until(lambda: server.started or not thread.is_alive(), "the server to start", 30)
    assert server.started, "the server exited while starting"
    yield url
    server.should_exit = True
    thread.join(10)


async def test_build_calibrate_and_score_a_cache(embedding_url: str) -> None:
    async with EmbeddingClient(embedding_url, token=TOKEN) as client:
        info = await client.create_cache("belt", k=2)
        assert (info.name, info.size, info.k, info.calibration) == ("belt", 0, 2, None)
        added = await client.add_texts("belt", NOMINAL[:6])
        assert added.size == 6 and len(added.ids) == 6 and added.job is not None
        polls: list[JobInfo] = []
        more = await client.add_texts("belt", NOMINAL[6:], progress=polls.append, poll_s=0.05)
        assert more.size == len(NOMINAL) and polls and polls[-1].state == "succeeded"
        cal = await client.calibrate("belt", "tpr-target", tpr=0.5, calibration=[
            (NOMINAL[0], False), (NOMINAL[1], False), (ODD, True), ("a fire", True)])
        assert cal.method == "tpr-target" and cal.cache == "belt" and cal.roc is not None
        scored = await client.score("belt", [NOMINAL[0], ODD])
        assert scored.threshold == cal.threshold and scored.version == cal.version
        assert scored.results[0].is_anomaly is False and scored.results[1].is_anomaly is True
        assert scored.results[0].neighbors[0].text == NOMINAL[0]
        kept = await client.experience("belt", added.ids[0])
        assert kept.text == NOMINAL[0]
        gone = await client.delete("belt", added.ids[0])
        assert gone.size == len(NOMINAL) - 1
        assert [c.name for c in await client.caches()] == ["belt"]
        assert (await client.cache("belt")).calibration.stale  # type: ignore[union-attr]


async def test_errors_come_back_with_status_code_and_field(embedding_url: str) -> None:
    async with EmbeddingClient(embedding_url, token=TOKEN) as client:
        with pytest.raises(ServiceError) as missing:
            await client.cache("nowhere")
        assert (missing.value.status, missing.value.code, missing.value.field) == (
            404, "not_found", "name")
        await client.create_cache("tiny", k=1)
        with pytest.raises(ServiceError) as bad:
            await client.score("tiny", [" "])
        assert bad.value.status == 422 and bad.value.field == "texts[0]"
    async with EmbeddingClient(embedding_url) as anonymous:
        with pytest.raises(ServiceError) as denied:
            await anonymous.create_cache("mine")
        assert denied.value.status == 401 and denied.value.code == "unauthorized"
    async with EmbeddingClient("http://127.0.0.1:9", timeout_s=2) as nobody:
        with pytest.raises(httpx.TransportError):
            await nobody.caches()


@pytest.mark.slow
def test_the_control_client_speaks_to_a_real_control_service(tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {"AESOP_ADMIN_TOKEN": TOKEN, "AESOP_ZENOH_LISTEN": endpoint,
           "AESOP_CONTROL_RATE_HZ": "10"}
    sim_port = free_port()
    with ServiceProcess(["serve", "control", "--port", str(port)], port=port, env=env,
                        log_path=tmp_path / "control.log", ready_timeout_s=60) as proc:
        asyncio.run(_control_round_trip(proc.url, None))
        sim_env = {"AESOP_ADMIN_TOKEN": TOKEN, "AESOP_ZENOH_CONNECT": endpoint}
        with ServiceProcess(["serve", "sim", "--port", str(sim_port)], port=sim_port,
                            env=sim_env, log_path=tmp_path / "sim.log",
                            ready_timeout_s=60) as sim:
            asyncio.run(_sim_round_trip(sim.url, proc.url))


async def _control_round_trip(url: str, position: tuple[float, float, float] | None) -> None:
    async with ControlClient(url, token=TOKEN) as control:
        state = await control.state()
        assert state.mode == "waiting" and state.method == "aesop"
        assert state.scenario == "paper-quadrotor-sim"  # the default scene, paper.yaml
        regions = await control.regions()
        assert len(regions.regions) == 4 and len(regions.goal) == 3
        reset = await control.reset()  # no vehicle yet: nowhere to say
        assert reset.position == position and reset.mode == "waiting"
        swapped = await control.set_regions(regions.regions[:2])
        assert [r.name for r in swapped.regions] == [r.name for r in regions.regions[:2]]


async def _sim_round_trip(url: str, control_url: str) -> None:
    async with SimClient(url, token=TOKEN) as sim, \
            ControlClient(control_url, token=TOKEN) as control:
        moved = await sim.reset([10.0, 2.0, 2.0])
        assert moved.truth.position == pytest.approx((10.0, 2.0, 2.0), abs=1e-3)
        assert moved.t < 0.5  # a new flight
        state = await sim.state()
        assert state.truth.position == pytest.approx((10.0, 2.0, 2.0), abs=0.01)
        assert state.holding and state.scenario == "paper-quadrotor-sim"
        assert (await sim.reporting(delay_s=0.02)).reporting["delay_s"] == 0.02
        assert (await sim.faults(deaf_s=1.0)).faults["deaf_left_s"] > 0
        deadline = asyncio.get_running_loop().time() + 30

        async def seen_there() -> bool:  # the moved vehicle's state has reached control
            shown = (await control.state()).state
            return shown is not None and shown.x[:3] == pytest.approx((10.0, 2.0, 2.0),
                                                                      abs=0.01)

        while not await seen_there():
            assert asyncio.get_running_loop().time() < deadline
            await asyncio.sleep(0.1)
        reset = await control.reset()
        assert reset.position == pytest.approx((10.0, 2.0, 2.0), abs=0.01)
        trace = await sim.trace()
        assert len(trace.t) == len(trace.x) > 0 and len(trace.x[0]) == 12
        with pytest.raises(ServiceError) as outside:
            await sim.reset([1e6, 0.0, 1.0])
        assert outside.value.status == 422 and outside.value.field == "start"


@pytest.mark.slow
def test_the_reasoner_client_speaks_to_a_real_reasoner_and_llm(tmp_path: Path) -> None:
    llm_port, port = free_port(), free_port()
    env = {"AESOP_ADMIN_TOKEN": TOKEN, "AESOP_ZENOH_LISTEN": f"tcp/127.0.0.1:{free_port()}",
           "AESOP_REASONER_LLM_BASE_URL": f"http://127.0.0.1:{llm_port}/v1",
           "AESOP_REASONER_LLM_MODEL": "fake-fixed-0.05"}
    with ServiceProcess(["serve", "fake-llm", "--port", str(llm_port)], port=llm_port,
                        log_path=tmp_path / "llm.log"), \
            ServiceProcess(["serve", "reasoner", "--port", str(port)], port=port, env=env,
                           log_path=tmp_path / "reasoner.log") as proc:
        asyncio.run(_reasoner_round_trip(proc.url))


async def _reasoner_round_trip(url: str) -> None:
    options = [Option(index=0, label="continue"), Option(index=1, label="land on the blue box")]
    scene = Observation(seq=1, text="a red box is on fire below the drone", task="inspect")
    async with ReasonerClient(url, token=TOKEN) as reasoner:
        decision = await reasoner.reason(scene, options, deadline_s=5.0, request_id="r1")
        assert decision.request_id == "r1" and decision.source == "llm"
        assert decision.choice in (0, 1)
        backends = await reasoner.backends()
        assert [b.name for b in backends.backends] == ["primary"]
        assert backends.backends[0].model == "fake-fixed-0.05"
        accepted = await reasoner.calibrate_latency(n=60, warmup=1, timeout_s=5.0)
        job = await reasoner.wait_for_job(accepted.job, poll_s=0.1)
        assert job.result is not None and job.result["n"] == 60 and job.result["k_s"] > 0
        with pytest.raises(ServiceError) as late:
            await reasoner.reason(scene, options, deadline_s=1e9)
        assert late.value.status == 422 and late.value.field == "deadline_s"
        with pytest.raises(ServiceError) as hedge:
            await reasoner.calibrate_latency(backend="hedge")
        assert hedge.value.status == 409 and hedge.value.field == "backend"


@pytest.mark.slow
def test_the_dashboard_client_reads_a_real_dashboards_snapshot(tmp_path: Path) -> None:
    port = free_port()
    env = {"AESOP_ZENOH_LISTEN": f"tcp/127.0.0.1:{free_port()}", "AESOP_ROBOT": "drone7"}
    with ServiceProcess(["serve", "dashboard", "--port", str(port)], port=port, env=env,
                        log_path=tmp_path / "dashboard.log") as proc:
        asyncio.run(_dashboard_round_trip(proc.url))


async def _dashboard_round_trip(url: str) -> None:
    async with DashboardClient(url) as dashboard:
        snapshot = await dashboard.snapshot()
    assert snapshot.robot == "drone7" and snapshot.state is None and snapshot.trail == []
