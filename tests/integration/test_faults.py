"""Faults on the real stack: real processes on a private Zenoh endpoint, the real model.

One embedding service (a small calibrated cache of the quadrotor scene), one control
loop (the paper scenario, 10 Hz) and the simulated vehicle it flies serve the whole
module; each test starts its own fake LLM and reasoner. A feed publishes the scene as
Observations at 10 Hz; a test turns it anomalous and watches what the services publish.
The fail-safe rules under test (docs/architecture.md): a dead reasoner never leaves the
robot waiting, a stale anomaly verdict counts as an anomaly, and a bad LLM answer becomes a
labelled fallback.
"""

from __future__ import annotations

import asyncio
import contextlib
import secrets
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Generic, TypeVar

import httpx
import numpy as np
import pytest
import zenoh

from services.embedding.client import EmbeddingClient
from shared import topics
from shared.bus import Bus
from shared.messages import (
    AnomalyVerdict,
    ControlState,
    Event,
    Message,
    ReasonerDecision,
    ReasonerRequest,
)
from shared.process import ServiceProcess, free_port
from shared.settings import BusSettings
from tests.zenoh_peers import wait_until
from tools.bench.bus import (
    CACHE,
    ROBOT,
    START,
    control_process,
    embedding_process,
    pick_scenes,
    service_env,
    sim_process,
)
from tools.scenes.hardware import build_scene_cache, camera_observation

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(240)]

WAIT_S = 30.0  # a bound on each wait, far above what a healthy stack needs
REGION_WAIT_S = 45.0  # from the fallback into the region: ~4 s of flight at 10 Hz
CACHE_DETECTIONS = 2  # 55 nominal experiences: quick to embed
POSITION_TOLERANCE = 0.05  # m beyond the box still counts as inside (control's regions.py)

M = TypeVar("M", bound=Message)


@dataclass(frozen=True)
class Got(Generic[M]):
    message: M
    at: float  # time.monotonic() on arrival


class Inbox(Generic[M]):
    """Every message on ``key`` in arrival order (thread-safe)."""

    def __init__(self, bus: Bus, key: str, model: type[M]) -> None:
        self.model = model
        self._lock = threading.Lock()
        self._items: list[Got[M]] = []
        self._sub = bus.session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        got = Got(self.model.decode(sample.payload.to_bytes()), time.monotonic())
        with self._lock:
            self._items.append(got)

    def messages(self, since: int = 0) -> list[M]:
        with self._lock:
            return [g.message for g in self._items[since:]]

    def mark(self) -> int:
        with self._lock:
            return len(self._items)

    def wait_for(self, cond: Callable[[M], bool], what: str, since: int = 0,
                 timeout: float = WAIT_S) -> M:
        deadline = time.monotonic() + timeout
        while not (found := [m for m in self.messages(since) if cond(m)]):
            if time.monotonic() > deadline:
                last = [m.model_dump(exclude={"x", "u"}) for m in self.messages(since)[-3:]]
                raise AssertionError(f"timed out waiting for {what}; last seen: {last}")
            time.sleep(0.01)
        return found[0]


class SceneFeed:
    """Publishes the current scene text as an Observation every 100 ms (one per tick)."""

    def __init__(self, bus: Bus, text: str) -> None:
        self.bus, self.text, self.seq = bus, text, 0
        self.paused = False  # the camera off: nothing published
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            if self.paused:
                continue
            self.seq += 1
            self.bus.publish(topics.observation(ROBOT),
                             camera_observation(self.text, self.seq, ROBOT))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)


