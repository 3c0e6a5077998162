"""``aesop bench loop``: the fixed-rate control loop's timing over simulated flights.

The service's own loop (:class:`~.loop.FixedRateScheduler` driving
:class:`~.loop.ControlRuntime` on its tick thread) runs for a number of
simulated minutes at each rate, flying the simulated vehicle as a separate process
(``aesop serve sim``) over Zenoh: its state arrives on the bus at 100 Hz, the
set-points go back on it, and the vehicle's clock is queried as the service queries
it. The verdicts and decisions are scripted in this process: a fresh nominal verdict
every tick, an anomaly every ``cycle_s`` of flight (in the middle of the scene's
anomaly window), the reasoner's answer (the first region offered) ``answer_s``
later, and a new flight once the recovery has had time to land: the vehicle moved to
a new start over its HTTP route, then the loop reset beside the ticks on the event
loop as the ``POST /v1/reset`` route runs it. So every mode of Algorithm 1 is timed,
resets included.

Jitter is a tick's start minus its deadline; an overrun is a tick whose work
ended after the next deadline. The vehicle runs ``rate * dt`` simulated seconds per
second (its ``time_scale``), so 20 Hz flies the paper scene (dt 0.1 s) at twice real
time and the hardware scene (dt 0.05 s) in real time.
"""

from __future__ import annotations

import asyncio
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from services.control.core.scenario import Scenario, load_scenario, resolve_scenario
from services.control.loop import ControlRuntime, FixedRateScheduler, TickTiming
from services.control.service import VehicleAges, sync_clock
from services.control.settings import ControlSettings, ControlTuning
from services.sim.client import SimClient
from shared import topics
from shared.bus import Bus, Received
from shared.messages import AnomalyVerdict, ReasonerDecision, VehicleState
from shared.process import ServiceProcess, free_port
from shared.settings import BusSettings
from shared.stats import spread
from tools import progress

ROBOT = "bench"

NOMINAL = AnomalyVerdict(seq=0, score=-0.9, threshold=-0.7, is_anomaly=False, k=1,
                         model="bench", cache="bench", cache_version=1, latency_ms=1.0)


class FlightScript:
    """What the outside world sends on tick ``k``: a verdict, maybe a decision."""

    def __init__(self, dt: float, cycle_s: float = 20.0, anomaly_s: float = 4.0,
                 answer_s: float = 1.0) -> None:
        self.cycle = max(1, round(cycle_s / dt))
        self.anomaly = round(anomaly_s / dt)
        self.answer = max(1, round(answer_s / dt))
        self._decision: tuple[int, ReasonerDecision] | None = None
        self.paused = False  # no verdicts while a new flight is set up

    def verdict(self, k: int) -> AnomalyVerdict:
        flagged = k % self.cycle == self.anomaly
        return NOMINAL.model_copy(update={"seq": k, "is_anomaly": flagged,
                                          "score": -0.5 if flagged else -0.9})

    def decision(self, k: int) -> ReasonerDecision | None:
        if self._decision is not None and self._decision[0] == k:
            return self._decision[1]
        return None

    def answered(self, k: int, request_id: str, choice: int) -> None:
        self._decision = (k + self.answer, ReasonerDecision(
            request_id=request_id, choice=choice, source="llm", latency_ms=1000.0))

    def reset_after(self, k: int) -> bool:
        return k % self.cycle == self.cycle - 1


