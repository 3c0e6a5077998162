"""``aesop bench ...``: the benchmarks, as tables or one JSON object (``--json``).

``aesop bench detector|reasoner|mpc|closed-loop|loop|bus|fairness|ros2|fleet|link``; they
need the ``bench`` extra."""

from __future__ import annotations

import argparse
import functools
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tools import progress
from tools.commands import CliError, control_scenario, emit
from tools.stack.cli import add_llm_options


def _add_template_options(br: argparse.ArgumentParser) -> None:
    """``aesop bench reasoner --llm local``'s own options (the template bench)."""
    br.add_argument("--repeats", type=int, default=3,
                    help="--llm local: times each case is asked per template (3)")
    br.add_argument("--deadline", type=float, default=60.0,
                    help="--llm local: each decision's deadline in s (60)")
    br.add_argument("--domain-samples", type=int, default=2,
                    help="--llm local: anomalies, nominal scenes per synthetic domain (2)")
    br.add_argument("--threads", type=int, default=None,
                    help="--llm local: the server's threads (default 2, the model alone on "
                         "the cores; 1 where anything runs beside it, as the stack serves it)")
    br.add_argument("--template", action="append", default=None,
                    choices=["cot", "single", "cot-json", "single-json", "single-json-first"],
                    help="--llm local: only these templates (repeatable; default all)")


def _json_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true",
                        help="print the result as one JSON object instead of tables")


def _seed_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=0,
                        help="random seed of what is drawn (default 0)")