class Stack:
    """The module's services, the test's bus (the hub every service connects to), inboxes."""

    def __init__(self, tmp: Path, bus: Bus, endpoint: str, token: str) -> None:
        self.tmp, self.bus, self.endpoint, self.token = tmp, bus, endpoint, token
        self.auth = {"Authorization": f"Bearer {token}"}
        self.states = Inbox(bus, topics.state(ROBOT), ControlState)
        self.events = Inbox(bus, topics.events(ROBOT), Event)
        self.requests = Inbox(bus, topics.reasoner_request(ROBOT), ReasonerRequest)
        self.decisions = Inbox(bus, topics.reasoner_decision(ROBOT), ReasonerDecision)
        self.verdicts = Inbox(bus, topics.anomaly(ROBOT), AnomalyVerdict)
        self.embedding = embedding_process(tmp / "embedding", endpoint, token)
        self.control = control_process(tmp, endpoint, token, AESOP_CONTROL_VERDICT_STALE_S="1.0")
        self.sim = sim_process(tmp, endpoint, token)
        self.nominal = self.anomalous = ""
        self.feed: SceneFeed | None = None

    def start(self) -> None:
        self.embedding.start()
        with self.detector() as http:
            asyncio.run(self._build_cache())
            assert http.get(f"/v1/caches/{CACHE}").json()["calibration"] is not None
        self.control.start()
        self.sim.start()
        self.feed = SceneFeed(self.bus, self.nominal)

    async def _build_cache(self) -> None:
        async with EmbeddingClient(self.embedding.url, token=self.token,
                                   timeout_s=300) as client:
            await build_scene_cache(client, CACHE, model="sentence-transformers/all-MiniLM-L6-v2",
                                    max_detections=CACHE_DETECTIONS)
            self.nominal, self.anomalous = await pick_scenes(client, CACHE_DETECTIONS)

    def stop(self) -> None:
        if self.feed is not None:
            self.feed.close()
        self.sim.stop()
        self.control.stop()
        self.embedding.stop()

    def detector(self) -> httpx.Client:
        return httpx.Client(base_url=self.embedding.url, headers=self.auth, timeout=30)

    def pilot(self) -> httpx.Client:
        return httpx.Client(base_url=self.control.url, headers=self.auth, timeout=30)

    def show(self, text: str) -> None:
        assert self.feed is not None
        self.feed.text = text

    def nominal_flight(self) -> None:
        """The scene nominal, a new flight from the start, its first tick nominal: as an
        operator starts one, the camera off (the reset loop then waits), the loop reset,
        the vehicle moved to the start, the camera on again.

        A restart is tried again if the flight leaves nominal on its own (a verdict
        that came late on a loaded machine counts as an anomaly, by design).
        """
        assert self.feed is not None
        self.show(self.nominal)
        with self.pilot() as http, httpx.Client(base_url=self.sim.url, headers=self.auth,
                                                timeout=30) as vehicle:
            for _attempt in range(3):
                self.feed.paused = True
                time.sleep(1.2)  # the newest verdict goes stale (verdict_stale_s 1.0)
                r = http.post("/v1/reset", json={})
                assert r.status_code == 200, r.text
                assert vehicle.post("/v1/reset", json={"start": list(START)}).status_code == 200
                wait_until(lambda: np.allclose(http.get("/v1/state").json()["state"]["x"][:3],
                                               START, atol=0.02), "the vehicle at the start",
                           WAIT_S)
                since = self.states.mark()  # only the new flight's from here
                self.feed.paused = False
                after = self.states.wait_for(lambda s: s.t > 0.0, "the flight", since)
                if after.mode == "nominal":
                    return
        raise AssertionError(f"the flight kept leaving nominal: {self.events.messages()[-5:]}")

    @contextlib.contextmanager
    def reasoner(self, *llm_args: str) -> Iterator[tuple[ServiceProcess, ServiceProcess]]:
        """A fake LLM started with ``llm_args`` and a reasoner that asks it, on the bus."""
        tmp = self.tmp / f"reasoner-{secrets.token_hex(4)}"
        tmp.mkdir()
        llm_port, port = free_port(), free_port()
        llm = ServiceProcess(["serve", "fake-llm", "--port", str(llm_port), *llm_args],
                             port=llm_port, log_path=tmp / "fake-llm.log")
        env = {**service_env(self.endpoint, self.token),
               "AESOP_REASONER_LLM_BASE_URL": f"http://127.0.0.1:{llm_port}/v1"}
        reasoner = ServiceProcess(["serve", "reasoner", "--port", str(port), "--data-dir",
                                   str(tmp)], port=port, env=env, log_path=tmp / "reasoner.log")
        with llm, reasoner:
            wait_until(lambda: "reasoner" in self.bus.alive(), "the reasoner on the bus",
                       WAIT_S)
            yield llm, reasoner


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    tmp = tmp_path_factory.mktemp("faults")
    (tmp / "embedding").mkdir()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Bus.open(BusSettings(zenoh_listen=[endpoint]), "tester") as bus:
        stack = Stack(tmp, bus, endpoint, secrets.token_urlsafe(24))
        try:
            stack.start()
            yield stack
        finally:
            stack.stop()


def in_box(position: tuple[float, ...], region: dict) -> bool:
    return all(lo - POSITION_TOLERANCE <= p <= hi + POSITION_TOLERANCE for p, lo, hi in
               zip(position, region["position_lo"], region["position_hi"], strict=True))


def first_recovery(request: ReasonerRequest) -> int:
    return min(o.index for o in request.options if o.index != 0)


