"""``aesop bench link``: the robot and the server on two hosts, a lossy link between them.

The rig (:mod:`tools.link.rig`): a network namespace for the robot joined to this one by a
veth pair, ``aesop zenoh certs``, ``aesop up --role server`` here and ``aesop up --role
robot`` there, their routers linked over mutual TLS through a fault proxy on the link.
Then:

1. **Conditions**: at each one-way delay (0, 20, 50, 100 ms, each with up to ± 20 ms
   jitter, both ways) the four hardware scenarios, ``repeats`` times, each judged on the
   vehicle's truth as ``aesop demo`` judges it (the expected region and decision, no tick
   outside the limits); each verdict's round trip on the robot (an observation's arrival at
   its router to its verdict's); the link's own RTT through the same proxy
   (:func:`tools.link.proxy.measure_rtt`: p50 and p99, the verdict's p99 judged against the
   RTT's, jitter being the link's and in both); the link's load (Zenoh's bytes each way).
2. **Cuts**: the nominal flight with the link cut 3 s (and 30 s) into it: violations, whether
   the loop committed its fallback (by K, when the silence outlasts it), the time from the
   link's return to the robot's first verdict again, and the writes the server acknowledged
   across the link that it then did not have.
3. **Faults**: a 1 s stall, the server's router and the robot's router killed mid-flight.

Targets (issue 41): 100 % in the expected region and no violation at 50 ± 20 ms; verdict
p99 ≤ the link's RTT (p99) + 30 ms; a cut: no violation, the robot hearing verdicts again ≤ 2 s
after the link returns, no acknowledged write lost. Needs root (the namespace).
"""

from __future__ import annotations

import itertools
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from statistics import median
from typing import Any

import numpy as np

from shared.tables import table
from tools import progress
from tools.bench.bus import BenchError, say
from tools.link.netns import missing
from tools.link.proxy import measure_rtt
from tools.link.rig import Fault, Flight, Rig, delay

SCENARIOS = ("1", "2a", "2b", "3")
TARGET_RECONNECT_S = 2.0
TARGET_MARGIN_MS = 30.0  # verdict p99 over the link's RTT


def run_link_bench(*, delays: Sequence[float] = (0, 20, 50, 100), jitter_ms: float = 20.0,
                   repeats: int = 1, cuts: Sequence[float] = (3, 30), faults: bool = True,
                   out: Path | None = None, table_out: bool = True) -> dict[str, Any]:
    why = missing()
    if why is not None:
        raise BenchError(f"the robot's network namespace: {why}")
    with tempfile.TemporaryDirectory(prefix="aesop-link-") as tmp, \
            Rig(out or Path(tmp), say=say) as rig:
        others = (Fault("stall 1 s", stall_s=1.0),
                  Fault("server's router restarted", restart="server"),
                  Fault("robot's router restarted", restart="robot")) if faults else ()
        steps = itertools.count(1)
        total = len(delays) + len(cuts) + len(others)

        def step(label: str) -> None:
            progress.step(label, next(steps), total)

        conditions = [_condition(rig, delay(ms, jitter_ms), repeats, step) for ms in delays]
        cut_rows = [_cut(rig, Fault(f"cut {s:g} s", cut_s=s), step) for s in cuts]
        fault_rows = [_fault(rig, f, step) for f in others]
    result = {"conditions": conditions, "cuts": cut_rows, "faults": fault_rows,
              "targets": _targets(conditions, cut_rows)}
    if table_out:
        print(report(result))
    return result


def _condition(rig: Rig, fault: Fault, repeats: int, step: Callable[[str], None]
               ) -> dict[str, Any]:
    step(f"{fault.name} ± {fault.jitter_ms:g} ms: the four scenarios x {repeats}")
    flights = [rig.fly(fault, s) for _ in range(repeats) for s in SCENARIOS]
    verdicts = [ms for f in flights for ms in f.verdict_ms]
    rtt = measure_rtt(fault.impairment, 50)
    return {"delay_ms": fault.delay_ms, "jitter_ms": fault.jitter_ms,
            "scenarios": len(flights),
            "success_rate": round(sum(f.row["outcome"] == "ok" for f in flights)
                                  / len(flights), 3),
            "violations": sum(f.row["constraint_violations"] for f in flights),
            "verdict_p50_ms": _pct(verdicts, 50), "verdict_p99_ms": _pct(verdicts, 99),
            "rtt_ms": round(median(rtt), 1), "rtt_p99_ms": _pct(rtt, 99),
            "link_kb_s": [round(median(f.link_kb_s[i] for f in flights), 1) for i in (0, 1)],
            "failures": [f"{f.scenario}: {f.row['outcome']}" for f in flights
                         if f.row["outcome"] != "ok"]}


def _cut(rig: Rig, fault: Fault, step: Callable[[str], None]) -> dict[str, Any]:
    step(f"{fault.name} into the nominal flight")
    flight = rig.fly(fault, "1")
    return {"cut_s": fault.cut_s, "violations": flight.row["constraint_violations"],
            "fallbacks": int(flight.fallback), **_after(flight)}


def _fault(rig: Rig, fault: Fault, step: Callable[[str], None]) -> dict[str, Any]:
    step(f"{fault.name} in the nominal flight")
    flight = rig.fly(fault, "1")
    return {"fault": fault.name, "violations": flight.row["constraint_violations"],
            "fallbacks": int(flight.fallback), **_after(flight)}


def _after(flight: Flight) -> dict[str, Any]:
    row = flight.row
    return {"reconnect_s": None if flight.reconnect_s is None else round(flight.reconnect_s, 2),
            "acknowledged_lost": len(flight.lost), "acknowledged": len(flight.acked),
            "ended_in": row["ended_in"], "decision": row["decision"],
            "source": row["decision_source"], "outcome": row["outcome"]}


def _pct(values: Sequence[float], q: float) -> float | None:
    return round(float(np.percentile(values, q)), 1) if values else None


def _targets(conditions: Sequence[dict[str, Any]], cuts: Sequence[dict[str, Any]]
             ) -> dict[str, bool]:
    at_50 = [c for c in conditions if c["delay_ms"] == 50]
    return {
        "all expected at 50 ms, no violation": bool(at_50) and all(
            c["success_rate"] == 1.0 and c["violations"] == 0 for c in at_50),
        "verdict p99 <= the link's RTT p99 + 30 ms": all(
            c["verdict_p99_ms"] is not None
            and c["verdict_p99_ms"] <= c["rtt_p99_ms"] + TARGET_MARGIN_MS for c in conditions),
        "cuts: no violation, back <= 2 s, none lost": all(
            c["violations"] == 0 and c["acknowledged_lost"] == 0
            and c["reconnect_s"] is not None and c["reconnect_s"] <= TARGET_RECONNECT_S
            for c in cuts)}


def report(result: dict[str, Any]) -> str:
    conditions = [{k: v for k, v in c.items() if k != "failures"} for c in result["conditions"]]
    out = [table("the four hardware scenarios across the link (one-way delay ± jitter)",
                 conditions),
           table("the link cut mid-flight", result["cuts"])]
    if result["faults"]:
        out.append(table("faults mid-flight", result["faults"]))
    out.append(table("targets", [{"target": k, "met": v}
                                 for k, v in result["targets"].items()]))
    failures = [f for c in result["conditions"] for f in c["failures"]]
    if failures:
        out.append("failed flights: " + "; ".join(failures))
    return "\n".join(out)