def register(sub: argparse._SubParsersAction) -> None:
    bench = sub.add_parser("bench", help="benchmarks (tables, or one JSON object with --json)")
    bsub = bench.add_subparsers(dest="bench_command", required=True)
    bd = bsub.add_parser("detector", help="detector quality, latency, memory and throughput")
    _json_option(bd)
    bd.add_argument("--quick", action="store_true", help="small sizes, for a smoke run")
    bd.add_argument("--only", action="append", help="run only these parts (repeatable)")
    bd.add_argument("--plot", type=Path, default=None, help="write the quality figure (PNG)")
    _seed_option(bd)
    bd.set_defaults(func=cmd_bench_detector)
    br = bsub.add_parser("reasoner", help="deadline, fallbacks, overhead and hedging of the "
                         "slow reasoner against the fake LLM (bimodal profile)")
    br.add_argument("--requests", type=int, default=1000, help="decisions per run (default 1000)")
    br.add_argument("--scale", type=float, default=0.1,
                    help="time scale of the latencies and of K = 4.3 s (default 0.1)")
    br.add_argument("--concurrency", type=int, default=8, help="decisions in flight (8)")
    br.add_argument("--seed", type=int, default=0, help="fake LLM seed (second backend: +1)")
    br.add_argument("--hedge-after", type=float, default=None,
                    help="hedging delay in s (default: the single-backend p50 latency)")
    br.add_argument("--cpu-hog", type=int, default=0,
                    help="this many other processes spin on the CPU throughout (default 0)")
    _json_option(br)
    add_llm_options(br)
    _add_template_options(br)
    br.set_defaults(func=cmd_bench_reasoner)

    bm = bsub.add_parser("mpc", help="per-tick AESOP control step vs a CVXPY reference of eq. 3")
    bm.add_argument("--flights", type=int, default=3, help="nominal flights (default 3)")
    bm.add_argument("--ticks", type=int, default=60, help="ticks per flight (default 60)")
    bm.add_argument("--reference-every", type=int, default=10,
                    help="solve the CVXPY reference every N ticks (default 10)")
    bm.add_argument("--scenario", type=Path, default=None,
                    help="a bundled scenario (paper, hardware) or a file (default: paper)")
    bm.add_argument("--horizons", type=int, nargs="+", default=[],
                    help="also re-grid the scene to these N at the same T (e.g. 40 100 200 400)")
    _seed_option(bm)
    _json_option(bm)
    bm.set_defaults(func=cmd_bench_mpc)
    bc = bsub.add_parser("closed-loop", help="the paper's ablation: naive, FS-MPC and AESOP")
    bc.add_argument("--scenarios", type=int, default=500, help="cases (default 500)")
    _seed_option(bc)
    bc.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                    help="worker processes (default: every CPU)")
    bc.add_argument("--inconsequential", type=int, default=5,
                    help="cases flown again with y = 0 to measure the time lost (default 5)")
    bc.add_argument("--scenario", type=Path, default=None,
                    help="a bundled scenario (paper, hardware) or a file (default: paper)")
    bc.add_argument("--plot", type=Path, default=None, help="write a figure of case 0 (PNG)")
    bc.add_argument("--state-delay-ms", type=float, nargs="+", default=[0.0],
                    help="the vehicle's state is published this long after the instant it is "
                         "valid for (default 0); several: one condition each")
    bc.add_argument("--state-rate-hz", type=float, nargs="+", default=[100.0],
                    help="the vehicle's state rate (default 100); several: one condition each")
    bc.add_argument("--methods", nargs="+", choices=["naive", "fsmpc", "aesop"],
                    default=["naive", "fsmpc", "aesop"], help="(default: all three)")
    _json_option(bc)
    bc.set_defaults(func=cmd_bench_closed_loop)
    bl = bsub.add_parser("loop", help="the fixed-rate control loop's jitter and overruns over "
                         "simulated flights (the simulator a process over Zenoh)")
    bl.add_argument("--rates", type=float, nargs="+", default=[10.0, 20.0],
                    help="loop rates in Hz, run one after the other (default 10 20)")
    bl.add_argument("--minutes", type=float, default=10.0,
                    help="simulated flight per rate, in minutes (default 10)")
    bl.add_argument("--scenario", type=Path, default=None,
                    help="a bundled scenario (paper, hardware) or a file (default: paper)")
    _seed_option(bl)
    _json_option(bl)
    bl.set_defaults(func=cmd_bench_loop)
    bb = bsub.add_parser("bus", help="observation -> verdict and -> control reaction latency "
                         "over Zenoh (embedding and control as processes)")
    bb.add_argument("--observations", type=int, default=500,
                    help="observations timed for the verdict latency (default 500)")
    bb.add_argument("--rate", type=float, default=20.0, help="observations per second (20)")
    bb.add_argument("--anomalies", type=int, default=20,
                    help="anomalies timed for the control reaction (default 20)")
    bb.add_argument("--cache-detections", type=int, default=4, choices=[1, 2, 3, 4],
                    help="cache every combination of up to N scene detections (default 4)")
    _model_option(bb)
    _json_option(bb)
    bb.set_defaults(func=cmd_bench_bus)
    _fairness_parser(bsub)
    _ros2_parser(bsub)
    _fleet_parser(bsub)
    _link_parser(bsub)
    bench.set_defaults(needs_bench_extra=True)


def _fairness_parser(bsub: argparse._SubParsersAction) -> None:
    bf = bsub.add_parser("fairness", help="one robot floods its observations: another robot's "
                         "verdict latency and losses, through the hub (or --direct)")
    bf.add_argument("--flood-hz", type=float, default=2000.0,
                    help="robot1's observations per second (default 2000)")
    bf.add_argument("--rate", type=float, default=10.0, help="robot0's per second (10)")
    bf.add_argument("--seconds", type=float, default=30.0,
                    help="robot0 timed alone, and as long flooded (default 30)")
    bf.add_argument("--rounds", type=int, default=3,
                    help="alone then flooded, this many times over, to share the machine's "
                         "drift (default 3)")
    bf.add_argument("--direct", action="store_true",
                    help="no hub: the robots reach the service as peers (its own defence only)")
    bf.add_argument("--same-text", action="store_true",
                    help="robot1 floods one fixed observation (the detector's memo makes it "
                         "nearly free) instead of distinct ones")
    _model_option(bf)
    _json_option(bf)
    bf.set_defaults(func=cmd_bench_fairness)


def _ros2_parser(bsub: argparse._SubParsersAction) -> None:
    br = bsub.add_parser("ros2", help="the ROS 2 bridge's latency both ways (aesop serve ros2 "
                         "as a process, this one playing the robot and the stack)")
    br.add_argument("--seconds", type=float, default=20.0, help="each way (default 20)")
    br.add_argument("--rate", type=float, default=100.0,
                    help="samples per second (100: odometry's usual rate)")
    _json_option(br)
    br.set_defaults(func=cmd_bench_ros2)