async def time_loop(scenario: Scenario, rate_hz: float, ticks: int, bus: Bus, sim: SimClient,
                    seed: int = 0, script: FlightScript | None = None) -> dict[str, Any]:
    """Run ``ticks`` ticks of the loop at ``rate_hz`` flying the vehicle behind ``bus`` and
    ``sim``; the scheduler's statistics and the vehicle state's age at the ticks.

    As in the service, the ticks run on their own thread, the clock queries on another,
    and the resets (as ``POST /v1/reset`` would) on this event loop, beside them.
    """
    settings = ControlSettings(rate_hz=rate_hz, robot=ROBOT,
                               tuning=ControlTuning(stats_window=max(ticks, 10)),
                               verdict_stale_s=max(0.5, 5.0 / rate_hz))
    runtime = ControlRuntime(settings, scenario)
    scheduler = FixedRateScheduler(runtime.period_s, window=max(ticks, 10))
    script = script or FlightScript(scenario.dt, **_timeline(scenario))
    counts = {"requests": 0, "resets": 0}
    ages = VehicleAges(window=max(ticks, 10))  # the state's age at the ticks, as the service
    overruns: dict[str, int] = {}  # by the mode the tick flew in ("reset": during one)
    flights: list[dict[str, Any]] = []  # the set-points' ages at the vehicle, per flight
    resets: list[Future] = []
    loop = asyncio.get_running_loop()
    rng = np.random.default_rng(seed)
    states = bus.latest(topics.vehicle_state(ROBOT), VehicleState)
    setpoints = topics.vehicle_setpoint(ROBOT)
    stop_sync = threading.Event()
    syncing = threading.Thread(target=sync_clock, args=(bus, ROBOT, runtime.vehicle.clock, 1.0,
                                                        stop_sync), daemon=True)
    k = 0

    async def new_flight(start: np.ndarray) -> None:
        """As an operator starts one: the detector off (the reset loop waits), the loop
        reset, the vehicle moved to ``start``; once its state says so, the detector on."""
        script.paused = True
        flights.append((await sim.state()).setpoints)
        await runtime.reset()
        await sim.reset([float(v) for v in start[0:3]])
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            newest = runtime.vehicle.newest
            if newest is not None and np.linalg.norm(newest[0:3] - start[0:3]) < 0.05:
                break
            await asyncio.sleep(0.01)
        script.paused = False

    def note(timing: TickTiming) -> None:
        if timing.overrun:
            phase = "reset" if script.paused else runtime.mode.value
            overruns[phase] = overruns.get(phase, 0) + 1

    def tick(deadline: float) -> None:
        nonlocal k
        verdict = None if script.paused else Received("bench", script.verdict(k),
                                                      time.monotonic())
        result = runtime.tick(deadline=deadline, verdict=verdict, decision=script.decision(k),
                              state=states.get())
        if result.setpoint is not None:
            bus.publish(setpoints, result.setpoint)
        ages.record(result)
        if result.request is not None:
            counts["requests"] += 1
            script.answered(k, result.request.request_id, result.request.options[1].index)
        if script.reset_after(k) and k < ticks - 1:
            resets.append(asyncio.run_coroutine_threadsafe(
                new_flight(scenario.sample_start(rng)), loop))
            counts["resets"] += 1
        k += 1

    await sim.reset([float(v) for v in scenario.start_center])  # where the loop warmed up
    syncing.start()
    switch = sys.getswitchinterval()
    sys.setswitchinterval(settings.tuning.switch_interval_s)
    started = time.monotonic()
    counting = asyncio.create_task(count_ticks(lambda: k, ticks))
    try:
        await asyncio.to_thread(scheduler.run, tick, on_tick=note, max_ticks=ticks)
    finally:
        counting.cancel()
        sys.setswitchinterval(switch)
        stop_sync.set()
        states.close()
        runtime.close()
    for reset in resets:
        await asyncio.wrap_future(reset)
    summary = scheduler.stats.summary()
    flights.append((await sim.state()).setpoints)
    return {"rate_hz": rate_hz, "wall_s": round(time.monotonic() - started, 1),
            "simulated_s": round(ticks * scenario.dt, 1), **counts, **summary,
            "setpoints": ages.setpoints, "stale_state_ticks": ages.stale_ticks,
            "overruns_by_mode": overruns, **spread(ages.ages_ms, "state_age"),
            **setpoint_ages(flights)}


async def count_ticks(flown: Callable[[], int], ticks: int, every_s: float = 2.0) -> None:
    """The ticks flown so far on the progress line, from the event loop's thread (not the
    ticks' own), every ``every_s``, until cancelled."""
    while True:
        progress.count(flown(), ticks, "ticks")
        await asyncio.sleep(every_s)


def setpoint_ages(flights: Sequence[dict[str, Any]]) -> dict[str, float | None]:
    """The set-points' ages at the vehicle, from its per-flight figures (its ages start
    again with each reset): the median flight's p50, the worst flight's p99 and max."""
    def pick(key: str, how: Any) -> float | None:
        values = [f[key] for f in flights if f.get(key) is not None]
        return round(float(how(values)), 3) if values else None

    return {"setpoint_age_p50_ms": pick("age_p50_ms", np.median),
            "setpoint_age_p99_ms": pick("age_p99_ms", max),
            "setpoint_age_max_ms": pick("age_max_ms", max)}


