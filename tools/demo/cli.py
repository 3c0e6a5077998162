"""``aesop demo``'s flags and handlers: a stack of its own, or one attached to (``--attach``)."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from tools import progress
from tools.stack.cli import add_fleet_options, add_llm_options


def register(sub: argparse._SubParsersAction) -> None:
    demo = sub.add_parser("demo", help="the paper's hardware scenarios on the whole stack")
    demo.add_argument("--json", action="store_true",
                      help="print the result as one JSON object instead of tables")
    demo.add_argument("--out", type=Path, default=Path("aesop-demo-report"),
                      help="report directory (default ./aesop-demo-report)")
    demo.add_argument("--random-ports", action="store_true",
                      help="free ports instead of 7447 (Zenoh) and 8001-8003, 8010, 8080")
    demo.add_argument("--keep-up", action="store_true",
                      help="leave the stack running after the scenarios (Ctrl-C stops it)")
    demo.add_argument("--model", default=None,
                      help="embedding model (default: onnx:all-MiniLM-L6-v2, the service's)")
    attach = demo.add_argument_group(
        "attach", "fly against a stack that is already up (docker compose: its published "
        "ports and deploy/secrets), as its robot: the Zenoh session from AESOP_ZENOH_* "
        "(default: a client of tcp/127.0.0.1:7447 as robot-<AESOP_ROBOT>, the password "
        "from deploy/secrets), the token from AESOP_ADMIN_TOKEN(_FILE) or "
        "deploy/secrets/admin-token")
    attach.add_argument("--attach", action="store_true", help="do not start a stack")
    attach.add_argument("--embedding-url", default="http://127.0.0.1:8001",
                        help="its detector (default http://127.0.0.1:8001)")
    attach.add_argument("--control-url", default="http://127.0.0.1:8003",
                        help="its robot's control loop (default http://127.0.0.1:8003)")
    attach.add_argument("--sim-url", default="http://127.0.0.1:8004",
                        help="the simulated vehicle (aesop serve sim): reset over HTTP, "
                             "flights judged on its truth trace and set-point ages (default "
                             "http://127.0.0.1:8004)")
    attach.add_argument("--vehicle", choices=["sim", "bus"], default="sim",
                        help="sim (default): the simulator at --sim-url; bus: any vehicle "
                             "of the contract (docs/architecture.md 3a), reset by a query "
                             "when it answers one, judged on its vehicle/truth or states")
    attach.add_argument("--secrets", type=Path, default=Path("deploy/secrets"),
                        help="where the defaults come from (aesop zenoh credentials)")
    attach.add_argument("--data-dir", type=Path, default=None,
                        help="an `aesop up` stack's data dir instead: its zenoh/ passwords and "
                             "its admin-token (aesop up prints the whole command)")
    attach.add_argument("--connect", default=None, metavar="ENDPOINT",
                        help="its router (default tcp/127.0.0.1:7447, or AESOP_ZENOH_CONNECT)")
    attach.add_argument("--scenario-name", action="append", default=None, metavar="NAME",
                        help="only this scenario (2a, 2b, 3, 1; repeatable)")
    attach.add_argument("--measure-k", action="store_true",
                        help="first measure K on the model its reasoner asks, as --llm local "
                             "does; flies the K its control loop has, and writes the scene "
                             "with the K chosen to --out, saying how to fly it (default: "
                             "off, the loop's K, nothing measured)")
    attach.add_argument("--reasoner-url", default="http://127.0.0.1:8002",
                        help="its reasoner, for --measure-k (default http://127.0.0.1:8002)")
    add_fleet_options(demo)  # --robots 3: three scenarios flown at once, one per robot
    add_llm_options(demo)  # --llm local: a trained model, K measured on it first
    demo.set_defaults(func=cmd_demo, needs_bench_extra=True)


def cmd_demo(args: argparse.Namespace) -> int:
    if args.attach:
        return cmd_attached(args)
    from tools.demo.flights import run_stack_demo
    from tools.stack.cli import stack_options
    from tools.stack.up import hardware_scenario

    args.scenario = hardware_scenario()  # the demo flies the hardware scene, whatever the env
    out = args.out.resolve()
    with progress.shown("aesop demo"):
        result = run_stack_demo(stack_options(args, out / "data"), os.environ, out,
                                model=args.model, table=not args.json, keep_up=args.keep_up)
    if args.json:
        print(json.dumps({"scenarios": result["scenarios"], **(
            {"k": result["k"]} if "k" in result else {})}, allow_nan=False))
    # --keep-up: a service that died stopped the stack, as it ends `aesop up` (status 1)
    return 0 if result["ok"] and not result.get("stack_stopped") else 1


def cmd_attached(args: argparse.Namespace) -> int:
    from shared.settings import BusSettings, read_settings
    from tools.commands import DATA_DIR_LOGIN, CliError, joined
    from tools.demo.flights import Attached, demo_scenario, run_attached_demo
    from tools.stack.acl import robot_user
    from tools.stack.compose import TOKEN_FILE

    env = dict(os.environ)
    robot = env.get("AESOP_ROBOT", "robot0")
    # compose's secrets (aesop zenoh credentials), or an `aesop up` data dir's
    passwords, token_file = ((args.secrets, args.secrets / TOKEN_FILE) if args.data_dir is None
                             else (args.data_dir / "zenoh", args.data_dir / "admin-token"))
    defaults = {"zenoh_mode": "client", "zenoh_connect": "tcp/127.0.0.1:7447"}
    if "AESOP_ZENOH_USER" not in env:
        defaults |= {"zenoh_user": robot_user(robot),
                     "zenoh_password_file": passwords / f"{robot_user(robot)}.password"}
    forced = {} if args.connect is None else {"zenoh_connect": args.connect}
    try:
        bus = read_settings(BusSettings, env, defaults=defaults, **forced)
        bus.zenoh_secret()  # a password file that cannot be read, named now
        token = env.get("AESOP_ADMIN_TOKEN") or _first_line(
            Path(env.get("AESOP_ADMIN_TOKEN_FILE", token_file)))
        for name in args.scenario_name or ():
            demo_scenario(name)
    except (ValueError, KeyError) as exc:
        raise CliError(f"demo --attach: {exc}") from None
    # exits 2 unless the router lets the robot's user in, before the cache is built (a
    # refused client was a traceback after it; a peer session opened whatever answered)
    joined(bus, "demo --attach --data-dir <data-dir>", DATA_DIR_LOGIN)
    _services_answer({"--embedding-url": args.embedding_url, "--control-url": args.control_url,
                      **({"--sim-url": args.sim_url} if args.vehicle == "sim" else {})})
    stack = Attached(args.embedding_url, args.control_url,
                     args.sim_url if args.vehicle == "sim" else None, token, bus,
                     reasoner_url=args.reasoner_url if args.measure_k else None,
                     compose=args.data_dir is None)
    if args.measure_k:  # a reasoner that does not let us in, said before the cache is built
        _reasoner_answers(args.reasoner_url, token)
    with progress.shown("aesop demo"):
        result = run_attached_demo(stack, args.out.resolve(), names=args.scenario_name,
                                   model=args.model, table=not args.json)
    if args.json:
        print(json.dumps({"scenarios": result["scenarios"], **(
            {"k": result["k"]} if "k" in result else {})}, allow_nan=False))
    return 0 if result["ok"] else 1


def _services_answer(urls: dict[str, str]) -> None:
    """A usage error (status 2) naming the URL and its flag unless each service answers its
    ``/healthz`` (no token needed): one that is not up was an httpx traceback mid-demo."""
    import httpx

    from tools.commands import CliError

    for flag, url in urls.items():
        try:
            httpx.get(f"{url.rstrip('/')}/healthz", timeout=5.0).raise_for_status()
        except (httpx.HTTPError, OSError) as exc:
            raise CliError(f"demo --attach: nothing answers at {url} ({exc}): start the stack "
                           f"(aesop up, or docker compose up) or name the service with "
                           f"{flag}") from None


def _reasoner_answers(url: str, token: str) -> None:
    """A usage error (status 2) unless the reasoner at ``url`` answers its admin API."""
    import asyncio

    import httpx

    from services.reasoner.client import ReasonerClient
    from shared.client import ServiceError
    from tools.commands import CliError

    async def ask() -> None:
        async with ReasonerClient(url, token=token, timeout_s=10) as reasoner:
            await reasoner.backends()

    try:
        asyncio.run(ask())
    except (ServiceError, httpx.HTTPError, OSError) as exc:
        raise CliError(f"demo --attach --measure-k: the reasoner at {url} does not answer "
                       f"({exc}); --reasoner-url names it") from None


def _first_line(path: Path) -> str:
    try:
        return path.read_text().strip()
    except OSError as exc:
        raise ValueError(f"the admin token: cannot read {path}: {exc.strerror} (set "
                         "AESOP_ADMIN_TOKEN, or run as a user who may read it)") from None