def _fleet_parser(bsub: argparse._SubParsersAction) -> None:
    bfl = bsub.add_parser("fleet", help="1 to 64 robots' verdicts on one and two detector "
                          "replicas sharing PostgreSQL; replica lag; PostgreSQL vs SQLite")
    bfl.add_argument("--seconds", type=float, default=15.0,
                     help="each fleet size on each replica count (default 15)")
    bfl.add_argument("--rate", type=float, default=10.0, help="per robot per second (10)")
    bfl.add_argument("--lags", type=int, default=100, help="adds timed for the lag (100)")
    bfl.add_argument("--adds", type=int, default=50,
                     help="commits per store for its cost (default 50)")
    bfl.add_argument("--batch", type=int, default=100, help="experiences per commit (100)")
    _model_option(bfl)
    _json_option(bfl)
    bfl.set_defaults(func=cmd_bench_fleet)


def _link_parser(bsub: argparse._SubParsersAction) -> None:
    bl = bsub.add_parser("link", help="robot and server on two hosts (network namespaces, "
                         "needs root) over a lossy link: the hardware scenarios at each "
                         "delay, cuts, stalls, routers restarted")
    bl.add_argument("--delays", type=float, nargs="+", default=[0, 20, 50, 100],
                    metavar="MS", help="one-way delays (default 0 20 50 100)")
    bl.add_argument("--jitter", type=float, default=20.0, metavar="MS",
                    help="± jitter at each delay, at most the delay (default 20)")
    bl.add_argument("--repeats", type=int, default=1, help="the four scenarios per delay (1)")
    bl.add_argument("--cuts", type=float, nargs="*", default=[3, 30], metavar="S",
                    help="cuts into the nominal flight (default 3 30)")
    bl.add_argument("--no-faults", action="store_true",
                    help="leave out the stall and the routers restarted")
    bl.add_argument("--out", type=Path, default=None,
                    help="keep the logs and data here (default: a temporary folder)")
    _json_option(bl)
    bl.set_defaults(func=cmd_bench_link)


def _shown(command: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """The bench's progress on stderr while it runs (:mod:`tools.progress`), redrawn only
    when it changes: no thread of the display's wakes during the bench's timings."""
    @functools.wraps(command)
    def shown(args: argparse.Namespace) -> int:
        with progress.shown(f"aesop bench {args.bench_command}", ticking=False):
            return command(args)
    return shown


def _model_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", default=None,
                        help="embedding model (default: onnx:all-MiniLM-L6-v2, the service's)")


@_shown
def cmd_bench_detector(args: argparse.Namespace) -> int:
    from tools.bench.detector import run_detector_bench

    result = run_detector_bench(quick=args.quick, only=args.only, plot=args.plot,
                                seed=args.seed, table=not args.json)
    if args.json:
        emit(result, True)
    return 0


@_shown
def cmd_bench_reasoner(args: argparse.Namespace) -> int:
    from services.reasoner.deciding import keep_up
    from tools.bench.reasoner import run_reasoner_bench
    from tools.stack.cli import local_model

    model = local_model(args)
    if model is not None:
        return bench_templates(args, model)
    if args.requests < 1 or args.concurrency < 1 or not args.scale > 0:
        raise CliError("--requests and --concurrency must be >= 1 and --scale > 0")
    if args.hedge_after is not None and args.hedge_after < 0:
        raise CliError("--hedge-after must be >= 0")
    if not 0 <= args.cpu_hog <= 64:
        raise CliError("--cpu-hog must be in 0..64")
    keep_up()  # as `aesop serve reasoner` does
    result = run_reasoner_bench(requests=args.requests, scale=args.scale,
                                concurrency=args.concurrency, seed=args.seed,
                                hedge_after_s=args.hedge_after, table=not args.json,
                                cpu_hog=args.cpu_hog)
    if args.json:
        emit(result, True)
    return 0


