"""``aesop watch``: the dashboard's live stream as lines in this terminal."""

from __future__ import annotations

import argparse
import sys

from tools.commands import CliError, joined, not_joined


def register(sub: argparse._SubParsersAction) -> None:
    watch = sub.add_parser("watch", help="the dashboard's live stream as lines in this terminal")
    watch.add_argument("--robot", help="robot id, or all: every robot of a fleet, each line "
                       "led by its robot (default: AESOP_ROBOT or robot0)")
    watch.add_argument("--connect", action="append", metavar="ENDPOINT",
                       help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 "
                            "(repeatable; default: AESOP_ZENOH_CONNECT)")
    watch.add_argument("--state-every", type=float, default=1.0, metavar="S",
                       help="at most one state line per S seconds (default 1)")
    watch.set_defaults(func=cmd_watch)


def cmd_watch(args: argparse.Namespace) -> int:
    import asyncio
    import signal

    import zenoh

    from services.dashboard.watch import watch
    from shared.settings import BusSettings

    if not args.state_every >= 0:
        raise CliError("--state-every must be >= 0")
    fleet = args.robot == "all"
    overrides = {k: v for k, v in (("robot", None if fleet else args.robot),
                                   ("zenoh_connect", args.connect)) if v is not None}
    settings = BusSettings(**overrides)
    print(f"aesop watch: {'every robot' if fleet else 'robot ' + settings.robot}; Ctrl-C to "
          "stop", file=sys.stderr, flush=True)
    joined(settings, "watch")  # exits 2 unless the endpoints let it in
    # Ctrl-C (SIGINT) stops it even where it started with SIGINT ignored (a shell's
    # background job), as it stops aesop up
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        asyncio.run(watch(settings, sys.stdout, args.state_every, fleet=fleet))
    except KeyboardInterrupt:
        return 0
    except zenoh.ZError as exc:
        raise not_joined(exc) from None
    return 0
