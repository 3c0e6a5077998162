"""``aesop watch``: the dashboard's live stream as lines in this terminal."""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

from tools.commands import CliError, not_joined

if TYPE_CHECKING:
    from shared.settings import BusSettings

# how long the router (or peer) named has to let this session in before aesop watch gives up
JOIN_TIMEOUT_S = 5.0
LOGIN = ("AESOP_ZENOH_MODE=client AESOP_ZENOH_USER=monitor "
         "AESOP_ZENOH_PASSWORD_FILE=<data-dir>/zenoh/monitor.password")


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
    joined(settings)
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


def joined(settings: BusSettings) -> None:
    """Fail (a ``CliError``, status 2) unless the endpoints to connect to let a session in
    within ``JOIN_TIMEOUT_S``: a file named by the settings that cannot be read is named,
    and a router that refuses or does not answer is said, with how to log in.

    A peer session (the default mode) opens whether or not its endpoints answer and keeps
    retrying them, so against aesop up's router, which lets in only its users, aesop watch
    without a user used to wait silently for ever. This session is a probe of its own,
    closed once one router or peer is connected (any of several endpoints will do): the
    watch's session (services.dashboard.watch) keeps zenoh's defaults.
    """
    import time

    import zenoh

    from shared.bus import zenoh_config

    try:
        conf = zenoh_config(settings)
    except ValueError as exc:  # a file named by AESOP_ZENOH_* that cannot be read
        raise CliError(str(exc)) from None
    endpoints = json.loads(conf.get_json("connect/endpoints"))
    if not endpoints:
        return  # nothing to join: a peer that others connect to
    deadline = time.monotonic() + JOIN_TIMEOUT_S
    why = "no router or peer connected"
    try:
        with zenoh.open(conf) as session:  # a client that is refused raises here
            while not (list(session.info.routers_zid()) or list(session.info.peers_zid())):
                if time.monotonic() >= deadline:
                    break
                time.sleep(0.05)
            else:
                return
    except zenoh.ZError as exc:
        why = str(exc).split(" at /")[0].rstrip(". ")
    user = (f"as user {settings.zenoh_user}" if settings.zenoh_user is not None
            else "with no user (AESOP_ZENOH_USER unset)")
    raise CliError(
        f"cannot join the Zenoh network {user}: the router at {', '.join(endpoints)} refused "
        f"this session or did not answer within {JOIN_TIMEOUT_S:g} s ({why}). aesop up's "
        f"router lets in only its own users; log in as the read-only user monitor, as "
        f"aesop up prints: {LOGIN} aesop watch --connect ...")
