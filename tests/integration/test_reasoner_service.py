"""The slow-reasoner service: HTTP API and Zenoh worker against a real fake-LLM process."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from services.reasoner.api import build_decider, create_app
from services.reasoner.settings import LLMRequest, ReasonerLimits, ReasonerSettings
from services.reasoner.worker import ReasonerWorker
from shared import topics
from shared.bus import Bus
from shared.messages import Observation, Option, ReasonerDecision, ReasonerRequest
from shared.process import ServiceProcess, free_port
from tests.zenoh_peers import DEADLINE_S, async_wait_until, wait_until

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

TOKEN = "reasoner-test-token-0123"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
OPTIONS = [{"index": 0, "label": "continue"},
           {"index": 1, "label": "alternative landing site", "description": "the blue box"},
           {"index": 2, "label": "holding zone", "description": "hover and wait"}]
RED_BOX = {"seq": 1, "task": "landing on the red box",
           "text": "a red box on the ground\na blue box on the ground\na quadrotor on the red box"}


@pytest.fixture(scope="module")
def llm_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    port = free_port()
    log = Path(tmp_path_factory.mktemp("llm")) / "fake-llm.log"
    with ServiceProcess(["serve", "fake-llm", "--port", str(port), "--profile", "fixed",
                         "--fixed-s", "0.05"], port=port, log_path=log) as proc:
        yield f"{proc.url}/v1"


def settings_for(llm_url: str, **kw: object) -> ReasonerSettings:
    return ReasonerSettings(llm_base_url=llm_url, admin_token=TOKEN, **kw)


@pytest.fixture
def client(llm_url: str) -> Iterator[TestClient]:
    with TestClient(create_app(settings_for(llm_url)), headers=AUTH) as c:
        yield c


def test_reason_answers_with_the_llm_choice(client: TestClient) -> None:
    r = client.post("/v1/reason", headers=AUTH, json={
        "observation": RED_BOX, "options": OPTIONS, "deadline_s": 5.0, "request_id": "q1"})
    assert r.status_code == 200, r.text
    d = r.json()
    assert d["request_id"] == "q1" and d["source"] == "llm" and d["choice"] == 1
    assert d["model"] == "fake" and d["latency_ms"] > 0
    assert "aesop_reasoner_decisions_total" in client.get("/metrics").text


def test_tokens_are_counted(llm_url: str) -> None:
    settings = settings_for(llm_url, request=LLMRequest(stream=False))
    with TestClient(create_app(settings), headers=AUTH) as c:
        c.post("/v1/reason", headers=AUTH, json={
            "observation": RED_BOX, "options": OPTIONS, "deadline_s": 5.0})
        text = c.get("/metrics").text
    line = next(x for x in text.splitlines()
                if x.startswith('aesop_reasoner_tokens_total{kind="completion"}'))
    assert float(line.split()[-1]) > 0


def test_a_stalled_llm_gets_a_labelled_fallback(llm_url: str) -> None:
    with TestClient(create_app(settings_for(llm_url, llm_model="fake-stall")), headers=AUTH) as c:
        r = c.post("/v1/reason", headers=AUTH, json={
            "observation": RED_BOX, "options": OPTIONS, "deadline_s": 0.3})
    d = r.json()
    assert d["source"] == "timeout" and d["choice"] == 1  # first recovery option


@pytest.mark.parametrize(("change", "field"), [
    ({"options": []}, "options"),
    ({"options": [OPTIONS[0], OPTIONS[1], {**OPTIONS[2], "index": 1}]}, "options"),
    ({"deadline_s": 0}, "deadline_s"),
    ({"deadline_s": -1}, "deadline_s"),
    ({"deadline_s": 10_000}, "deadline_s"),
    ({"observation": {**RED_BOX, "text": "x" * 5000}}, "observation.text"),
    ({"observation": {**RED_BOX, "text": ""}}, "observation.text"),
])
def test_bad_requests_name_the_field(client: TestClient, change: dict, field: str) -> None:
    body = {"observation": RED_BOX, "options": OPTIONS, "deadline_s": 2.0, **change}
    r = client.post("/v1/reason", headers=AUTH, json=body)
    assert r.status_code == 422, r.text
    assert r.json()["error"]["field"] == field


def test_every_route_needs_the_token_and_backends_hide_credentials(llm_url: str) -> None:
    """Issue 14: ``/v1/backends`` was open and showed ``base_url`` with its credentials."""
    body = {"observation": RED_BOX, "options": OPTIONS, "deadline_s": 2.0}
    secret_url = llm_url.replace("http://", "http://user:hunter2@") + "?api-key=k3y"
    with TestClient(create_app(settings_for(secret_url))) as client:
        assert client.post("/v1/reason", json=body).status_code == 401
        assert client.get("/v1/backends").status_code == 401
        assert client.get("/v1/jobs/nope").status_code == 401
        r = client.get("/v1/backends", headers=AUTH)
    backends = r.json()["backends"]
    assert backends[0]["name"] == "primary" and backends[0]["model"] == "fake"
    assert "api_key" not in backends[0]
    assert "hunter2" not in r.text and "k3y" not in r.text
    assert backends[0]["base_url"] == llm_url.replace("http://", "http://***@") + "?***"


async def test_zenoh_round_trip(llm_url: str, listener: Bus, endpoint: str) -> None:
    settings = settings_for(llm_url, zenoh_connect=[endpoint])
    decider = build_decider(settings)
    worker = ReasonerWorker(decider, settings)
    task = asyncio.create_task(worker.run())
    sub = listener.subscribe(topics.reasoner_decision(topics.ANY_ROBOT), ReasonerDecision)
    await async_wait_until(lambda: worker.listening, "the deadline keeper", DEADLINE_S * 6)
    await asyncio.to_thread(wait_until, lambda: "reasoner" in listener.alive(),
                            "the keeper on the bus")
    request = ReasonerRequest(
        robot="drone7", request_id="z1", deadline_s=5.0,
        observation=Observation(robot="drone7", **RED_BOX),
        options=tuple(Option(**o) for o in OPTIONS))
    listener.publish(topics.reasoner_request("drone7"), request)
    got = await asyncio.wait_for(anext(sub), DEADLINE_S)
    assert got.key == topics.reasoner_decision("drone7")
    assert got.message.request_id == "z1" and got.message.choice == 1
    assert got.message.source == "llm" and got.message.robot == "drone7"
    await worker.stop()
    await asyncio.wait_for(task, DEADLINE_S)
    await decider.aclose()


def test_latency_calibration_job_recommends_k(client: TestClient) -> None:
    r = client.post("/v1/latency/calibrate", headers=AUTH,
                    json={"n": 60, "warmup": 2, "quantile": 0.95, "confidence": 0.95})
    assert r.status_code == 202, r.text
    job_id = r.json()["job"]
    deadline = time.monotonic() + 60
    while (job := client.get(f"/v1/jobs/{job_id}").json())["state"] == "running":
        assert time.monotonic() < deadline, job
        time.sleep(0.05)
    assert job["state"] == "succeeded", job
    report = job["result"]
    assert report["n"] == 60 and len(report["cold_s"]) == 2 and report["n_failed"] == 0
    assert 0 < report["k_s"] <= report["k_upper_s"] and report["quantile"] == 0.95
    assert sum(report["histogram"]["counts"]) == 60
    assert job["done"] == job["total"] == 62


@pytest.mark.parametrize(("body", "field"), [
    ({"n": 20}, "n"),  # 59 are needed for a 0.95 bound at 0.95 confidence
    ({"n": 100, "quantile": 1.0}, "quantile"),
])
def test_latency_calibration_refuses_bad_plans(client: TestClient, body: dict,
                                               field: str) -> None:
    r = client.post("/v1/latency/calibrate", headers=AUTH, json=body)
    assert r.status_code == 422 and r.json()["error"]["field"] == field
    if field == "n":
        assert "59" in r.json()["error"]["message"]
    assert client.get("/v1/jobs/nope").status_code == 404


def test_latency_calibration_of_a_backend_not_configured_is_a_conflict(
        client: TestClient) -> None:
    r = client.post("/v1/latency/calibrate", headers=AUTH, json={"backend": "hedge"})
    assert r.status_code == 409 and r.json()["error"]["field"] == "backend"


def test_latency_calibrations_running_at_once_are_capped(llm_url: str) -> None:
    """Issue 14: each query of a calibration is a (paid) LLM call, and any number ran at
    once (past the job registry's own cap it was a 500)."""
    settings = settings_for(llm_url, llm_model="fake-stall",
                            limits=ReasonerLimits(max_calibration_jobs=1))
    with TestClient(create_app(settings), headers=AUTH) as client:
        plan = {"n": 60, "warmup": 0, "timeout_s": 30}
        assert client.post("/v1/latency/calibrate", json=plan).status_code == 202
        r = client.post("/v1/latency/calibrate", json=plan)
    assert r.status_code == 429, r.text
    assert "AESOP_REASONER_LIMITS__MAX_CALIBRATION_JOBS" in r.json()["error"]["message"]