def bench_templates(args: argparse.Namespace, model: Any) -> int:
    import tempfile

    from tools.bench.templates import TEMPLATES, render, run_templates_bench
    from tools.local_llm import THREADS

    threads = THREADS if args.threads is None else args.threads
    if args.repeats < 1 or not args.deadline > 0 or args.domain_samples < 0 or threads < 1:
        raise CliError("--repeats and --threads must be >= 1, --deadline > 0 and "
                       "--domain-samples >= 0")
    with tempfile.TemporaryDirectory(prefix="aesop-bench-templates-") as logs:
        result = run_templates_bench(model, repeats=args.repeats, deadline_s=args.deadline,
                                     templates=args.template or tuple(TEMPLATES),
                                     logs=Path(logs), domain_samples=args.domain_samples,
                                     threads=threads)
    if args.json:
        emit(result, True)
    else:
        print(render(result))
    return 0


@_shown
def cmd_bench_mpc(args: argparse.Namespace) -> int:
    from shared.tables import table
    from tools.bench.control import bench_mpc

    if args.flights < 1 or args.ticks < 2 or args.reference_every < 1:
        raise CliError("--flights and --reference-every must be >= 1, --ticks >= 2")
    if any(n < 10 or n > 2000 for n in args.horizons):
        raise CliError("--horizons: each N must be in 10..2000")
    result = bench_mpc(control_scenario(args.scenario), flights=args.flights, ticks=args.ticks,
                       reference_every=args.reference_every, seed=args.seed,
                       horizons=args.horizons)
    if args.json:
        emit(result, True)
        return 0
    rows = [_mpc_row(result)] + [_mpc_row(r) for r in result.get("horizons", [])]
    print(table("per-tick AESOP control step (selection over every pair + solve) [ms], and the "
                "CVXPY/Clarabel reference on the same states", rows))
    if result.get("growth_exponent_p50") is not None:  # fitted from two horizons on
        print(f"growth of the step's p50 in N: N^{result['growth_exponent_p50']:.2f}")
    return 0


def _mpc_row(run: dict) -> dict:
    step, ref = run["step_ms"], run["reference_step_ms"]
    diff = run["objective_rel_diff_max"]
    return {"N": run["problem"]["horizon"], "dt [s]": run["problem"]["dt_s"],
            "p50": step["p50"], "p99": step["p99"], "max": step["max"],
            "warm-up": run["warm_up_ms"]["p50"], "first tick": run["first_tick_ms"]["max"],
            "iters p50": run["iterations"]["p50"] if run["iterations"] else None,
            "refereed": run["refereed_chains"], "infeasible": run["infeasible_ticks"],
            "undecided": run["undecided_ticks"], "ticks": run["ticks"],
            "CVXPY p50": ref["p50"], "speed-up": f"{run['speedup_p50']:.0f}x",
            "obj. diff": "-" if diff is None else f"{diff:.1e}"}


@_shown
def cmd_bench_closed_loop(args: argparse.Namespace) -> int:
    from services.sim.vehicle import Reporting
    from shared.tables import table
    from tools.bench.control import bench_closed_loop

    if args.scenarios < 1 or args.workers < 1 or args.inconsequential < 0:
        raise CliError("--scenarios and --workers must be >= 1, --inconsequential >= 0")
    if any(not 0 < r <= 10_000 for r in args.state_rate_hz):
        raise CliError("--state-rate-hz: every rate must be in (0, 10000]")
    if any(not 0 <= d <= 10_000 for d in args.state_delay_ms):
        raise CliError("--state-delay-ms: every delay must be in [0, 10000]")
    reportings = [Reporting(rate_hz=r, delay_s=d / 1000.0)
                  for r in args.state_rate_hz for d in args.state_delay_ms]
    result = bench_closed_loop(args.scenarios, args.seed, args.workers,
                               control_scenario(args.scenario), args.inconsequential, args.plot,
                               reportings, args.methods)
    if args.json:
        emit(result, True)
        return 0
    rows = [{"state": f"{c['state']['rate_hz']:g} Hz, {c['state']['delay_ms']:g} ms",
             "method": m, **r} for c in result["conditions"] for m, r in c["methods"].items()]
    print(table(f"closed loop, {result['scenario']}, {args.scenarios} cases, seed {args.seed}",
                rows))
    for c in result["conditions"]:
        print(f"inconsequential case at {c['state']['rate_hz']:g} Hz, "
              f"{c['state']['delay_ms']:g} ms: {c['inconsequential']}")
    return 0


