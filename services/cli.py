"""The ``aesop`` command.

Subcommands import their service lazily, so ``aesop --help`` stays fast and a
service never imports another. With ``--json`` a command prints exactly one
JSON object on stdout; progress and logs go to stderr.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import os
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from services.commands import CliError, emit, not_joined


def main(argv: list[str] | None = None) -> int:
    given = sys.argv[1:] if argv is None else argv
    if given[:2] == ["serve", "fake-llm"] and ({"-h", "--help"} & set(given[2:])):
        from services.fakes.llm import build_parser as fake_llm_parser

        fake_llm_parser().parse_args(["--help"])  # the fake's own flags (exits 0)
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra and getattr(args, "service", None) != "fake-llm":
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    args.extra = extra
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request is noise
    logging.getLogger("faiss.loader").setLevel(logging.WARNING)  # which build it found
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
    if args.command in ("serve", "up", "demo"):
        warn_unknown_settings(os.environ)
    try:
        if args.command in ("bench", "demo"):
            require_bench_extra()
        return int(args.func(args) or 0)
    except CliError as exc:
        print(f"aesop: {exc}", file=sys.stderr)
        return 2
    except ValidationError as exc:
        print(f"aesop: invalid settings:\n{exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


DEFAULT_EMBEDDING_URL = "http://127.0.0.1:8001"  # aesop up's embedding service


def add_url_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--url", default=DEFAULT_EMBEDDING_URL,
                        help=f"the embedding service (default {DEFAULT_EMBEDDING_URL}); the "
                             "token from AESOP_ADMIN_TOKEN")


def warn_unknown_settings(environ: Mapping[str, str]) -> list[str]:
    """Say which ``AESOP_*`` variables no service reads (an old or misspelt name is
    otherwise silently ignored); the lines said."""
    from pydantic_settings import BaseSettings

    from services.control.settings import ControlSettings
    from services.dashboard.settings import DashboardSettings
    from services.embedding.settings import EmbeddingSettings
    from services.fakes.llm import FakeLLMServiceSettings, FakeLLMSettings
    from services.reasoner.settings import ReasonerSettings
    from services.sim.settings import SimSettings
    from shared.settings import unknown_names

    classes: list[type[BaseSettings]] = [EmbeddingSettings, ReasonerSettings, ControlSettings,
                                          DashboardSettings, SimSettings,
                                          FakeLLMServiceSettings, FakeLLMSettings]
    lines = [f"aesop: {name} is not a setting of any service" +
             (f" (did you mean {meant}?)" if meant else "")
             for name, meant in unknown_names(environ, classes).items()]
    for line in lines:
        print(line, file=sys.stderr)
    return lines


BENCH_EXTRA = ("matplotlib", "cvxpy", "psutil")  # what `aesop bench` and `aesop demo` add


def require_bench_extra() -> None:
    """The benchmarks and the demo need the ``bench`` extra, which the image leaves out."""
    missing = [name for name in BENCH_EXTRA if importlib.util.find_spec(name) is None]
    if missing:
        raise CliError(f"this command needs the bench extra ({', '.join(missing)} not "
                       "installed): pip install 'aesop-stack[bench]'")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="aesop", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    serve = sub.add_parser("serve", help="run one service (settings also from AESOP_* env vars)")
    serve.add_argument("service",
                       choices=["embedding", "reasoner", "control", "dashboard", "sim",
                                "fake-llm"],
                       help="sim: the simulated vehicle control flies; fake-llm: an "
                            "OpenAI-compatible test server, see its --help")
    serve.add_argument("--host")
    serve.add_argument("--port", type=int)
    serve.add_argument("--data-dir", type=Path)
    serve.add_argument("--scenario", default=None,
                       help="control and sim: a bundled scenario (paper, hardware) or a file "
                            "(default: AESOP_CONTROL_SCENARIO or AESOP_SIM_SCENARIO, else "
                            "paper)")
    serve.set_defaults(func=cmd_serve)

    detector = sub.add_parser("detector", help="offline tools for the fast anomaly detector")
    dsub = detector.add_subparsers(dest="detector_command", required=True)
    ev = dsub.add_parser("eval", help="evaluate the detector on labelled JSONL text sets")
    ev.add_argument("--nominal", type=Path, help="JSONL of nominal experiences (required "
                    "but with --recording against a running cache: --cache)")
    ev.add_argument("--calibration", type=Path, help="JSONL labelled calibration set")
    what = ev.add_mutually_exclusive_group(required=True)
    what.add_argument("--test", type=Path, help="JSONL labelled test set")
    what.add_argument("--recording", type=Path, metavar="FILE.mcap",
                      help="re-score a recorded flight: each observation's recorded verdict "
                           "and today's, and where they differ")
    ev.add_argument("--cache", help="with --recording: score against this cache of a running "
                    "embedding service (--url) instead of --nominal")
    add_url_argument(ev)
    ev.add_argument("--robot", help="with --recording: only this robot's observations")
    ev.add_argument("--changed-only", action="store_true",
                    help="with --recording: list only the observations whose verdict changed")
    ev.add_argument("--k", type=int, default=5)
    ev.add_argument("--alpha", type=float, default=0.95)
    ev.add_argument("--tpr", type=float, default=0.9, help="target TPR for tpr-target")
    ev.add_argument("--method", choices=["loo-quantile", "conformal", "tpr-target"],
                    default="loo-quantile")
    ev.add_argument("--score", choices=["topk", "mahalanobis", "detections", "combined"],
                    default="topk", help="detections, combined: each line's 'detections' "
                    "against the nominal set's (combined: with topk, as conformal p-values)")
    ev.add_argument("--pairs", action="store_true",
                    help="with --score combined: pairs of detections no nominal line holds "
                         "together as a third component")
    ev.add_argument("--model", default=None, help="embedding model (default: all-MiniLM-L6-v2)")
    ev.add_argument("--json", action="store_true")
    ev.set_defaults(func=cmd_detector_eval)

    dd = dsub.add_parser("domains", help="write the synthetic domains as JSONL sets for "
                         "eval: <domain>-nominal.jsonl (80%% of the nominal samples) and "
                         "<domain>-test.jsonl (the other 20%% and every anomaly), with "
                         "their detections")
    dd.add_argument("--out", type=Path, required=True, help="the folder")
    dd.add_argument("--seed", type=int, default=0)
    dd.add_argument("--form", choices=["brief", "prompt"], default="brief",
                    help="the text: the observation (brief) or the paper's whole prompt")
    dd.set_defaults(func=cmd_detector_domains)

    bench = sub.add_parser("bench", help="benchmarks (tables, or one JSON object with --json)")
    bsub = bench.add_subparsers(dest="bench_command", required=True)
    bd = bsub.add_parser("detector", help="detector quality, latency, memory and throughput")
    bd.add_argument("--json", action="store_true")
    bd.add_argument("--quick", action="store_true", help="small sizes, for a smoke run")
    bd.add_argument("--only", action="append", help="run only these parts (repeatable)")
    bd.add_argument("--plot", type=Path, default=None, help="write the quality figure (PNG)")
    bd.add_argument("--seed", type=int, default=0)
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
    br.add_argument("--json", action="store_true")
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
    bm.add_argument("--seed", type=int, default=0)
    bm.add_argument("--json", action="store_true")
    bm.set_defaults(func=cmd_bench_mpc)
    bc = bsub.add_parser("closed-loop", help="the paper's ablation: naive, FS-MPC and AESOP")
    bc.add_argument("--scenarios", type=int, default=500, help="cases (default 500)")
    bc.add_argument("--seed", type=int, default=0)
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
    bc.add_argument("--json", action="store_true")
    bc.set_defaults(func=cmd_bench_closed_loop)
    bl = bsub.add_parser("loop", help="the fixed-rate control loop's jitter and overruns over "
                         "simulated flights (no Zenoh)")
    bl.add_argument("--rates", type=float, nargs="+", default=[10.0, 20.0],
                    help="loop rates in Hz, run one after the other (default 10 20)")
    bl.add_argument("--minutes", type=float, default=10.0,
                    help="simulated flight per rate, in minutes (default 10)")
    bl.add_argument("--scenario", type=Path, default=None,
                    help="a bundled scenario (paper, hardware) or a file (default: paper)")
    bl.add_argument("--seed", type=int, default=0)
    bl.add_argument("--json", action="store_true")
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
    bb.add_argument("--model", default=None,
                    help="embedding model (default: onnx:all-MiniLM-L6-v2, the service's)")
    bb.add_argument("--json", action="store_true")
    bb.set_defaults(func=cmd_bench_bus)

    watch = sub.add_parser("watch", help="the dashboard's live stream as lines in this terminal")
    watch.add_argument("--robot", help="robot id (default: AESOP_ROBOT or robot0)")
    watch.add_argument("--connect", action="append", metavar="ENDPOINT",
                       help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 "
                            "(repeatable; default: AESOP_ZENOH_CONNECT)")
    watch.add_argument("--state-every", type=float, default=1.0, metavar="S",
                       help="at most one state line per S seconds (default 1)")
    watch.set_defaults(func=cmd_watch)

    rec = sub.add_parser("record", help="the stack's Zenoh topics into an MCAP file "
                         "(Foxglove opens it); Ctrl-C stops")
    rec.add_argument("--out", type=Path, default=None,
                     help="the file (default ./aesop-<robot or all>-<UTC time>.mcap)")
    rec.add_argument("--robot", help="only this robot (default: every robot)")
    rec.add_argument("--topics", nargs="+", metavar="TOPIC",
                     help="only these: observation anomaly state plan reasoner/request "
                          "reasoner/decision event regions vehicle/state vehicle/setpoint "
                          "(default: all)")
    rec.add_argument("--connect", action="append", metavar="ENDPOINT",
                     help="Zenoh endpoint (repeatable; default: AESOP_ZENOH_CONNECT)")
    rec.set_defaults(func=recording_command("record_command"))

    rp = sub.add_parser("replay", help="publish a recording on Zenoh again with its timing "
                        "(the dashboard and aesop watch show the flight); Ctrl-C stops")
    rp.add_argument("file", type=Path, metavar="FILE.mcap")
    rp.add_argument("--speed", type=float, default=1.0, help="time scale (2: twice as fast)")
    rp.add_argument("--topics", nargs="+", metavar="TOPIC",
                    help="only these (e.g. observation: a live stack's detector sees the "
                         "recorded scenes; default: all)")
    rp.add_argument("--loop", action="store_true", help="start over at the end")
    rp.add_argument("--connect", action="append", metavar="ENDPOINT",
                    help="Zenoh endpoint (repeatable; default: AESOP_ZENOH_CONNECT)")
    rp.add_argument("--listen", action="append", metavar="ENDPOINT",
                    help="listen here instead, for a dashboard to connect to (repeatable)")
    rp.set_defaults(func=recording_command("replay_command"))

    ca = sub.add_parser("cache", help="nominal experience caches of a running embedding service")
    casub = ca.add_subparsers(dest="cache_command", required=True)
    ci = casub.add_parser("import", help="add a recorded flight's distinct scenes as nominal "
                          "experiences (then calibrate)")
    ci.add_argument("--recording", type=Path, required=True, action="append",
                    metavar="FILE.mcap", help="a recorded flight (repeatable)")
    ci.add_argument("--cache", required=True, help="the cache (created if there is none)")
    ci.add_argument("--since", help="from here: seconds from each recording's start (12.5) "
                    "or an ISO 8601 time (UTC unless it says)")
    ci.add_argument("--until", help="up to here, as --since")
    ci.add_argument("--robot", help="only this robot's observations (default: all)")
    ci.add_argument("--model", default=None, help="embedding model of a new cache")
    ci.add_argument("--k", type=int, default=None,
                    help="neighbours a new cache scores with (default 5; the paper's "
                         "hardware cache: 1)")
    add_url_argument(ci)
    ci.add_argument("--json", action="store_true")
    ci.set_defaults(func=recording_command("cache_import_command"))
    cc = casub.add_parser("calibrate", help="tau of a cache from its own experiences (eq. 2: "
                          "the alpha quantile of the leave-one-out scores)")
    cc.add_argument("--cache", required=True)
    cc.add_argument("--alpha", type=float, default=0.95)
    cc.add_argument("--pairs", action="store_true",
                    help="score pairs of detections too (two nominal objects never seen "
                         "together)")
    add_url_argument(cc)
    cc.add_argument("--json", action="store_true")
    cc.set_defaults(func=recording_command("cache_calibrate_command"))

    zn = sub.add_parser("zenoh", help="the router's access control for docker compose")
    zsub = zn.add_subparsers(dest="zenoh_command", required=True)
    rc = zsub.add_parser("router-config", help="print the router config (the stack's ACL)")
    rc.add_argument("--robot", action="append", default=None,
                    help="a robot that may publish its observations (repeatable; robot0)")
    rc.set_defaults(func=cmd_zenoh_router_config)
    cr = zsub.add_parser("credentials", help="a fresh password for every Zenoh user: the "
                         "router's users.txt and <user>.password files (0600)")
    cr.add_argument("folder", type=Path, help="e.g. deploy/secrets (compose reads it)")
    cr.add_argument("--robot", action="append", default=None,
                    help="a robot to make a user for (repeatable; robot0)")
    cr.set_defaults(func=cmd_zenoh_credentials)

    up = sub.add_parser("up", help="the whole stack on this machine as processes (Ctrl-C stops)")
    up.add_argument("--data-dir", type=Path, default=Path("aesop-data"),
                    help="one subdirectory per service (default ./aesop-data)")
    up.add_argument("--scenario", type=Path, default=None,
                    help="control scenario: a bundled name (paper, hardware) or a file "
                         "(default: AESOP_CONTROL_SCENARIO or the hardware scene)")
    up.add_argument("--random-ports", action="store_true",
                    help="free ports instead of 7447 (Zenoh) and 8001-8003, 8010, 8080")
    up.add_argument("--no-dashboard", action="store_true")
    up.set_defaults(func=cmd_up)

    demo = sub.add_parser("demo", help="the paper's hardware scenarios on the whole stack")
    demo.add_argument("--json", action="store_true")
    demo.add_argument("--out", type=Path, default=Path("aesop-demo-report"),
                      help="report directory (default ./aesop-demo-report)")
    demo.add_argument("--random-ports", action="store_true",
                      help="free ports instead of 7447 (Zenoh) and 8001-8003, 8010, 8080")
    demo.add_argument("--keep-up", action="store_true",
                      help="leave the stack running after the scenarios (Ctrl-C stops it)")
    demo.add_argument("--model", default=None,
                      help="embedding model (default: onnx:all-MiniLM-L6-v2, the service's)")
    demo.set_defaults(func=cmd_demo)
    return parser


def cmd_serve(args: argparse.Namespace) -> int:
    if args.service == "fake-llm":
        from services.fakes.llm import main as fake_llm

        given = [(flag, v) for flag, v in (("--host", args.host), ("--port", args.port))
                 if v is not None]
        return fake_llm([str(x) for pair in given for x in pair] + args.extra)

    overrides = {k: v for k, v in (("host", args.host), ("port", args.port),
                                   ("data_dir", args.data_dir)) if v is not None}
    if args.scenario is not None and args.service not in ("control", "sim"):
        raise CliError("--scenario: only `aesop serve control` and `aesop serve sim` take a "
                       "scenario")
    if args.service == "sim":
        return serve_sim(overrides, args.scenario)
    if args.service == "reasoner":
        return serve_reasoner(overrides)
    if args.service == "control":
        return serve_control(overrides, args.scenario)
    if args.service == "dashboard":
        return serve_dashboard(overrides)

    from services.embedding.api import create_app
    from services.embedding.settings import EmbeddingSettings
    from services.embedding.worker import DetectorWorker
    from shared.http import serve

    settings = EmbeddingSettings(**overrides)
    try:
        settings.check_exposure()
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if settings.torch_threads:
        import torch

        torch.set_num_threads(settings.torch_threads)
    factory = DetectorWorker.factory(settings) if settings.zenoh_worker else None
    serve(create_app(settings, worker_factory=factory), settings)
    return 0


def serve_reasoner(overrides: dict[str, Any]) -> int:
    from services.reasoner.api import create_app
    from services.reasoner.deciding import keep_deadlines, settle
    from services.reasoner.settings import ReasonerSettings
    from services.reasoner.worker import ReasonerWorker
    from shared.http import serve

    settings = ReasonerSettings(**overrides)
    try:
        settings.check_exposure()
    except ValueError as exc:
        raise CliError(str(exc)) from None
    keep_deadlines()
    serve(create_app(settings, worker_factory=ReasonerWorker.factory(settings),
                     on_started=settle), settings)
    return 0


def serve_control(overrides: dict[str, Any], scenario: str | None = None) -> int:
    from services.control.api import create_app
    from services.control.loop import ControlRuntime
    from services.control.scenario import ScenarioError, load_scenario
    from services.control.service import SERVICE
    from services.control.settings import ControlSettings
    from shared.bus import Bus
    from shared.http import serve

    if scenario is not None:
        overrides = {**overrides, "scenario": scenario}
    settings = ControlSettings(**overrides)
    try:
        settings.check_exposure()
        runtime = ControlRuntime(settings, load_scenario(settings.scenario))
    except ScenarioError as exc:  # the message names the file and the field
        raise CliError(f"--scenario: {exc}" if scenario is not None else str(exc)) from None
    except ValueError as exc:
        raise CliError(str(exc)) from None
    app = create_app(settings, runtime, bus_factory=lambda: Bus.open(settings, SERVICE))
    serve(app, settings)
    return 0


def serve_sim(overrides: dict[str, Any], scenario: str | None = None) -> int:
    from services.control.scenario import ScenarioError, load_scenario
    from services.sim.api import create_app
    from services.sim.service import SERVICE
    from services.sim.settings import SimSettings
    from shared.bus import Bus
    from shared.http import serve

    if scenario is not None:
        overrides = {**overrides, "scenario": scenario}
    settings = SimSettings(**overrides)
    try:
        settings.check_exposure()
        app = create_app(settings, load_scenario(settings.scenario),
                         bus_factory=lambda: Bus.open(settings, SERVICE))
    except ScenarioError as exc:
        raise CliError(f"--scenario: {exc}" if scenario is not None else str(exc)) from None
    except ValueError as exc:
        raise CliError(str(exc)) from None
    serve(app, settings)
    return 0


def serve_dashboard(overrides: dict[str, Any]) -> int:
    from services.dashboard.api import create_app
    from services.dashboard.service import SERVICE
    from services.dashboard.settings import DashboardSettings
    from shared.bus import Bus
    from shared.http import serve

    settings = DashboardSettings(**overrides)
    try:
        settings.check_exposure()
    except ValueError as exc:
        raise CliError(str(exc)) from None
    serve(create_app(settings, bus_factory=lambda: Bus.open(settings, SERVICE)), settings)
    return 0


def recording_command(name: str) -> Callable[[argparse.Namespace], int]:
    """``services.recording.cli.<name>``, imported when the command runs."""
    def run(args: argparse.Namespace) -> int:
        from services.recording import cli

        command: Callable[[argparse.Namespace], int] = getattr(cli, name)
        return command(args)
    return run


def cmd_zenoh_router_config(args: argparse.Namespace) -> int:
    from services.stack.acl import router_config_text

    print(router_config_text(args.robot or ["robot0"]), end="")
    return 0


def cmd_zenoh_credentials(args: argparse.Namespace) -> int:
    from services.stack.acl import new_passwords, users_of, write_credentials

    users = users_of(args.robot or ["robot0"])
    try:
        write_credentials(args.folder, new_passwords(users))
    except OSError as exc:
        raise CliError(f"cannot write the credentials into {args.folder}: {exc}") from None
    print(f"wrote {args.folder}/users.txt (the router's) and a password file for each of "
          f"{', '.join(users)}", file=sys.stderr)
    return 0


def cmd_watch(args: argparse.Namespace) -> int:
    import asyncio
    import signal

    import zenoh

    from services.dashboard.watch import watch
    from shared.settings import BusSettings

    if not args.state_every >= 0:
        raise CliError("--state-every must be >= 0")
    overrides = {k: v for k, v in (("robot", args.robot), ("zenoh_connect", args.connect))
                 if v is not None}
    settings = BusSettings(**overrides)
    print(f"aesop watch: robot {settings.robot}; Ctrl-C to stop", file=sys.stderr, flush=True)
    # Ctrl-C (SIGINT) stops it even where it started with SIGINT ignored (a shell's
    # background job), as it stops aesop up
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        asyncio.run(watch(settings, sys.stdout, args.state_every))
    except KeyboardInterrupt:
        return 0
    except zenoh.ZError as exc:
        raise not_joined(exc) from None
    return 0


def cmd_detector_eval(args: argparse.Namespace) -> int:
    from services.bench.evaluate import EvalConfig, evaluate, read_jsonl
    from services.embedding.embedders import EmbedderError, load_embedder
    from services.embedding.errors import DetectorError
    from services.embedding.settings import DEFAULT_MODEL

    for name in ("nominal", "calibration", "test", "recording"):
        path = getattr(args, name)
        if path is not None and not path.is_file():
            raise CliError(f"--{name}: no such file: {path}")
    if not 0 < args.alpha < 1:
        raise CliError("--alpha must be in (0, 1)")
    if args.k < 1:
        raise CliError("--k must be at least 1")
    if args.recording is None and (args.cache or args.robot or args.changed_only):
        raise CliError("--cache, --robot and --changed-only go with --recording")
    if args.recording is not None:
        from services.recording.cli import rescore_recording

        return rescore_recording(args)
    if args.nominal is None:
        raise CliError("--nominal is required (the JSONL of nominal experiences)")
    try:
        config = EvalConfig(k=args.k, alpha=args.alpha, method=args.method, score=args.score,
                            tpr=args.tpr, pairs=args.pairs)
        nominal = read_jsonl(args.nominal)
        test = read_jsonl(args.test)
        calibration = read_jsonl(args.calibration) if args.calibration else []
        embedder = load_embedder(args.model or DEFAULT_MODEL)
        result = evaluate(embedder, nominal, test, calibration, config)
    except (DetectorError, EmbedderError, ValueError) as exc:
        raise CliError(str(exc)) from None
    emit(result, args.json)
    return 0


def cmd_detector_domains(args: argparse.Namespace) -> int:
    from services.scenes.base import write_jsonl
    from services.scenes.registry import DOMAINS, generate

    for name in DOMAINS:
        nominal, test = generate(name, seed=args.seed).split_for_eval(args.seed)
        write_jsonl(args.out / f"{name}-nominal.jsonl", nominal, args.form)
        write_jsonl(args.out / f"{name}-test.jsonl", test, args.form)
        print(f"{name}: {len(nominal)} nominal, {len(test)} test -> {args.out}",
              file=sys.stderr)
    return 0


def cmd_bench_detector(args: argparse.Namespace) -> int:
    from services.bench.detector import run_detector_bench

    result = run_detector_bench(quick=args.quick, only=args.only, plot=args.plot,
                                seed=args.seed, table=not args.json)
    if args.json:
        emit(result, True)
    return 0


def cmd_bench_reasoner(args: argparse.Namespace) -> int:
    from services.bench.reasoner import run_reasoner_bench
    from services.reasoner.deciding import keep_deadlines

    if args.requests < 1 or args.concurrency < 1 or not args.scale > 0:
        raise CliError("--requests and --concurrency must be >= 1 and --scale > 0")
    if args.hedge_after is not None and args.hedge_after < 0:
        raise CliError("--hedge-after must be >= 0")
    keep_deadlines()  # as `aesop serve reasoner` does
    result = run_reasoner_bench(requests=args.requests, scale=args.scale,
                                concurrency=args.concurrency, seed=args.seed,
                                hedge_after_s=args.hedge_after, table=not args.json)
    if args.json:
        emit(result, True)
    return 0


def _control_scenario(path: Path | None):
    from services.control.scenario import ScenarioError, load_scenario

    try:
        return load_scenario(path)
    except (ScenarioError, OSError) as exc:
        raise CliError(f"--scenario: {exc}") from None


def cmd_bench_mpc(args: argparse.Namespace) -> int:
    from services.bench.control import bench_mpc
    from shared.tables import table

    if args.flights < 1 or args.ticks < 2 or args.reference_every < 1:
        raise CliError("--flights and --reference-every must be >= 1, --ticks >= 2")
    if any(n < 10 or n > 2000 for n in args.horizons):
        raise CliError("--horizons: each N must be in 10..2000")
    result = bench_mpc(_control_scenario(args.scenario), flights=args.flights, ticks=args.ticks,
                       reference_every=args.reference_every, seed=args.seed,
                       horizons=args.horizons)
    if args.json:
        emit(result, True)
        return 0
    rows = [_mpc_row(result)] + [_mpc_row(r) for r in result.get("horizons", [])]
    print(table("per-tick AESOP control step (selection over every pair + solve) [ms], and the "
                "CVXPY/Clarabel reference on the same states", rows))
    if "growth_exponent_p50" in result:
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


def cmd_bench_closed_loop(args: argparse.Namespace) -> int:
    from services.bench.control import bench_closed_loop
    from services.sim.vehicle import Reporting
    from shared.tables import table

    if args.scenarios < 1 or args.workers < 1 or args.inconsequential < 0:
        raise CliError("--scenarios and --workers must be >= 1, --inconsequential >= 0")
    if any(not 0 < r <= 10_000 for r in args.state_rate_hz):
        raise CliError("--state-rate-hz: every rate must be in (0, 10000]")
    if any(not 0 <= d <= 10_000 for d in args.state_delay_ms):
        raise CliError("--state-delay-ms: every delay must be in [0, 10000]")
    reportings = [Reporting(rate_hz=r, delay_s=d / 1000.0)
                  for r in args.state_rate_hz for d in args.state_delay_ms]
    result = bench_closed_loop(args.scenarios, args.seed, args.workers,
                               _control_scenario(args.scenario), args.inconsequential, args.plot,
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


def cmd_bench_loop(args: argparse.Namespace) -> int:
    from services.bench.loop import bench_loop, print_loop_table

    if not args.minutes > 0 or any(not r > 0 for r in args.rates):
        raise CliError("--minutes and every --rates value must be > 0")
    _control_scenario(args.scenario)  # a bad scene is a usage error, named here
    result = bench_loop(args.rates, args.minutes, args.scenario, args.seed)
    if args.json:
        emit(result, True)
    else:
        print_loop_table(result)
    return 0


def cmd_bench_bus(args: argparse.Namespace) -> int:
    from services.bench.bus import BenchError, run_bus_bench
    from shared.process import ServiceFailed

    if args.observations < 1 or args.anomalies < 1 or not args.rate > 0:
        raise CliError("--observations and --anomalies must be >= 1 and --rate > 0")
    try:
        result = run_bus_bench(observations=args.observations, rate_hz=args.rate,
                               anomalies=args.anomalies, model=args.model,
                               cache_detections=args.cache_detections, table_out=not args.json)
    except (BenchError, ServiceFailed) as exc:
        print(f"aesop: bench bus: {exc}", file=sys.stderr)
        return 1
    if args.json:
        emit(result, True)
    return 0


def _stack_options(args: argparse.Namespace, data_dir: Path):
    import importlib.util

    from services.control.scenario import resolve_scenario
    from services.control.settings import ControlSettings
    from services.stack.up import Ports, StackOptions, hardware_scenario

    control = ControlSettings()  # what the environment asks of the control loop
    scenario_path = resolve_scenario(args.scenario or control.scenario or hardware_scenario())
    scenario = _control_scenario(scenario_path)
    dashboard = not getattr(args, "no_dashboard", False)
    if dashboard and importlib.util.find_spec("services.dashboard") is None:
        print("aesop: the dashboard is not in this checkout (services/dashboard): starting "
              "without it", file=sys.stderr)
        dashboard = False
    ports = Ports.free() if args.random_ports else Ports()
    busy = ports.busy()
    if busy:
        raise CliError(f"ports already in use: {', '.join(busy)} (is `aesop up` running?); "
                       "stop it or pass --random-ports")
    rate = None if control.rate_hz is not None else 1.0 / scenario.dt
    return StackOptions(data_dir=data_dir, ports=ports, scenario=scenario_path.resolve(),
                        rate_hz=rate, dashboard=dashboard)


def cmd_up(args: argparse.Namespace) -> int:
    from services.stack.up import run_up

    return run_up(_stack_options(args, args.data_dir.resolve()), os.environ)


def cmd_demo(args: argparse.Namespace) -> int:
    from services.demo.flights import run_stack_demo
    from services.stack.up import hardware_scenario

    args.scenario = hardware_scenario()  # the demo flies the hardware scene, whatever the env
    out = args.out.resolve()
    result = run_stack_demo(_stack_options(args, out / "data"), os.environ, out,
                            model=args.model, table=not args.json, keep_up=args.keep_up)
    if args.json:
        print(json.dumps({"scenarios": result["scenarios"]}, allow_nan=False))
    return 0 if result["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
