"""``aesop bench fairness``: one robot floods its observations; does another still get
its verdicts, and how late?

It starts the stack's hub (``python -m tools.stack.router``: a Zenoh router with the
stack's per-session observation rate, no users) and ``aesop serve embedding`` (the
bundled model, the hardware scene's calibrated cache, as ``aesop bench bus`` builds
it) as child processes. Two robots are client sessions of the hub, each its own:
robot0 publishes the nominal scene at ``rate_hz`` and times each verdict (publish to
arrival here, both on this process's ``time.monotonic``), first alone for
``seconds`` (the baseline), then for another ``seconds`` while robot1 publishes at
``flood_hz`` on a thread of its own. A robot0 observation without a verdict
``LOST_AFTER_S`` after the last one was published is lost.

With ``direct`` there is no hub: the service and both robots are peers of this
process's session, so only the detector's own per-robot inbox stands between the
flood and robot0 (the defence for a bus without a router).

Target (issue 26): robot0's p99 within 2x of its baseline and no verdict lost at a
2 kHz flood. The flood is published from this machine, so it also takes CPU from the
service: a flood from another machine would cost it less.
"""

from __future__ import annotations

import asyncio
import contextlib
import secrets
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from services.embedding.client import EmbeddingClient
from services.embedding.settings import SERVICE_MODEL
from shared import topics
from shared.bus import Bus
from shared.messages import AnomalyVerdict
from shared.process import free_port
from shared.settings import BusSettings
from shared.tables import table
from tools.bench.bus import CACHE, WAIT_S, BenchError, embedding_process, pick_scenes, say
from tools.scenes.hardware import build_scene_cache, camera_observation

QUIET, FLOODER = "robot0", "robot1"
LOST_AFTER_S = 5.0  # a verdict later than this after the last observation is lost
TARGET_RATIO = 2.0


class Timed:
    """robot0's observations on schedule, and its verdicts as they arrive."""

    def __init__(self, bus: Bus, text: str) -> None:
        self.bus, self.text = bus, text
        self.seq = 1
        self.sent: dict[int, float] = {}
        self.arrived: dict[int, float] = {}
        self._sub = bus.subscribe(topics.anomaly(QUIET), AnomalyVerdict, maxsize=8192)
        self.task = asyncio.create_task(self._collect())

    async def _collect(self) -> None:
        async for got in self._sub:
            self.arrived.setdefault(got.message.seq, got.received_at)

    async def phase(self, seconds: float, rate_hz: float) -> list[int]:
        """Observations at ``rate_hz`` for ``seconds``; their seqs."""
        first, period = self.seq, 1.0 / rate_hz
        start = time.monotonic()
        for k in range(max(1, round(seconds * rate_hz))):
            delay = start + k * period - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            self.sent[self.seq] = time.monotonic()
            self.bus.publish(topics.observation(QUIET),
                             camera_observation(self.text, self.seq, QUIET))
            self.seq += 1
        return list(range(first, self.seq))

    async def settle(self, seqs: list[int]) -> None:
        deadline = time.monotonic() + LOST_AFTER_S
        while not all(s in self.arrived for s in seqs) and time.monotonic() < deadline:
            await asyncio.sleep(0.01)

    def latencies(self, seqs: list[int]) -> tuple[list[float], int]:
        got = [(self.arrived[s] - self.sent[s]) * 1000.0 for s in seqs if s in self.arrived]
        return got, len(seqs) - len(got)

    async def close(self) -> None:
        self._sub.close()
        self.task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self.task


def flood(bus: Bus, text: str, hz: float, stop: threading.Event) -> int:
    """robot1's flood at ``hz`` until ``stop``; how many it published. The same encoded
    observation each time, through one declared publisher, as a flooding robot would send
    it: the flood's own cost on these shared cores is kept as small as it can be."""
    payload = camera_observation(text, 1, FLOODER).encode()
    publisher = bus.session.declare_publisher(topics.observation(FLOODER))
    period, sent, start = 1.0 / hz, 0, time.monotonic()
    while not stop.is_set():
        publisher.put(payload)
        sent += 1
        delay = start + sent * period - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    publisher.undeclare()
    return sent


def spread(ms: list[float]) -> dict[str, float | int | None]:
    if not ms:
        return {"n": 0, "p50": None, "p99": None, "max": None}
    a = np.asarray(ms)
    return {"n": len(ms), "p50": round(float(np.percentile(a, 50)), 2),
            "p99": round(float(np.percentile(a, 99)), 2), "max": round(float(a.max()), 2)}


