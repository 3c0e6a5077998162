"""One flight of a hardware scenario from the robot's side of a two-host stack.

Run on the robot (in its network namespace: :mod:`.rig` starts it with ``ip netns exec``),
it flies a demo scenario through the robot's own router, control loop and vehicle as
``aesop demo`` does (:func:`tools.demo.flights.fly_robot`: its camera, its judge on the
vehicle's truth), and meanwhile:

- prints ``started <monotonic s>`` as the flight starts (the rig applies its fault a
  while after: a cut, a stall, a router killed), ``anomaly <monotonic s>`` the moment the
  control loop first asks the reasoner, and ``flown`` once the flight is judged;
- times each verdict's round trip across the link: an observation's arrival at the robot's
  router to its verdict's (both heard on the robot, one clock);
- with ``--writes URL``, adds one experience every ``WRITE_PERIOD_S`` to a cache of the
  server through the link, keeping the ids the server acknowledged (2xx: durable);
- with ``--linger``, after the flight keeps its camera on (the nominal scene) until a line
  ``stop`` arrives on stdin, so that a link that comes back after the flight is seen to.

Then it prints one JSON object (``result <json>``): the flight's row, the verdicts'
``[observation, verdict]`` arrival times, the acknowledged and failed writes, and what the
control loop counted meanwhile (``/metrics``: ticks flown unmonitored, requests, fallbacks),
which no lost message can hide (the bus's events of a router's outage are lost with it).

    ip netns exec <ns> python -m tools.link.driver --router tcp/127.0.0.1:7447 \
        --control http://127.0.0.1:8003 --sim http://127.0.0.1:8004 --scenario 2a
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import httpx
from prometheus_client.parser import text_string_to_metric_families

from services.control.core.scenario import load_scenario
from shared import topics
from shared.bus import Bus
from shared.messages import AnomalyVerdict, Observation, ReasonerRequest
from shared.settings import BusSettings
from tools.demo.flights import CAMERA_PERIOD_S, demo_scenario, fly_robot
from tools.scenes.hardware import SCENARIOS, camera_observation, observation_text
from tools.stack.up import hardware_scenario

# the loop's counters the flight reads before and after (``aesop_control_<name>_total``)
LOOP_COUNTERS = ("stale_verdict_ticks", "stale_state_ticks", "reasoner_requests", "fallbacks")
WRITE_PERIOD_S = 0.25
WRITE_TIMEOUT_S = 2.0
LINGER_SEQ = 10**6  # the lingering camera's first seq: after any flight's


@dataclass
class Probe:
    """What the robot's side hears: when each observation and its verdict arrived, and
    when the loop first asked the reasoner."""

    observed: dict[int, float] = field(default_factory=dict)
    verdicts: list[tuple[float, float]] = field(default_factory=list)
    anomaly_at: float | None = None
    flying: bool = False

    def on_observation(self, seq: int, at: float) -> None:
        self.observed.setdefault(seq, at)

    def on_verdict(self, seq: int, at: float) -> None:
        sent = self.observed.get(seq)
        if sent is not None:
            self.verdicts.append((sent, at))

    def on_request(self) -> None:
        if self.flying and self.anomaly_at is None:
            self.anomaly_at = time.monotonic()
            print(f"anomaly {self.anomaly_at:.6f}", flush=True)


async def _listen(bus: Bus, robot: str, probe: Probe) -> None:
    observations = bus.subscribe(topics.observation(robot), Observation, maxsize=1024)
    verdicts = bus.subscribe(topics.anomaly(robot), AnomalyVerdict, maxsize=1024)
    requests = bus.subscribe(topics.reasoner_request(robot), ReasonerRequest)

    async def each(sub: Any, on: Any) -> None:
        async for got in sub:
            on(got)

    await asyncio.gather(
        each(observations, lambda g: probe.on_observation(g.message.seq, g.received_at)),
        each(verdicts, lambda g: probe.on_verdict(g.message.seq, g.received_at)),
        each(requests, lambda _: probe.on_request()))


@dataclass
class Writes:
    acked: list[str] = field(default_factory=list)
    failed: int = 0


async def _write(url: str, cache: str, token: str, writes: Writes, tag: str) -> None:
    """One experience every :data:`WRITE_PERIOD_S` to ``cache`` across the link; an id is
    kept once the server answered 2xx (it is durable then)."""
    headers = {"Authorization": f"Bearer {token}"}
    async with httpx.AsyncClient(base_url=url, headers=headers,
                                 timeout=WRITE_TIMEOUT_S) as client:
        n = 0
        while True:
            n += 1
            ident = f"{tag}-{n}"
            try:
                answer = await client.post(f"/v1/caches/{cache}/experiences", json={
                    "items": [{"id": ident, "text": f"a crate on the ground, write {ident}"}]})
                if answer.is_success:
                    writes.acked.append(ident)
                else:
                    writes.failed += 1
            except httpx.HTTPError:
                writes.failed += 1
            await asyncio.sleep(WRITE_PERIOD_S)


async def _linger(bus: Bus, robot: str) -> None:
    """The nominal scene, seen by the camera until ``stop`` arrives on stdin."""
    nominal = observation_text(SCENARIOS[0].detections((0.0, 0.0, 1.0)))
    stop = asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline)
    seq = LINGER_SEQ
    while not stop.done():
        seq += 1
        bus.publish(topics.observation(robot), camera_observation(nominal, seq, robot))
        await asyncio.sleep(CAMERA_PERIOD_S)


async def loop_counters(control: str) -> dict[str, float]:
    """The control loop's own counts of :data:`LOOP_COUNTERS`, from its ``/metrics``."""
    async with httpx.AsyncClient(base_url=control, timeout=10.0) as client:
        answer = await client.get("/metrics")
    answer.raise_for_status()
    found = {f"aesop_control_{name}_total": name for name in LOOP_COUNTERS}
    return {found[sample.name]: sample.value
            for family in text_string_to_metric_families(answer.text)
            for sample in family.samples if sample.name in found}


