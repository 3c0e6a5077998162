"""The Zenoh hub of ``aesop up``: a session in router mode on a loopback endpoint.

The ``eclipse-zenoh`` wheel ships no ``zenohd``; this process stands in for it.
Every service of the stack is a peer that connects here, with multicast
scouting off, so nothing leaves the machine. It serves until SIGINT/SIGTERM.

    python -m services.stack.hub --listen tcp/127.0.0.1:7447
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading

import zenoh


def hub_config(listen: str) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("router"))
    conf.insert_json5("listen/endpoints", json.dumps([listen]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="aesop-hub", description=__doc__.splitlines()[0])
    parser.add_argument("--listen", required=True, help="endpoint, e.g. tcp/127.0.0.1:7447")
    args = parser.parse_args(argv)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        session = zenoh.open(hub_config(args.listen))
    except zenoh.ZError as exc:
        print(f"hub: cannot listen on {args.listen}: {exc}", file=sys.stderr)
        return 2
    print(f"zenoh router {session.zid()} listening on {args.listen}", file=sys.stderr, flush=True)
    try:
        stop.wait()
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
