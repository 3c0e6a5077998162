"""``aesop demo``: the paper's hardware scenarios flown by the whole stack, with a report."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from tools.stack.cli import add_fleet_options, add_llm_options


def register(sub: argparse._SubParsersAction) -> None:
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
    add_fleet_options(demo)  # --robots 3: three scenarios flown at once, one per robot
    add_llm_options(demo)  # --llm local: a trained model, K measured on it first
    demo.set_defaults(func=cmd_demo, needs_bench_extra=True)


def cmd_demo(args: argparse.Namespace) -> int:
    from tools.demo.flights import run_stack_demo
    from tools.stack.cli import stack_options
    from tools.stack.up import hardware_scenario

    args.scenario = hardware_scenario()  # the demo flies the hardware scene, whatever the env
    out = args.out.resolve()
    result = run_stack_demo(stack_options(args, out / "data"), os.environ, out,
                            model=args.model, table=not args.json, keep_up=args.keep_up)
    if args.json:
        print(json.dumps({"scenarios": result["scenarios"], **(
            {"k": result["k"]} if "k" in result else {})}, allow_nan=False))
    return 0 if result["ok"] else 1