@contextlib.contextmanager
def hub_process(endpoint: str) -> Any:
    proc = subprocess.Popen([sys.executable, "-m", "tools.stack.router", "--listen", endpoint],
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        if "listening" not in line:
            raise BenchError(f"the hub did not start: {line.strip()}")
        yield proc
    finally:
        proc.terminate()
        proc.wait(10)


def robot_session(endpoint: str, robot: str, *, client: bool) -> Bus:
    mode = "client" if client else "peer"
    return Bus.open(BusSettings(robot=robot, zenoh_mode=mode, zenoh_connect=[endpoint]),
                    f"bench-{robot}")


async def _bench(seconds: float, rate_hz: float, flood_hz: float, direct: bool,
                 model: str) -> dict[str, Any]:
    token = secrets.token_urlsafe(24)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory(prefix="aesop-bench-fairness-") as tmp, \
            contextlib.ExitStack() as stack:
        if direct:  # this process's session is the meeting point
            stack.enter_context(Bus.open(BusSettings(zenoh_listen=[endpoint]), "bench"))
        else:
            stack.enter_context(hub_process(endpoint))
        extra = {} if direct else {"AESOP_ZENOH_MODE": "client"}
        service = stack.enter_context(embedding_process(Path(tmp), endpoint, token, **extra))
        quiet = stack.enter_context(robot_session(endpoint, QUIET, client=not direct))
        loud = stack.enter_context(robot_session(endpoint, FLOODER, client=not direct))
        say(f"embedding up on Zenoh {endpoint} ({'peers' if direct else 'through the hub'})")
        async with EmbeddingClient(service.url, token=token, timeout_s=WAIT_S * 5) as detector:
            info, _ = await build_scene_cache(detector, CACHE, model=model, say=say)
            nominal, _ = await pick_scenes(detector)
            timed = Timed(quiet, nominal)
            try:
                await _warm_up(timed)
                say(f"baseline: {QUIET} alone at {rate_hz:g} Hz for {seconds:g} s")
                base = await timed.phase(seconds, rate_hz)
                await timed.settle(base)
                say(f"flood: {FLOODER} at {flood_hz:g} Hz meanwhile")
                stop = threading.Event()
                flooding = asyncio.create_task(
                    asyncio.to_thread(flood, loud, nominal, flood_hz, stop))
                await asyncio.sleep(0.5)  # the flood is on before robot0 is timed
                flooded = await timed.phase(seconds, rate_hz)
                stop.set()
                sent = await flooding
                await timed.settle(flooded)
                metrics = (await detector.http.get("/metrics")).text
            finally:
                await timed.close()
        base_ms, base_lost = timed.latencies(base)
        flood_ms, flood_lost = timed.latencies(flooded)
    baseline, flooding_ = spread(base_ms), spread(flood_ms)
    ratio = None
    if baseline["p99"] and flooding_["p99"] is not None:
        ratio = round(float(flooding_["p99"]) / float(baseline["p99"]), 2)
    return {"seconds": seconds, "rate_hz": rate_hz, "flood_hz": flood_hz,
            "through": "peers" if direct else "hub", "model": info.model,
            "baseline_ms": baseline, "flood_ms": flooding_,
            "baseline_p99_ms": baseline["p99"], "flood_p99_ms": flooding_["p99"],
            "p99_ratio": ratio, "lost": flood_lost, "baseline_lost": base_lost,
            "flood_sent": sent, "flood_achieved_hz": round(sent / (seconds + 0.5), 1),
            "dropped": _dropped(metrics),
            "met": flood_lost == 0 and ratio is not None and ratio <= TARGET_RATIO}


async def _warm_up(timed: Timed) -> None:
    deadline = time.monotonic() + WAIT_S
    while not timed.arrived:
        if time.monotonic() > deadline:
            raise BenchError(f"no verdict for {QUIET} from the embedding service")
        await timed.phase(0.2, 10.0)
    warm = await timed.phase(1.0, 10.0)
    await timed.settle(warm)


def _dropped(metrics: str) -> dict[str, float]:
    """``aesop_embedding_observations_dropped_total`` by robot and reason."""
    out = {}
    for line in metrics.splitlines():
        if line.startswith("aesop_embedding_observations_dropped_total{"):
            labels, value = line.rsplit(" ", 1)
            out[labels.split("{", 1)[1].rstrip("}")] = float(value)
    return out


def run_fairness_bench(seconds: float = 15.0, rate_hz: float = 10.0, flood_hz: float = 2000.0,
                       direct: bool = False, model: str | None = None,
                       table_out: bool = True) -> dict[str, Any]:
    if not (seconds > 0 and rate_hz > 0 and flood_hz > 0):
        raise ValueError("seconds, rate_hz and flood_hz must be positive")
    result = asyncio.run(_bench(seconds, rate_hz, flood_hz, direct, model or SERVICE_MODEL))
    if table_out:
        print_table(result)
    return result


def print_table(result: dict[str, Any]) -> None:
    rows = [{"robot0's verdicts [ms]": label, **result[key],
             "lost": result["baseline_lost" if key == "baseline_ms" else "lost"]}
            for label, key in (("alone", "baseline_ms"),
                               (f"robot1 flooding at {result['flood_hz']:g} Hz", "flood_ms"))]
    verdict = "met" if result["met"] else "MISSED"
    print(table(f"fairness through the {result['through']}: robot0 at {result['rate_hz']:g} Hz, "
                f"{result['seconds']:g} s a phase ({result['model']}); p99 ratio "
                f"{result['p99_ratio']} (target <= {TARGET_RATIO:g}, none lost): {verdict}",
                rows))
    print(f"robot1 published {result['flood_sent']} ({result['flood_achieved_hz']} Hz); "
          f"dropped by the detector: {result['dropped'] or 'none'}")
