"""``aesop bench bus``: latency over the real Zenoh bus, real processes end to end.

It starts ``aesop serve embedding`` (the bundled all-MiniLM-L6-v2 unless
``--model``; a cache of the quadrotor hardware scene, every combination of up
to ``cache_detections`` nominal detections, calibrated for a 0.9 TPR with
top-1 scoring, as ``aesop demo`` does), ``aesop serve control`` (the
packaged paper scenario, 10 Hz) and the vehicle it flies (``aesop serve sim``) as child
processes, all on a private Zenoh endpoint that this process listens on. Then, in two
phases:

1. **verdict latency**: ``observations`` Observations, published at
   ``rate_hz`` on a fixed schedule, cycling through the paper's four test
   scenes. Per observation: the time from just before ``publish`` to the
   arrival here of the ``AnomalyVerdict`` with the same ``seq`` (both on this
   process's ``time.monotonic``; arrival is stamped in the Zenoh callback).
   It is two Zenoh hops plus the service's embedding and scoring.
2. **control reaction latency**: ``anomalies`` trials, with a scene stream
   at ``rate_hz`` going on throughout so the control loop's verdicts stay
   fresh. Each trial moves the vehicle back to the start and restarts the flight
   (the simulator's and control's ``POST /v1/reset``) while the scene is nominal and
   waits for a nominal ``ControlState`` of the restarted flight; then the scene turns
   anomalous (every frame published from then on shows the anomaly, as a real scene
   would). Reaction = the arrival here of
   the first ``ControlState`` with ``mode != "nominal"`` (the detection tick:
   Algorithm 1 enters ``anomaly_pending`` and asks the reasoner) minus the
   publish of the first anomalous observation. It is the verdict latency, plus
   the wait for the control loop's next tick (up to one period, 100 ms at
   10 Hz), plus that tick's work (the MPC step), plus one Zenoh hop; the
   report also gives the part after the verdict's arrival here
   (``reaction_after_verdict_ms``).

Warm-up observations (seq 0, until verdicts flow) are not counted. Results
are p50/p99/max in ms (linear-interpolated percentiles), printed as a table,
or as one JSON object with ``--json``. No reasoner runs: the unanswered
request ends in the control loop's fallback, and the next reset clears it.
"""

from __future__ import annotations

import asyncio
import contextlib
import secrets
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.control.client import ControlClient
from services.embedding.client import EmbeddingClient
from services.embedding.schemas import CacheInfo
from services.embedding.settings import SERVICE_MODEL
from services.sim.client import SimClient
from shared import topics
from shared.bus import Bus, Received, Subscription
from shared.messages import AnomalyVerdict, ControlState
from shared.process import ServiceProcess, free_port
from shared.settings import BusSettings
from shared.tables import table
from tools import progress
from tools.scenes import (
    QUADROTOR_SCENARIOS,
)
from tools.scenes.hardware import (
    build_scene_cache,
    camera_observation,
    detections_of,
    observation_text,
)
from tools.stack.up import DETECTOR_CACHE

CACHE = DETECTOR_CACHE
ROBOT = "robot0"
CONTROL_RATE_HZ = 10.0
START = (10.0, 2.0, 2.0)  # m: the paper scenario's start-box centre
MAX_ATTEMPTS = 5
WAIT_S = 60.0  # generous bound on any one wait (a loaded machine is slow, not broken)
STALE_WAIT_S = 0.8  # the control loop's verdicts go stale after 0.5 s by default


class BenchError(RuntimeError):
    """The stack did not behave: a service failed, or a wait ran out."""


# --------------------------------------------------------------------------- the stack


@dataclass
class Stack:
    """The child processes, an admin HTTP client for each, and the bench's own bus."""

    endpoint: str
    token: str
    embedding: ServiceProcess
    control: ServiceProcess
    sim: ServiceProcess
    bus: Bus
    detector: EmbeddingClient
    pilot: ControlClient
    vehicle: SimClient
    cache: CacheInfo | None = None


def service_env(endpoint: str, token: str) -> dict[str, str]:
    """Environment of a child service on the private endpoint (it connects to us)."""
    return {"AESOP_ADMIN_TOKEN": token, "AESOP_ZENOH_CONNECT": endpoint,
            "AESOP_ZENOH_LISTEN": "", "AESOP_ROBOT": ROBOT}


def embedding_process(tmp: Path, endpoint: str, token: str, **env: str) -> ServiceProcess:
    port = free_port()
    env = {**service_env(endpoint, token), "AESOP_EMBEDDING_DETECTOR_CACHE": CACHE, **env}
    return ServiceProcess(["serve", "embedding", "--port", str(port), "--data-dir", str(tmp)],
                          port=port, env=env, log_path=tmp / "embedding.log")


