"""The detector demo (``aesop demo`` until the full stack lands).

It runs the real thing end to end on one machine: ``aesop serve embedding`` as a
child process (HTTP admin API + Zenoh worker, the bundled all-MiniLM-L6-v2),
builds the nominal cache of the paper's quadrotor hardware scene over REST
(every combination of up to 4 nominal detections), calibrates tau for a 0.9
TPR on a labelled calibration set (hardware appendix, top-1 scoring), then
publishes the paper's test scenarios as ``Observation``s on Zenoh and prints
the ``AnomalyVerdict``s that come back.
"""

from __future__ import annotations

import asyncio
import secrets
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

from shared import topics
from shared.bus import Bus, Subscription
from shared.messages import AnomalyVerdict, Detection, Observation
from shared.process import ServiceProcess, free_port
from shared.settings import BusSettings

from .domains import QUADROTOR_SCENARIOS, quadrotor_calibration, quadrotor_nominal
from .domains.quadrotor import TASK
from .settings import DEFAULT_MODEL

CACHE = "quadrotor"
ROBOT = "robot0"


def run_demo(model: str | None = None, table: bool = True, port: int | None = None,
             zenoh_port: int | None = None) -> dict[str, Any]:
    result = asyncio.run(_demo(model or DEFAULT_MODEL, port, zenoh_port))
    if table:
        print_table(result)
    return result


async def _demo(model: str, port: int | None, zenoh_port: int | None) -> dict[str, Any]:
    token = secrets.token_urlsafe(24)
    port = port or free_port()
    zenoh_port = zenoh_port or free_port()
    endpoint = f"tcp/127.0.0.1:{zenoh_port}"
    with tempfile.TemporaryDirectory(prefix="aesop-demo-") as tmp:
        env = {"AESOP_ADMIN_TOKEN": token, "AESOP_DETECTOR_CACHE": CACHE,
               "AESOP_ZENOH_LISTEN": endpoint, "AESOP_ROBOT": ROBOT}
        _say(f"starting the vector-cache service on port {port} (Zenoh {endpoint})")
        service = ServiceProcess(["serve", "embedding", "--port", str(port), "--data-dir", tmp],
                                 port=port, env=env, log_path=Path(tmp) / "embedding.log")
        await asyncio.to_thread(service.start)
        try:
            async with httpx.AsyncClient(base_url=service.url, timeout=120, headers={
                    "Authorization": f"Bearer {token}"}) as http:
                cache = await build_cache(http, model)
            with Bus.open(BusSettings(zenoh_connect=[endpoint]), "demo") as bus:
                rows = await fly_scenarios(bus)
        finally:
            service.stop()
    return {"ok": all(r["ok"] for r in rows), "cache": cache, "scenarios": rows}


async def build_cache(http: httpx.AsyncClient, model: str) -> dict[str, Any]:
    _check(await http.put(f"/v1/caches/{CACHE}", json={"model": model, "k": 1}))
    nominal = quadrotor_nominal()
    _say(f"adding {len(nominal)} nominal experiences (combinations of up to 4 detections)")
    started = time.perf_counter()
    job = _check(await http.post(f"/v1/caches/{CACHE}/experiences", params={"wait": "false"},
                           json={"items": [{"text": s.brief, "metadata": {
                               "concepts": list(s.concepts)}} for s in nominal]}))
    while (state := _check(await http.get(f"/v1/jobs/{job['job']}")))["state"] == "running":
        await asyncio.sleep(0.5)
        _say(f"  embedded {state['done']}/{state['total']}")
    if state["state"] != "succeeded":
        raise RuntimeError(f"building the cache failed: {state['error']}")
    build_s = time.perf_counter() - started
    calibration = [{"text": s.brief, "label": s.label} for s in quadrotor_calibration(seed=0)]
    cal = _check(await http.post(f"/v1/caches/{CACHE}/calibrate", json={
        "method": "tpr-target", "tpr": 0.9, "calibration": calibration}))
    _say(f"calibrated: tau = {cal['threshold']:.4f}, TPR {cal['tpr']:.2f}, "
         f"FPR {cal['fpr']:.2f}, AUROC {cal['auroc']:.3f} on {cal['n']} labelled frames")
    return {"size": len(nominal), "build_s": round(build_s, 2), "model": model,
            "calibration": cal}


