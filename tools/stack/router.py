"""The Zenoh hub of ``aesop up``: a session in router mode on a loopback endpoint.

The ``eclipse-zenoh`` wheel ships no ``zenohd``; this process stands in for it.
Every service of the stack is a client that connects here, with multicast
scouting off, so nothing leaves the machine. With ``--users`` every session must
authenticate (a ``user:password`` dictionary) and the access-control list of
:mod:`.acl` applies (``--robot`` names the robots it lets publish observations,
``--ros2`` the ROS 2 bridge's config whose topics the ``ros2`` user may use);
a message past ``--max-message-bytes`` is dropped, and observations past
``--max-observation-hz`` per session. It serves until SIGINT/SIGTERM, with a larger share
of a busy machine's cores where allowed (:func:`shared.realtime.favoured`).

    python -m tools.stack.router --listen tcp/127.0.0.1:7447 \
        --users aesop-data/zenoh/users.txt --robot robot0
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

import zenoh

from services.ros2.config import BridgeConfig, ConfigError, load_config
from shared.realtime import favoured

from .acl import MAX_MESSAGE_BYTES, MAX_OBSERVATION_HZ, rate_cap, size_cap, stack_acl


def hub_config(listen: str, *, users: Path | None = None, robots: Sequence[str] = (),
               ros2: BridgeConfig | None = None,
               max_message_bytes: int = MAX_MESSAGE_BYTES,
               max_observation_hz: float = MAX_OBSERVATION_HZ) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("router"))
    conf.insert_json5("listen/endpoints", json.dumps([listen]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("low_pass_filter", json.dumps(size_cap(max_message_bytes)))
    conf.insert_json5("downsampling", json.dumps(rate_cap(max_observation_hz)))
    if users is not None:
        conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users)))
        conf.insert_json5("access_control", json.dumps(stack_acl(robots, ros2)))
    return conf


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="aesop-hub", description=__doc__.splitlines()[0])
    parser.add_argument("--listen", required=True, help="endpoint, e.g. tcp/127.0.0.1:7447")
    parser.add_argument("--users", type=Path,
                        help="user:password dictionary: authenticate every session and "
                             "apply the stack's access-control list")
    parser.add_argument("--robot", action="append", default=[],
                        help="a robot whose user may publish its observations (repeat)")
    parser.add_argument("--ros2", type=Path, default=None, metavar="CONFIG",
                        help="the ROS 2 bridge's config: its user may use those ROS topics")
    parser.add_argument("--max-message-bytes", type=int, default=MAX_MESSAGE_BYTES)
    parser.add_argument("--max-observation-hz", type=float, default=MAX_OBSERVATION_HZ,
                        help="observations per second passed on from each session")
    args = parser.parse_args(argv)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        ros2 = None if args.ros2 is None else load_config(args.ros2)
    except ConfigError as exc:
        print(f"hub: {exc}", file=sys.stderr)
        return 2
    favoured()  # every message of the stack passes here: its threads inherit the share
    try:
        session = zenoh.open(hub_config(args.listen, users=args.users, robots=args.robot,
                                        ros2=ros2,
                                        max_message_bytes=args.max_message_bytes,
                                        max_observation_hz=args.max_observation_hz))
    except zenoh.ZError as exc:
        print(f"hub: cannot listen on {args.listen}: {exc}", file=sys.stderr)
        return 2
    guard = (f"users from {args.users}, access control for robots {', '.join(args.robot)}"
             + (f" and the ROS 2 topics of {args.ros2}" if ros2 is not None else "")
             if args.users else "no authentication")
    print(f"zenoh router {session.zid()} listening on {args.listen} ({guard}; messages "
          f"up to {args.max_message_bytes} bytes)", file=sys.stderr, flush=True)
    try:
        stop.wait()
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