def test_a_reasoner_killed_mid_anomaly_leaves_the_fallback_at_k(stack: Stack) -> None:
    """The LLM stalls, the reasoner dies while it waits: control commits its own fallback
    at K, says so in an alarm Event, and flies into the chosen region."""
    with stack.reasoner("--profile", "stall") as (llm, reasoner):
        stack.nominal_flight()
        since = (stack.requests.mark(), stack.events.mark(), stack.states.mark(),
                 stack.decisions.mark())
        stack.show(stack.anomalous)
        request = stack.requests.wait_for(lambda r: True, "a reasoner request", since[0])
        assert request.observation.text == stack.anomalous
        wait_until(lambda: httpx.get(f"{llm.url}/_fake/stats").json()["active"] >= 1,
                   "the reasoner asking the LLM", WAIT_S)
        reasoner.kill()

        event = stack.events.wait_for(lambda e: e.kind == "fallback", "the fallback", since[1])
        assert event.source == "control" and event.severity == "alarm"
        assert event.data["to"] == "recovering" and event.data["fallback"] is True
        assert event.data["request_id"] == request.request_id
        chosen = event.data["chosen"]
        assert chosen in {o.index for o in request.options} - {0}
        state = stack.states.wait_for(lambda s: s.mode == "recovering", "recovering", since[2])
        assert state.chosen == chosen and state.t_anom is not None
        assert 0 < state.t - state.t_anom <= 1.5 + 1e-6  # committed by K = 1.5 s (sim time)
        assert not [d for d in stack.decisions.messages(since[3])
                    if d.request_id == request.request_id]

        with stack.pilot() as http:
            region = next(r for r in http.get("/v1/regions").json()["regions"]
                          if r["index"] == chosen)
        arrived = stack.states.wait_for(lambda s: in_box(s.x[:3], region),
                                        f"the flight in region {region['name']}", since[2],
                                        timeout=REGION_WAIT_S)
        assert arrived.mode == "recovering" and arrived.chosen == chosen
        stack.show(stack.nominal)


@pytest.mark.parametrize(("failure", "source"), [
    (("--rate-garbage", "1"), "parse_error"),
    (("--rate-5xx", "1"), "backend_error"),
])
def test_a_failing_llm_gives_a_labelled_fallback_decision(stack: Stack, failure: tuple[str, str],
                                                          source: str) -> None:
    with stack.reasoner(*failure):
        stack.nominal_flight()
        since = (stack.requests.mark(), stack.decisions.mark(), stack.states.mark())
        stack.show(stack.anomalous)
        request = stack.requests.wait_for(lambda r: True, "a reasoner request", since[0])
        decision = stack.decisions.wait_for(lambda d: d.request_id == request.request_id,
                                            "the decision", since[1])
        assert decision.source == source and decision.robot == ROBOT
        assert decision.choice == first_recovery(request) and decision.rationale
        state = stack.states.wait_for(lambda s: s.mode == "recovering", "recovering", since[2])
        assert state.chosen == decision.choice
        stack.show(stack.nominal)


def test_a_dead_detector_is_an_anomaly_the_robot_cannot_continue_out_of(
        stack: Stack) -> None:
    """Killed: verdicts go stale, control raises an alarm and asks the reasoner, telling it
    the detector is silent and not offering "continue"; it picks a region and the robot
    recovers there. Restarted on the same data: verdicts resume and the cache is the one it
    had, and the robot stays committed to its recovery until a reset."""
    with stack.reasoner("--profile", "fixed", "--fixed-s", "0.05"), stack.detector() as http:
        before = http.get(f"/v1/caches/{CACHE}").json()
        stack.nominal_flight()
        since = (stack.events.mark(), stack.states.mark(), stack.requests.mark(),
                 stack.decisions.mark())
        stack.embedding.kill()

        alarm = stack.events.wait_for(lambda e: e.kind == "verdict_stale", "the stale alarm",
                                      since[0])
        assert alarm.severity == "alarm" and alarm.source == "control"
        stack.states.wait_for(lambda s: s.mode == "anomaly_pending", "the anomaly", since[1])
        request = stack.requests.wait_for(lambda r: True, "a reasoner request", since[2])
        assert "gone silent" in request.observation.text
        assert 0 not in [o.index for o in request.options]
        decision = stack.decisions.wait_for(lambda d: d.request_id == request.request_id,
                                            "the decision", since[3])
        assert decision.source == "llm" and decision.choice in [o.index for o in
                                                               request.options]
        stack.states.wait_for(lambda s: s.mode == "recovering" and s.chosen == decision.choice,
                              "the recovery", since[1])

    stack.embedding = embedding_process(stack.tmp / "embedding", stack.endpoint, stack.token)
    stack.embedding.start()
    verdicts = stack.verdicts.mark()
    stack.events.wait_for(lambda e: e.kind == "verdict_fresh", "verdicts again", since[0])
    verdict = stack.verdicts.wait_for(lambda v: True, "a verdict", verdicts)
    assert verdict.is_anomaly is False and verdict.cache_version == before["version"]
    with stack.detector() as http:
        after = http.get(f"/v1/caches/{CACHE}").json()
    assert (after["size"], after["version"], after["threshold"]) == \
        (before["size"], before["version"], before["threshold"])
    assert after["calibration"] == before["calibration"]
    states = stack.states.mark()
    state = stack.states.wait_for(lambda s: True, "a tick", states)
    assert state.mode == "recovering"  # committed: fresh verdicts do not undo a recovery
    with stack.pilot() as http:
        body = http.get("/v1/state").json()
    assert body["verdict_stale"] is False and body["mode"] == "recovering"