def control_process(tmp: Path, endpoint: str, token: str, **env: str) -> ServiceProcess:
    port = free_port()
    full = {**service_env(endpoint, token), "AESOP_CONTROL_RATE_HZ": str(CONTROL_RATE_HZ),
            **env}
    return ServiceProcess(["serve", "control", "--port", str(port), "--data-dir", str(tmp)],
                          port=port, env=full, log_path=tmp / "control.log", ready_timeout_s=60)


def sim_process(tmp: Path, endpoint: str, token: str, **env: str) -> ServiceProcess:
    """The vehicle control flies (the paper scene at the start, in real time at 10 Hz)."""
    port = free_port()
    full = {**service_env(endpoint, token), "AESOP_SIM_START_POSITION": str(list(START)),
            **env}
    return ServiceProcess(["serve", "sim", "--port", str(port), "--data-dir", str(tmp)],
                          port=port, env=full, log_path=tmp / "sim.log", ready_timeout_s=60)


async def pick_scenes(detector: EmbeddingClient, cache_detections: int = 4
                      ) -> tuple[str, str]:
    """A nominal scene the cache holds and a test scene it flags: (nominal, anomalous)."""
    nominal = observation_text(QUADROTOR_SCENARIOS["nominal"].detections[:cache_detections])
    anomalous = [observation_text(s.detections) for s in QUADROTOR_SCENARIOS.values()
                 if s.expected_anomaly]
    texts = [nominal, *anomalous]  # scored with their detections, as the camera sends them
    scored = await detector.score(CACHE, texts, detections=[
        detections_of(text.splitlines()) for text in texts])
    flags = [r.is_anomaly for r in scored.results]
    if flags[0]:
        raise BenchError(f"the cache flags its own nominal scene {nominal!r}")
    flagged = [text for text, flag in zip(anomalous, flags[1:], strict=True) if flag]
    if not flagged:
        raise BenchError("the calibrated cache flags none of the anomalous test scenes")
    return nominal, flagged[0]


@contextlib.asynccontextmanager
async def running_stack(tmp: Path, model: str, cache_detections: int):
    """Embedding and control up on a private endpoint, the scene cache built and calibrated."""
    token = secrets.token_urlsafe(24)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Bus.open(BusSettings(zenoh_listen=[endpoint]), "bench") as bus:
        embedding = embedding_process(tmp, endpoint, token)
        control = control_process(tmp, endpoint, token)
        sim = sim_process(tmp, endpoint, token)
        progress.step(f"starting embedding, control and the vehicle on Zenoh {endpoint}")
        with embedding, control, sim:
            async with EmbeddingClient(embedding.url, token=token,
                                       timeout_s=WAIT_S * 5) as detector, \
                    ControlClient(control.url, token=token, timeout_s=WAIT_S) as pilot, \
                    SimClient(sim.url, token=token, timeout_s=WAIT_S) as vehicle:
                stack = Stack(endpoint, token, embedding, control, sim, bus, detector, pilot,
                              vehicle)
                stack.cache, _ = await build_scene_cache(detector, CACHE, model=model, say=say,
                                                         max_detections=cache_detections)
                yield stack


# --------------------------------------------------------------------------- measuring


class Scene:
    """Publishes one Observation per period of ``rate_hz`` showing the current scene text."""

    def __init__(self, bus: Bus, rate_hz: float, text: str, first_seq: int) -> None:
        self.bus, self.period, self.text = bus, 1.0 / rate_hz, text
        self.seq = first_seq
        self.paused = False  # the stream publishes nothing (a new flight is being set up)
        self.sent: dict[int, float] = {}  # seq -> monotonic time just before publish

    def publish(self, text: str | None = None) -> tuple[int, float]:
        """One observation now; ``text`` switches the scene first."""
        if text is not None:
            self.text = text
        seq, self.seq = self.seq, self.seq + 1
        obs = camera_observation(self.text, seq, ROBOT)
        sent = time.monotonic()
        self.bus.publish(topics.observation(ROBOT), obs)
        self.sent[seq] = sent
        return seq, sent

    async def stream(self) -> None:
        """One observation at each ``start + k * period`` until cancelled."""
        start = time.monotonic()
        k = 0
        while True:
            delay = start + k * self.period - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            if not self.paused:
                self.publish()
            k += 1