async def run(args: argparse.Namespace, token: str) -> dict[str, Any]:
    scenario = load_scenario(hardware_scenario())
    settings = BusSettings(zenoh_mode="client", zenoh_connect=[args.router], robot=args.robot)
    probe, writes = Probe(), Writes()
    detector = json.loads(args.detector)

    def started() -> None:
        probe.flying = True
        print(f"started {time.monotonic():.6f}", flush=True)

    with Bus.open(settings, "link-probe") as bus:
        background = [asyncio.create_task(_listen(bus, args.robot, probe))]
        if args.writes:
            background.append(asyncio.create_task(
                _write(args.writes, args.writes_cache, token, writes, args.tag)))
        before = await loop_counters(args.control)
        try:
            result, _ = await fly_robot(None, args.control, args.sim, token, settings,
                                        scenario, None, [demo_scenario(args.scenario)],
                                        real_model=not args.strict, detector=detector,
                                        on_start=started)
            probe.flying = False
            print("flown", flush=True)
            if args.linger:
                await _linger(bus, args.robot)
            after = await loop_counters(args.control)
        finally:
            for task in background:
                task.cancel()
            await asyncio.gather(*background, return_exceptions=True)
    return {"row": result["scenarios"][0], "anomaly_at": probe.anomaly_at,
            "verdicts": probe.verdicts, "writes": {"acked": writes.acked,
                                                   "failed": writes.failed},
            "loop": {name: after.get(name, 0.0) - before.get(name, 0.0)
                     for name in LOOP_COUNTERS}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="aesop-link-driver",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--router", required=True, help="the robot's router, tcp/...")
    parser.add_argument("--control", required=True, help="the control loop's URL")
    parser.add_argument("--sim", required=True, help="the vehicle's URL")
    parser.add_argument("--robot", default="robot0")
    parser.add_argument("--scenario", required=True, help="a demo scenario: 1, 2a, 2b, 3")
    parser.add_argument("--detector", required=True, help="the cache built, as JSON")
    parser.add_argument("--strict", action="store_true",
                        help="the decision must be the expected one (no fault on the link)")
    parser.add_argument("--writes", default=None, metavar="URL",
                        help="the server's embedding service, reached across the link")
    parser.add_argument("--writes-cache", default="link-writes")
    parser.add_argument("--tag", default="w", help="the writes' id prefix")
    parser.add_argument("--linger", action="store_true",
                        help="after the flight, keep the camera on until 'stop' on stdin")
    args = parser.parse_args(argv)
    token = os.environ.get("AESOP_ADMIN_TOKEN", "")
    result = asyncio.run(run(args, token))
    print("result " + json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