async def fly_rate(scenario: Scenario, path: Path, rate_hz: float, ticks: int,
                   seed: int, script: FlightScript | None = None) -> dict[str, Any]:
    """:func:`time_loop` against a simulator process of its own, as fast as the rate flies
    the scene (``time_scale = rate * dt``)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory(prefix="aesop-bench-loop-") as tmp, \
            Bus.open(BusSettings(zenoh_listen=[endpoint], robot=ROBOT), "bench") as bus:
        port = free_port()
        env = {"AESOP_ZENOH_CONNECT": endpoint, "AESOP_ZENOH_LISTEN": "", "AESOP_ROBOT": ROBOT,
               "AESOP_SIM_TIME_SCALE": str(rate_hz * scenario.dt), "AESOP_SIM_SEED": str(seed)}
        with ServiceProcess(["serve", "sim", "--port", str(port), "--scenario", str(path)],
                            port=port, env=env, log_path=Path(tmp) / "sim.log",
                            unset=["AESOP_ADMIN_TOKEN"]) as process:
            async with SimClient(process.url, timeout_s=30) as sim:
                return await time_loop(scenario, rate_hz, ticks, bus, sim, seed, script)


def _timeline(scenario: Scenario) -> dict[str, float]:
    """An anomaly in the middle of the scene's anomaly window; the flight reset once the
    recovery has had T and 5 s more."""
    lo, hi = scenario.anomaly_window
    anomaly_s = (lo + hi) / 2
    return {"anomaly_s": anomaly_s, "cycle_s": max(20.0, anomaly_s + scenario.horizon_s + 5.0)}


def bench_loop(rates: Sequence[float] = (10.0, 20.0), minutes: float = 10.0,
               scenario: Path | None = None, seed: int = 0) -> dict[str, Any]:
    """``minutes`` of simulated flight at each of ``rates``, one after the other, each
    against a simulator process of its own (``scenario``: a bundled name or a file)."""
    path = resolve_scenario(scenario or "paper")
    scene = load_scenario(path)
    ticks = max(1, round(minutes * 60.0 / scene.dt))
    runs = []
    for n, rate in enumerate(rates, 1):
        progress.step(f"{ticks} ticks at {rate:g} Hz ({ticks / rate:.0f} s of wall time)", n,
                      len(rates))
        runs.append(asyncio.run(fly_rate(scene, path, rate, ticks, seed)))
    return {"scenario": scene.name, "simulated_minutes": minutes, "ticks": ticks,
            "runs": runs}


def print_loop_table(result: dict[str, Any], out: TextIO | None = None) -> None:
    out = sys.stdout if out is None else out  # today's (a progress line may stand in for it)
    print(f"control loop, {result['simulated_minutes']:g} min of simulated flight per rate "
          f"({result['ticks']} ticks, scenario {result['scenario']})", file=out)
    print(f"{'rate':>6} {'jitter p50':>11} {'jitter p99':>11} {'jitter max':>11} "
          f"{'tick p50':>9} {'tick p99':>9} {'overruns':>9} {'missed':>7} {'requests':>9} "
          f"{'state age p50/p99/max':>22} {'stale':>6} {'set-point age p50/p99/max':>26}",
          file=out)

    def ages(r: dict[str, Any], what: str) -> str:
        got = [r[f"{what}_age_{q}_ms"] for q in ("p50", "p99", "max")]
        return "/".join("-" if v is None else f"{v:.1f}" for v in got) + "ms"

    for r in result["runs"]:
        print(f"{r['rate_hz']:>4g}Hz {r['jitter_p50_ms']:>9.3f}ms {r['jitter_p99_ms']:>9.3f}ms "
              f"{r['jitter_max_ms']:>9.3f}ms {r['tick_p50_ms']:>7.2f}ms "
              f"{r['tick_p99_ms']:>7.2f}ms {r['overruns']:>9} {r['missed_ticks']:>7} "
              f"{r['requests']:>9} {ages(r, 'state'):>22} {r['stale_state_ticks']:>6} "
              f"{ages(r, 'setpoint'):>26}", file=out)
        if r.get("overruns_by_mode"):
            by = ", ".join(f"{mode} {n}" for mode, n in sorted(r["overruns_by_mode"].items()))
            print(f"{'':>6} overruns by the mode the tick flew in: {by}", file=out)