class Verdicts:
    """Arrival times of verdicts by seq, collected by a task."""

    def __init__(self, sub: Subscription[AnomalyVerdict]) -> None:
        self.sub = sub
        self.arrived: dict[int, Received[AnomalyVerdict]] = {}
        self.task = asyncio.create_task(self._collect())

    async def _collect(self) -> None:
        async for got in self.sub:
            self.arrived.setdefault(got.message.seq, got)

    async def wait(self, seq: int, timeout_s: float = WAIT_S) -> Received[AnomalyVerdict]:
        deadline = time.monotonic() + timeout_s
        while seq not in self.arrived:
            if time.monotonic() > deadline:
                raise BenchError(f"no verdict for observation {seq} after {timeout_s:.0f} s")
            await asyncio.sleep(0.002)
        return self.arrived[seq]


async def warm_up(scene: Scene, verdicts: Verdicts, n: int = 10) -> None:
    """Probes (seq 0, not counted) until verdicts flow, then ``n`` more to warm the model."""
    deadline = time.monotonic() + WAIT_S
    while 0 not in verdicts.arrived:
        if time.monotonic() > deadline:
            raise BenchError("no verdict from the embedding service over Zenoh")
        probe = camera_observation(scene.text, 0, ROBOT)
        scene.bus.publish(topics.observation(ROBOT), probe)
        await asyncio.sleep(0.2)
    for _ in range(n):
        seq, _ = scene.publish()
        await verdicts.wait(seq)


async def verdict_phase(scene: Scene, verdicts: Verdicts, texts: list[str], n: int
                        ) -> list[float]:
    """Phase 1: ``n`` observations on schedule, cycling ``texts``; latency per verdict (ms)."""
    first = scene.seq
    start = time.monotonic()
    for k in range(n):
        delay = start + k * scene.period - time.monotonic()
        if delay > 0:
            await asyncio.sleep(delay)
        scene.publish(texts[k % len(texts)])
    out = []
    for seq in range(first, first + n):
        got = await verdicts.wait(seq)
        out.append((got.received_at - scene.sent[seq]) * 1000.0)
    return out


async def reaction_phase(stack: Stack, scene: Scene, verdicts: Verdicts, nominal: str,
                         anomalous: str, n: int) -> tuple[list[float], list[float]]:
    """Phase 2: ``n`` reset-then-anomaly trials.

    Per trial (ms): the reaction latency, and the part of it after the anomalous
    observation's verdict reached this process (tick wait + step + one hop).
    """
    states = stack.bus.subscribe(topics.state(ROBOT), ControlState, maxsize=4096)
    scene.text = nominal
    stream = asyncio.create_task(scene.stream())
    reaction: list[float] = []
    after_verdict: list[float] = []
    try:
        while len(reaction) < n:
            for _attempt in range(MAX_ATTEMPTS):
                await nominal_flight(stack, scene, verdicts, states, nominal)
                seq, sent = scene.publish(anomalous)
                got = await next_state(states, lambda s: s.mode != "nominal",
                                       "the detection tick")
                scene.text = nominal
                if got.received_at > sent:
                    break
                say("  the flight left nominal before the anomaly: trying again")
            else:
                raise BenchError(f"the flight kept leaving nominal on its own "
                                 f"({MAX_ATTEMPTS} attempts)")
            verdict = await verdicts.wait(seq)
            reaction.append((got.received_at - sent) * 1000.0)
            after_verdict.append((got.received_at - verdict.received_at) * 1000.0)
            progress.count(len(reaction), n, f"anomalies (the last {reaction[-1]:.1f} ms)")
    finally:
        stream.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await stream
        states.close()
    return reaction, after_verdict


async def nominal_flight(stack: Stack, scene: Scene, verdicts: Verdicts,
                         states: Subscription[ControlState], nominal: str) -> None:
    """A new flight from the start, the scene nominal, one nominal tick seen: as an
    operator starts one, the camera off (the reset loop then waits: no fresh verdict),
    every verdict so far in (so a late anomalous one from the previous trial cannot
    reach the new flight), the loop reset, the vehicle moved to the start and seen
    there, the camera on again."""
    for _attempt in range(MAX_ATTEMPTS):
        scene.paused, scene.text = True, nominal
        for seq in [s for s in scene.sent if s not in verdicts.arrived]:
            await verdicts.wait(seq)
        await asyncio.sleep(STALE_WAIT_S)
        await stack.pilot.reset()
        await stack.vehicle.reset(START)
        deadline = time.monotonic() + WAIT_S
        while not await at_start(stack.pilot):
            if time.monotonic() > deadline:
                raise BenchError("control never saw the vehicle at the start")
            await asyncio.sleep(0.05)
        scene.paused = False
        await next_state(states, lambda s: s.mode == "nominal" and s.t == 0.0,
                         "the restarted flight")
        got = await next_state(states, lambda s: True, "a tick")
        if got.message.mode == "nominal":
            return
    raise BenchError(f"the restarted flight never stayed nominal ({MAX_ATTEMPTS} attempts)")