async def fly_scenarios(bus: Bus) -> list[dict[str, Any]]:
    sub = bus.subscribe(topics.anomaly(ROBOT), AnomalyVerdict, maxsize=256)
    scenarios = list(QUADROTOR_SCENARIOS.values())
    await _wait_for_worker(bus, sub, scenarios[0].sample().brief)
    rows = []
    for seq, scenario in enumerate(scenarios, start=1):
        obs = Observation(robot=ROBOT, seq=seq, task=TASK, text=scenario.sample().brief,
                          detections=tuple(Detection(label=d) for d in scenario.detections))
        bus.publish(topics.observation(ROBOT), obs)
        verdict = await _verdict(sub, seq)
        nearest = verdict.neighbors[0] if verdict.neighbors else None
        rows.append({
            "name": scenario.name,
            "detections": list(scenario.detections),
            "expected_anomaly": scenario.expected_anomaly,
            "is_anomaly": verdict.is_anomaly,
            "score": round(verdict.score, 4),
            "threshold": verdict.threshold,
            "nearest": None if nearest is None else _observed(nearest.text),
            "similarity": None if nearest is None else round(nearest.similarity, 4),
            "latency_ms": round(verdict.latency_ms, 1),
            "expected_choice": scenario.expected_choice,
            "ok": verdict.is_anomaly == scenario.expected_anomaly,
        })
    sub.close()
    return rows


async def _wait_for_worker(bus: Bus, sub: Subscription[AnomalyVerdict], text: str,
                           timeout_s: float = 30.0) -> None:
    """Publish a probe (seq 0) until the worker's verdict comes back: routes are up."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        bus.publish(topics.observation(ROBOT), Observation(robot=ROBOT, seq=0, text=text))
        try:
            await asyncio.wait_for(anext(sub), 0.5)
            return
        except TimeoutError:
            continue
    raise RuntimeError("no verdict from the vector-cache service over Zenoh")


async def _verdict(sub: Subscription[AnomalyVerdict], seq: int,
                   timeout_s: float = 30.0) -> AnomalyVerdict:
    while True:
        got = await asyncio.wait_for(anext(sub), timeout_s)
        if got.message.seq == seq:
            return got.message


def _observed(text: str | None) -> str:
    """The detection list of a brief observation (the part after 'observes:')."""
    if not text:
        return ""
    return text.split("observes:", 1)[-1].strip()


def print_table(result: dict[str, Any]) -> None:
    cal = result["cache"]["calibration"]
    print(f"\nAESOP fast anomaly detector — quadrotor landing scene "
          f"({result['cache']['size']} nominal experiences, {result['cache']['model']})")
    print(f"threshold tau = {cal['threshold']:.4f} ({cal['method']}, TPR target 0.9: "
          f"TPR {cal['tpr']:.2f}, FPR {cal['fpr']:.2f}, AUROC {cal['auroc']:.3f})\n")
    header = f"{'scenario':<22} {'expected':<9} {'verdict':<9} {'score':>8} {'ms':>6}  " \
             f"{'next step':<42} ok"
    print(header)
    print("-" * len(header))
    for r in result["scenarios"]:
        print(f"{r['name']:<22} {_label(r['expected_anomaly']):<9} {_label(r['is_anomaly']):<9} "
              f"{r['score']:>8.4f} {r['latency_ms']:>6.1f}  "
              f"{_next_step(r):<42} {'yes' if r['ok'] else 'NO'}")
    print(f"\n{'all scenarios as expected' if result['ok'] else 'SOME SCENARIOS FAILED'}")


def _label(anomaly: bool) -> str:
    return "anomaly" if anomaly else "nominal"


def _next_step(row: dict[str, Any]) -> str:
    if not row["is_anomaly"]:
        return "keep landing"
    return f"ask LLM (expect: {row['expected_choice']})"


def _check(response: httpx.Response) -> dict[str, Any]:
    if response.status_code >= 400:
        raise RuntimeError(f"{response.request.method} {response.request.url.path} -> "
                           f"{response.status_code}: {response.text}")
    return response.json()


def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)
