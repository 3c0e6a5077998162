"""``aesop bench loop``: the fixed-rate control loop's timing over simulated flights.

The service's own loop (:class:`~.loop.FixedRateScheduler` driving
:class:`~.loop.ControlRuntime` on its tick thread) runs for a number of
simulated minutes at each rate, without Zenoh: a fresh nominal verdict every
tick, an anomaly every ``cycle_s`` of flight (in the middle of the scene's
anomaly window), the reasoner's answer (the first region offered) ``answer_s``
later, and a reset to a new start once the recovery has had time to land, run
beside the loop on the event loop as the ``POST /v1/reset`` route runs it. So
every mode of Algorithm 1 is timed, resets included.

Jitter is a tick's start minus its deadline; an overrun is a tick whose work
ended after the next deadline. The plant advances ``dt`` per tick whatever the
rate, so 20 Hz flies the simulation at twice real time.
"""

from __future__ import annotations

import asyncio
import sys
import time
from collections.abc import Sequence
from concurrent.futures import Future
from typing import Any

from services.control.loop import ControlRuntime, FixedRateScheduler
from services.control.scenario import Scenario, load_scenario
from services.control.settings import ControlSettings
from shared.bus import Received
from shared.messages import AnomalyVerdict, ReasonerDecision

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


async def time_loop(scenario: Scenario, rate_hz: float, ticks: int, seed: int = 0,
                    script: FlightScript | None = None) -> dict[str, Any]:
    """Run ``ticks`` ticks of the loop at ``rate_hz``; the scheduler's statistics.

    As in the service, the ticks run on their own thread, and the resets (as
    ``POST /v1/reset`` would) on this event loop, beside them.
    """
    settings = ControlSettings(rate_hz=rate_hz, seed=seed, stats_window=max(ticks, 10),
                               verdict_stale_s=max(0.5, 5.0 / rate_hz))
    runtime = ControlRuntime(settings, scenario)
    scheduler = FixedRateScheduler(runtime.period_s, window=max(ticks, 10))
    script = script or FlightScript(scenario.dt, **_timeline(scenario))
    counts = {"requests": 0, "resets": 0}
    resets: list[Future] = []
    loop = asyncio.get_running_loop()
    k = 0

    def tick(deadline: float) -> None:
        nonlocal k
        verdict = Received("bench", script.verdict(k), time.monotonic())
        result = runtime.tick(deadline=deadline, verdict=verdict, decision=script.decision(k))
        if result.request is not None:
            counts["requests"] += 1
            script.answered(k, result.request.request_id, result.request.options[1].index)
        if script.reset_after(k):
            resets.append(asyncio.run_coroutine_threadsafe(runtime.reset(), loop))
            counts["resets"] += 1
        k += 1

    switch = sys.getswitchinterval()
    sys.setswitchinterval(settings.switch_interval_s)
    started = time.monotonic()
    try:
        await asyncio.to_thread(scheduler.run, tick, max_ticks=ticks)
    finally:
        sys.setswitchinterval(switch)
    for reset in resets:
        await asyncio.wrap_future(reset)
    summary = scheduler.stats.summary()
    return {"rate_hz": rate_hz, "wall_s": round(time.monotonic() - started, 1),
            "simulated_s": round(ticks * scenario.dt, 1), **counts, **summary}


def _timeline(scenario: Scenario) -> dict[str, float]:
    """An anomaly in the middle of the scene's anomaly window; the flight reset once the
    recovery has had T and 5 s more."""
    lo, hi = scenario.anomaly_window
    anomaly_s = (lo + hi) / 2
    return {"anomaly_s": anomaly_s, "cycle_s": max(20.0, anomaly_s + scenario.horizon_s + 5.0)}


def bench_loop(rates: Sequence[float] = (10.0, 20.0), minutes: float = 10.0,
               scenario: Scenario | None = None, seed: int = 0) -> dict[str, Any]:
    """``minutes`` of simulated flight at each of ``rates``, one after the other."""
    scenario = scenario or load_scenario()
    ticks = max(1, round(minutes * 60.0 / scenario.dt))
    runs = []
    for rate in rates:
        print(f"bench loop: {ticks} ticks at {rate:g} Hz ({ticks / rate:.0f} s of wall time)",
              file=sys.stderr, flush=True)
        runs.append(asyncio.run(time_loop(scenario, rate, ticks, seed)))
    return {"scenario": scenario.name, "simulated_minutes": minutes, "ticks": ticks,
            "runs": runs}


def print_loop_table(result: dict[str, Any], out=sys.stdout) -> None:
    print(f"control loop, {result['simulated_minutes']:g} min of simulated flight per rate "
          f"({result['ticks']} ticks, scenario {result['scenario']})", file=out)
    print(f"{'rate':>6} {'jitter p50':>11} {'jitter p99':>11} {'jitter max':>11} "
          f"{'tick p50':>9} {'tick p99':>9} {'overruns':>9} {'missed':>7} {'requests':>9}",
          file=out)
    for r in result["runs"]:
        print(f"{r['rate_hz']:>4g}Hz {r['jitter_p50_ms']:>9.3f}ms {r['jitter_p99_ms']:>9.3f}ms "
              f"{r['jitter_max_ms']:>9.3f}ms {r['tick_p50_ms']:>7.2f}ms "
              f"{r['tick_p99_ms']:>7.2f}ms {r['overruns']:>9} {r['missed_ticks']:>7} "
              f"{r['requests']:>9}", file=out)
