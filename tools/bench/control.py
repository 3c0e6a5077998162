"""``aesop bench mpc`` and ``aesop bench closed-loop``.

* ``mpc``: the per-tick control step (subset selection over every pair of
  the scene's regions, plus the solve) on nominal flights of the simulated
  vehicle, against a straightforward CVXPY/Clarabel statement of the same
  eq. 3 solving the same pairs at sampled ticks of the same run; optionally
  swept over horizons N at the same T, with the growth exponent in N.
* ``closed-loop``: the paper's ablation (naive, FS-MPC, AESOP) over seeded
  cases, in worker processes, plus the inconsequential case's time loss.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from services.control.core.controllers import METHODS, make_controller, mpc_config
from services.control.core.mpc import SolveStatus, promised_step
from services.control.core.scenario import Scenario, load_scenario, planning_model
from services.sim.plant import make_plant
from services.sim.vehicle import Reporting
from tools import progress

from .reference import reference_solve
from .sim import fly, run_case, sample_cases, summarize, time_lost


def _pct(values: Sequence[float]) -> dict:
    return {"p50": float(np.percentile(values, 50)), "p99": float(np.percentile(values, 99)),
            "max": float(np.max(values)), "n": len(values)}


def bench_mpc(scenario: Scenario | None = None, flights: int = 3, ticks: int = 60,
              reference_every: int = 10, seed: int = 0,
              horizons: Sequence[int] = ()) -> dict:
    """Step time of AESOP's nominal tick and the CVXPY reference on the same states.

    The scene's own grid first; then, for each of ``horizons``, the scene re-gridded to
    that many steps of the same T (``Scenario.regridded``), its flights as long in seconds,
    and the growth exponent of the step's p50 in N fitted over them.
    """
    scenario = scenario or load_scenario()
    result = _mpc_run(scenario, flights, ticks, reference_every, seed, (1, 1 + len(horizons)))
    if horizons:
        runs = []
        for i, n in enumerate(horizons, 2):
            scale = scenario.dt * n / scenario.horizon_s  # ticks per tick of the scene's grid
            runs.append(_mpc_run(scenario.regridded(n), flights, max(2, round(ticks * scale)),
                                 max(1, round(reference_every * scale)), seed,
                                 (i, 1 + len(horizons))))
        result["horizons"] = runs
        result["growth_exponent_p50"] = _exponent([r["problem"]["horizon"] for r in runs],
                                                  [r["step_ms"]["p50"] for r in runs])
    return result


def _exponent(ns: Sequence[int], values: Sequence[float]) -> float | None:
    """The least-squares slope of log(value) in log(N): 1 is linear growth."""
    if len(ns) < 2:
        return None
    return float(np.polyfit(np.log(ns), np.log(values), 1)[0])


def _mpc_run(scenario: Scenario, flights: int, ticks: int, reference_every: int,
             seed: int, run: tuple[int, int] = (1, 1)) -> dict:
    model = planning_model(scenario)
    config = mpc_config(scenario)
    rng = np.random.default_rng(seed)
    step_ms: list[float] = []
    first_ms: list[float] = []
    warm_up_ms, reference_ms, rel_diffs, iterations = [], [], [], []
    infeasible = undecided = referee = 0
    progress.step(f"{scenario.name}, N = {config.horizon}, dt = {scenario.dt:g} s", *run)
    for flight in range(flights):
        progress.count(flight, flights, "flights")
        controller = make_controller("aesop", scenario, config)
        plant = make_plant(scenario, scenario.sample_start(rng))
        start = time.perf_counter()
        controller.warm_up(plant.state)  # as the service does, off the loop
        warm_up_ms.append((time.perf_counter() - start) * 1e3)
        for tick in range(ticks):
            x = plant.state
            start = time.perf_counter()
            out = controller.make_step(x, False)
            elapsed = (time.perf_counter() - start) * 1e3
            (first_ms if tick == 0 else step_ms).append(elapsed)
            if out.plan is not None:
                iterations.append(out.plan.iterations)
                referee += out.plan.refereed
            infeasible += out.status is SolveStatus.INFEASIBLE
            undecided += not out.status.decided
            if tick >= 1 and (tick - 1) % reference_every == 0:  # the second tick, then every
                ref_total, diffs = _reference_tick(model, scenario, config, controller)
                reference_ms.append(ref_total)
                rel_diffs += diffs
            plant.step(out.u)
    return {
        "problem": {"horizon": config.horizon, "consensus": config.consensus,
                    "regions": len(scenario.regions), "subsets": len(list(
                        itertools.combinations(scenario.regions, 2))), "dt_s": scenario.dt,
                    "model": scenario.model},
        "step_ms": _pct(step_ms),
        "first_tick_ms": _pct(first_ms),
        "warm_up_ms": _pct(warm_up_ms),
        "reference_step_ms": _pct(reference_ms),
        "speedup_p50": float(np.percentile(reference_ms, 50) / np.percentile(step_ms, 50)),
        "objective_rel_diff_max": float(max(rel_diffs)) if rel_diffs else None,
        "objective_compared": len(rel_diffs),
        "iterations": _pct(iterations) if iterations else None,
        "refereed_chains": referee,
        "infeasible_ticks": infeasible,
        "undecided_ticks": undecided,
        "ticks": len(step_ms) + len(first_ms),
        "eps": config.eps_abs,
    }


def _reference_tick(model, scenario, config, controller) -> tuple[float, list[float]]:
    """CVXPY on every candidate subset of the controller's last selection, at its state;
    the relative cost gap where both call it feasible. (The plans are the ones that tick
    solved: nothing is solved again here, so the next tick's timing is untouched.)"""
    total, diffs = 0.0, []
    xm, goal = controller.measured, controller.goal
    for subset, plan in controller.selector.last.candidates.items():
        regions = [scenario.region(i) for i in subset]
        ref = reference_solve(model, config, regions, xm, goal,
                              region_step=promised_step(config, 0))
        total += ref.total_ms
        if ref.status == "optimal" and plan.feasible:
            diffs.append(abs(plan.cost - ref.cost) / max(abs(ref.cost), 1e-9))
    return total, diffs


def bench_closed_loop(scenarios: int = 500, seed: int = 0, workers: int = 2,
                      scenario: Scenario | None = None, inconsequential: int = 5,
                      plot: Path | None = None, reportings: Sequence[Reporting] = (),
                      methods: Sequence[str] = METHODS) -> dict:
    """The ablation of ``methods`` over ``scenarios`` seeded cases, once per way the
    vehicle reports its state (``reportings``; default: 100 Hz, no delay): one
    condition each, the same cases in every one."""
    scenario = scenario or load_scenario()
    cases = sample_cases(scenario, scenarios, seed)
    conditions = []
    started = time.perf_counter()
    steps = 0
    with ProcessPoolExecutor(max(1, workers)) as pool:
        for reporting in reportings or (Reporting(),):
            state = {"rate_hz": reporting.rate_hz, "delay_ms": round(reporting.delay_s * 1e3, 3)}
            rows: dict[str, Any] = {}
            outcomes: dict[str, list[Any]] = {}
            for method in methods:
                steps += 1
                progress.step(f"{method} at {state['rate_hz']:g} Hz, {state['delay_ms']:g} ms",
                              steps, len(methods) * max(1, len(reportings)))
                outcomes[method] = []
                for outcome in pool.map(run_case, [(method, scenario, c, reporting)
                                                   for c in cases]):
                    outcomes[method].append(outcome)
                    progress.count(len(outcomes[method]), len(cases), "cases")
                rows[method] = summarize(outcomes[method])
                progress.say(f"bench closed-loop: {method} at {state['rate_hz']:g} Hz, "
                             f"{state['delay_ms']:g} ms done, "
                             f"{time.perf_counter() - started:.0f} s")
            lost = list(pool.map(_time_lost, [(scenario, c, reporting)
                                               for c in cases[:inconsequential]]))
            losses = [r["time_lost_s"] for r in lost if r["time_lost_s"] is not None]
            conditions.append({
                "state": state,
                "methods": rows,
                "inconsequential": {"cases": len(lost),
                                    "mean_time_lost_s": float(np.mean(losses)) if losses
                                    else None,
                                    "max_time_lost_s": float(np.max(losses)) if losses
                                    else None,
                                    "reached_goal": len(losses)},
                "failures": {m: [o.case for o in outs if not o.success][:20]
                             for m, outs in outcomes.items()},
            })
    result = {"scenario": scenario.name, "scenarios": scenarios, "seed": seed,
              "conditions": conditions, "wall_s": time.perf_counter() - started}
    if plot is not None:
        plot_case(scenario, cases[0], plot)
        result["plot"] = str(plot)
    return result


def _time_lost(args) -> dict:
    scenario, case, reporting = args
    return time_lost(scenario, case, reporting=reporting)


def plot_case(scenario: Scenario, case, path: Path) -> None:
    """A figure like the paper's: the three methods' flights of one case over the regions,
    with AESOP's plan tree at the anomaly (nominal plan and recovery branches)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    colours = {"naive": "tab:red", "fsmpc": "tab:orange", "aesop": "tab:blue"}
    for ax, (i, j, names) in zip(axes, ((0, 1, "x [m] / y [m]"), (0, 2, "x [m] / z [m]")),
                                 strict=True):
        for region in scenario.regions:
            lo, hi = region.position_lo, region.position_hi
            ax.add_patch(Rectangle((lo[i], lo[j]), hi[i] - lo[i], hi[j] - lo[j], alpha=0.25,
                                   color="tab:green"))
            ax.annotate(f"{region.index}: {region.name}", (lo[i], hi[j]), fontsize=8)
        ax.plot(scenario.goal[i], scenario.goal[j], "k*", markersize=12, label="goal")
        ax.set_xlabel(names.split(" / ")[0])
        ax.set_ylabel(names.split(" / ")[1])
    for method in METHODS:
        flight = fly(method, scenario, case)
        for ax, (i, j) in zip(axes, ((0, 1), (0, 2)), strict=True):
            ax.plot(flight.states[:, i], flight.states[:, j], color=colours[method],
                    label=f"{method} (chose {flight.chosen})")
            if flight.t_anom_s is not None:
                k = int(round(flight.t_anom_s / scenario.dt))
                ax.plot(flight.states[k, i], flight.states[k, j], "x", color=colours[method])
    tree = _tree_at_anomaly(scenario, case)
    if tree is not None:
        for ax, (i, j) in zip(axes, ((0, 1), (0, 2)), strict=True):
            if tree.nominal is not None:
                ax.plot(tree.nominal[:, i], tree.nominal[:, j], "k--", linewidth=1,
                        label="AESOP nominal plan at anomaly")
            for branch in tree.recovery.values():
                ax.plot(branch[:, i], branch[:, j], ":", color="tab:purple", linewidth=1)
    axes[0].legend(fontsize=8, loc="lower left")
    fig.suptitle(f"{scenario.name}: case {case.index}, anomaly at {case.anomaly_s:.1f} s "
                 "(dotted: AESOP recovery tree at the anomaly)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _tree_at_anomaly(scenario: Scenario, case):
    controller = make_controller("aesop", scenario)
    plant = make_plant(scenario, case.x0)
    anomaly_tick = int(round(case.anomaly_s / scenario.dt))
    for tick in range(anomaly_tick + 1):
        out = controller.make_step(plant.state, tick == anomaly_tick, None)
        plant.step(out.u)
    return out.plan