@_shown
def cmd_bench_loop(args: argparse.Namespace) -> int:
    from tools.bench.loop import bench_loop, print_loop_table

    if not args.minutes > 0 or any(not r > 0 for r in args.rates):
        raise CliError("--minutes and every --rates value must be > 0")
    control_scenario(args.scenario)  # a bad scene is a usage error, named here
    result = bench_loop(args.rates, args.minutes, args.scenario, args.seed)
    if args.json:
        emit(result, True)
    else:
        print_loop_table(result)
    return 0


@_shown
def cmd_bench_bus(args: argparse.Namespace) -> int:
    from tools.bench.bus import run_bus_bench

    if args.observations < 1 or args.anomalies < 1 or not args.rate > 0:
        raise CliError("--observations and --anomalies must be >= 1 and --rate > 0")
    return _with_processes("bus", lambda: run_bus_bench(
        observations=args.observations, rate_hz=args.rate, anomalies=args.anomalies,
        model=args.model, cache_detections=args.cache_detections, table_out=not args.json),
        args.json)


@_shown
def cmd_bench_fairness(args: argparse.Namespace) -> int:
    from tools.bench.fairness import run_fairness_bench

    if not (args.flood_hz > 0 and args.rate > 0 and args.seconds > 0 and args.rounds >= 1):
        raise CliError("--flood-hz, --rate and --seconds must be positive, --rounds at least 1")
    return _with_processes("fairness", lambda: run_fairness_bench(
        seconds=args.seconds, rate_hz=args.rate, flood_hz=args.flood_hz, direct=args.direct,
        model=args.model, table_out=not args.json, same_text=args.same_text,
        rounds=args.rounds), args.json)


@_shown
def cmd_bench_ros2(args: argparse.Namespace) -> int:
    from tools.bench.ros2 import run_ros2_bench

    if not (args.seconds > 0 and args.rate > 0):
        raise CliError("--seconds and --rate must be positive")
    return _with_processes("ros2", lambda: run_ros2_bench(
        seconds=args.seconds, rate_hz=args.rate, table_out=not args.json), args.json)


@_shown
def cmd_bench_fleet(args: argparse.Namespace) -> int:
    from tools.bench.fleet import run_fleet_bench

    if not (args.seconds > 0 and args.rate > 0) or min(args.lags, args.adds, args.batch) < 1:
        raise CliError("--seconds and --rate must be positive, --lags, --adds and --batch "
                       "at least 1")
    return _with_processes("fleet", lambda: run_fleet_bench(
        seconds=args.seconds, rate_hz=args.rate, lags=args.lags, adds=args.adds,
        batch=args.batch, model=args.model, table_out=not args.json), args.json)


@_shown
def cmd_bench_link(args: argparse.Namespace) -> int:
    from tools.bench.link import run_link_bench

    if args.repeats < 1 or any(d < 0 for d in args.delays) or args.jitter < 0 \
            or any(c <= 0 for c in args.cuts):
        raise CliError("--repeats counts from 1; --delays and --jitter are not negative, "
                       "--cuts positive")
    return _with_processes("link", lambda: run_link_bench(
        delays=args.delays, jitter_ms=args.jitter, repeats=args.repeats, cuts=args.cuts,
        faults=not args.no_faults, out=args.out, table_out=not args.json), args.json)


def _with_processes(name: str, run: Callable[[], dict[str, Any]], as_json: bool) -> int:
    """A bench of service processes: a service that fails, or a wait that runs out, is
    said in one line and exit status 1."""
    from shared.process import ServiceFailed
    from tools.bench.bus import BenchError

    try:
        result = run()
    except (BenchError, ServiceFailed) as exc:
        print(f"aesop: bench {name}: {exc}", file=sys.stderr)
        return 1
    if as_json:
        emit(result, True)
    return 0