async def at_start(pilot: ControlClient) -> bool:
    """The loop waits, with the vehicle seen at rest at the start."""
    state = (await pilot.state()).state
    return state is not None and state.mode == "waiting" and bool(
        np.allclose(state.x[:3], START, atol=0.02))


async def next_state(states: Subscription[ControlState], cond: Any, what: str
                     ) -> Received[ControlState]:
    deadline = time.monotonic() + WAIT_S
    while True:
        left = deadline - time.monotonic()
        try:
            got = await asyncio.wait_for(anext(states), max(left, 0.0))
        except TimeoutError:
            raise BenchError(f"control: timed out waiting for {what}") from None
        if cond(got.message):
            return got


async def fresh_verdicts_at_control(pilot: ControlClient, scene: Scene) -> None:
    """Publish the scene until the control loop reports fresh verdicts."""
    deadline = time.monotonic() + WAIT_S
    while (await pilot.state()).verdict_stale is not False:
        if time.monotonic() > deadline:
            raise BenchError("the control loop never saw a fresh verdict")
        scene.publish()
        await asyncio.sleep(0.05)


def summary(ms: list[float]) -> dict[str, float | int]:
    a = np.asarray(ms, dtype=float)
    return {"n": int(a.size), "p50": round(float(np.percentile(a, 50)), 3),
            "p99": round(float(np.percentile(a, 99)), 3), "max": round(float(a.max()), 3)}


async def _bench(observations: int, rate_hz: float, anomalies: int, model: str,
                 cache_detections: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="aesop-bench-bus-") as tmp:
        async with running_stack(Path(tmp), model, cache_detections) as stack:
            nominal, anomalous = await pick_scenes(stack.detector, cache_detections)
            scene = Scene(stack.bus, rate_hz, nominal, first_seq=1)
            sub = stack.bus.subscribe(topics.anomaly(ROBOT), AnomalyVerdict, maxsize=8192)
            verdicts = Verdicts(sub)
            try:
                await warm_up(scene, verdicts)
                await fresh_verdicts_at_control(stack.pilot, scene)
                texts = [observation_text(s.detections) for s in QUADROTOR_SCENARIOS.values()]
                progress.step(f"{observations} observations at {rate_hz:g} Hz", 1, 2)
                verdict_ms = await verdict_phase(scene, verdicts, texts, observations)
                progress.step(f"{anomalies} anomalies, control at {CONTROL_RATE_HZ:g} Hz", 2,
                              2)
                reaction_ms, after_ms = await reaction_phase(
                    stack, scene, verdicts, nominal, anomalous, anomalies)
            finally:
                sub.close()
                verdicts.task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await verdicts.task
            return {"observations": observations, "rate_hz": rate_hz,
                    "verdict_ms": summary(verdict_ms),
                    "anomalies": anomalies, "reaction_ms": summary(reaction_ms),
                    "reaction_after_verdict_ms": summary(after_ms),
                    "model": stack.cache.model if stack.cache else model,
                    "cache_size": stack.cache.size if stack.cache else 0,
                    "control_rate_hz": CONTROL_RATE_HZ}


def run_bus_bench(observations: int = 500, rate_hz: float = 20.0, anomalies: int = 20,
                  model: str | None = None, cache_detections: int = 4,
                  table_out: bool = True) -> dict[str, Any]:
    if observations < 1 or anomalies < 1 or not rate_hz > 0:
        raise ValueError("observations and anomalies must be >= 1 and rate_hz > 0")
    if not 1 <= cache_detections <= 4:
        raise ValueError("cache_detections must be in 1..4")
    result = asyncio.run(_bench(observations, rate_hz, anomalies, model or SERVICE_MODEL,
                                cache_detections))
    if table_out:
        print_table(result)
    return result


def print_table(result: dict[str, Any]) -> None:
    rows = [{"latency [ms]": "observation -> verdict", **result["verdict_ms"]},
            {"latency [ms]": "observation -> control reaction", **result["reaction_ms"]},
            {"latency [ms]": "  of which after the verdict",
             **result["reaction_after_verdict_ms"]}]
    print(table(f"bus latency: {result['observations']} observations at "
                f"{result['rate_hz']:g} Hz, {result['anomalies']} anomalies, control at "
                f"{result['control_rate_hz']:g} Hz ({result['model']}, cache of "
                f"{result['cache_size']})", rows))


def say(message: str) -> None:
    """A line of the bench's to keep, on stderr (:func:`tools.progress.say`)."""
    progress.say(message)
