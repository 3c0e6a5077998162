"""The Zenoh routers of ``aesop up``: a session in router mode, in one of three roles.

The ``eclipse-zenoh`` wheel ships no ``zenohd``; this process stands in for it.

* ``hub`` (one machine): on a loopback endpoint; with ``--users`` every session must
  authenticate (a ``user:password`` dictionary) and the access-control list of :mod:`.acl`
  applies (``--robot`` names the robots whose control loop and vehicle may publish their
  keys, ``--ros2`` the ROS 2 bridge's config whose topics the ``ros2`` user may use).
* ``server`` (``aesop up --role server``): listens for robots on ``tls/`` endpoints with
  mutual TLS (``--tls DIR``: the stack's CA, the router's certificate and key, as
  ``aesop zenoh certs`` makes them); every session presents a certificate of that CA, the
  ACL knows it by its common name, and each ``--linked`` robot's own router is one subject,
  ``robot-<id>``, that may publish that robot's keys only.
* ``robot`` (``aesop up --role robot``): the robot's own router, as rmw_zenohd is to a ROS 2
  robot: it listens on the robot's loopback with no authentication (the robot's control
  loop, its vehicle or bridge and its ROS 2 nodes, with rmw_zenoh's default session config,
  are its clients or peers), timestamps what it routes, and links to the server
  (``--connect tls/HOST:PORT``) with the robot's certificate (``--tls DIR``: the folder
  ``aesop zenoh certs`` made for this robot), again and again while the link is down: the
  robot's local traffic stays local, and only what the server subscribes to and its ACL
  lets in crosses.

``--config FILE`` serves a zenohd config file as it is instead (docker compose's
``deploy/zenoh/router.json5``, which :mod:`.acl` writes): the router ``zenohd`` would be, from
the stack's own image.

With an ACL, a message past ``--max-message-bytes`` is dropped, and observations past
``--max-observation-hz`` per session. It serves until SIGINT/SIGTERM, with a larger share
of a busy machine's cores where allowed (:func:`shared.realtime.favoured`).

    python -m tools.stack.router --listen tcp/127.0.0.1:7447 \
        --users aesop-data/zenoh/users.txt --robot robot0
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import zenoh

from services.ros2.config import BridgeConfig, ConfigError, load_config
from shared.bus import RECONNECT
from shared.process import stop_on
from shared.realtime import favoured

from .acl import (
    MAX_MESSAGE_BYTES,
    MAX_OBSERVATION_HZ,
    rate_cap,
    robot_user,
    size_cap,
    stack_acl,
)
from .certs import ROUTER, load_identity

ROLES = ("hub", "server", "robot")


def _config(values: Mapping[str, Any]) -> zenoh.Config:
    conf = zenoh.Config()
    for key, value in values.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def _common(listen: Sequence[str]) -> dict[str, Any]:
    return {"mode": "router", "listen/endpoints": list(listen),
            "scouting/multicast/enabled": False}


def _guards(max_message_bytes: int, max_observation_hz: float) -> dict[str, Any]:
    return {"low_pass_filter": size_cap(max_message_bytes),
            "downsampling": rate_cap(max_observation_hz)}


def hub_config(listen: str, *, users: Path | None = None, robots: Sequence[str] = (),
               ros2: BridgeConfig | None = None,
               max_message_bytes: int = MAX_MESSAGE_BYTES,
               max_observation_hz: float = MAX_OBSERVATION_HZ) -> zenoh.Config:
    values = {**_common([listen]), **_guards(max_message_bytes, max_observation_hz)}
    if users is not None:
        values |= {"transport/auth/usrpwd/dictionary_file": str(users),
                   "access_control": stack_acl(robots, ros2)}
    return _config(values)


def server_config(listen: Sequence[str], tls: Path, *, linked: Sequence[str],
                  max_message_bytes: int = MAX_MESSAGE_BYTES,
                  max_observation_hz: float = MAX_OBSERVATION_HZ) -> zenoh.Config:
    """The server's router: mutual TLS on ``listen``, identities by certificate."""
    ca, cert, key = load_identity(tls, ROUTER)
    return _config({
        **_common(listen), **_guards(max_message_bytes, max_observation_hz),
        "transport/link/tls": {"root_ca_certificate": str(ca), "listen_certificate": str(cert),
                               "listen_private_key": str(key), "enable_mtls": True},
        "access_control": stack_acl((), identity="tls", linked=linked)})


def robot_config(listen: Sequence[str], connect: Sequence[str], tls: Path, robot: str
                 ) -> zenoh.Config:
    """A robot's own router: open on its loopback, linked to the server over mutual TLS
    with the robot's certificate; it starts whether or not the server answers, and tries
    the link again within a second of losing it."""
    ca, cert, key = load_identity(tls, robot_user(robot))
    return _config({
        **_common(listen),
        "connect/endpoints": list(connect),
        "connect/timeout_ms": {"router": 0},
        "connect/exit_on_failure": {"router": False},
        "connect/retry": RECONNECT,
        # as rmw_zenohd: ROS 2 publishers that keep history (TRANSIENT_LOCAL) need it
        "timestamping/enabled": {"router": True},
        "transport/link/tls": {"root_ca_certificate": str(ca), "connect_certificate": str(cert),
                               "connect_private_key": str(key), "enable_mtls": True}})


def default_listen(port: int) -> list[str]:
    """Where a server's router listens for robots unless told: every address, IPv6 and
    IPv4 where the host has IPv6, else every IPv4 address."""
    return [f"tls/[::]:{port}" if _has_ipv6_any() else f"tls/0.0.0.0:{port}"]


def usable(endpoints: Sequence[str]) -> list[str]:
    """``endpoints`` less the IPv6 loopback ones where this host has no ``::1`` (a network
    namespace or a kernel without IPv6): the IPv4 one still serves ``localhost``."""
    return [e for e in endpoints if not e.startswith("tcp/[::1]:") or _has_ipv6_loopback()]


def _has_ipv6_loopback() -> bool:
    return _binds("::1")


def _has_ipv6_any() -> bool:
    return _binds("::")


def _binds(address: str) -> bool:
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_STREAM) as sock:
            sock.bind((address, 0))
        return True
    except OSError:
        return False


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="aesop-router", description=__doc__.splitlines()[0])
    parser.add_argument("--role", choices=ROLES, default="hub")
    parser.add_argument("--config", type=Path, default=None, metavar="FILE",
                        help="a zenohd config file served as it is (docker compose's "
                             "deploy/zenoh/router.json5): its listen endpoints, users, ACL")
    parser.add_argument("--listen", action="append", default=[],
                        help="endpoint, e.g. tcp/127.0.0.1:7447 (repeat for more)")
    parser.add_argument("--connect", action="append", default=[],
                        help="robot: the server's endpoint, tls/HOST:PORT")
    parser.add_argument("--tls", type=Path, default=None, metavar="DIR",
                        help="server: the stack's certificates; robot: this robot's folder")
    parser.add_argument("--users", type=Path,
                        help="hub: user:password dictionary: authenticate every session and "
                             "apply the stack's access-control list")
    parser.add_argument("--robot", action="append", default=[],
                        help="hub: a robot whose loop and vehicle may publish its keys; "
                             "robot: this robot (repeat on the hub)")
    parser.add_argument("--linked", action="append", default=[], metavar="ROBOT",
                        help="server: a robot linked through its own router (repeat)")
    parser.add_argument("--ros2", type=Path, default=None, metavar="CONFIG",
                        help="hub: the ROS 2 bridge's config: its user may use those ROS topics")
    parser.add_argument("--max-message-bytes", type=int, default=MAX_MESSAGE_BYTES)
    parser.add_argument("--max-observation-hz", type=float, default=MAX_OBSERVATION_HZ,
                        help="observations per second passed on from each session")
    args = parser.parse_args(argv)
    if args.config is not None and (args.listen or args.role != "hub"):
        parser.error("--config is the whole router: no --listen or --role with it")
    if args.config is None and not args.listen:
        parser.error("--listen (or --config) is required")
    if args.role != "hub" and args.tls is None:
        parser.error(f"--role {args.role} needs --tls DIR")
    if args.role == "robot" and (len(args.robot) != 1 or not args.connect):
        parser.error("--role robot needs one --robot and the server's --connect endpoint")
    if args.role == "hub" and args.config is None and len(args.listen) != 1:
        parser.error("--role hub listens on one --listen endpoint")
    stop = threading.Event()
    stop_on(stop)
    try:
        if args.config is not None:
            conf = zenoh.Config.from_file(args.config)
            endpoints = json.loads(conf.get_json("listen/endpoints"))  # a list, or per mode
            listen = (endpoints if isinstance(endpoints, list)
                      else [e for each in endpoints.values() for e in each])
            guard = f"as {args.config} says"
        else:
            listen = usable(args.listen)
            conf, guard = _role_config(args, listen)
    except zenoh.ZError as exc:
        print(f"router: {args.config}: {exc}", file=sys.stderr)
        return 2
    except (ConfigError, FileNotFoundError) as exc:
        print(f"router: {exc}", file=sys.stderr)
        return 2
    favoured()  # every message of the stack passes here: its threads inherit the share
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        print(f"router: cannot listen on {', '.join(listen)}: {exc}", file=sys.stderr)
        return 2
    limit = "" if args.config else f"; messages up to {args.max_message_bytes} bytes"
    print(f"zenoh router {session.zid()} listening on {', '.join(listen)} ({guard}{limit})",
          file=sys.stderr, flush=True)
    try:
        stop.wait()
    finally:
        session.close()
    return 0


def _role_config(args: argparse.Namespace, listen: list[str]) -> tuple[zenoh.Config, str]:
    """The role's config and what guards it, in words."""
    limits = {"max_message_bytes": args.max_message_bytes,
              "max_observation_hz": args.max_observation_hz}
    if args.role == "server":
        return (server_config(listen, args.tls, linked=args.linked, **limits),
                f"mutual TLS with {args.tls / 'ca.pem'}, access control for linked robots "
                f"{', '.join(args.linked) or 'none'}")
    if args.role == "robot":
        (robot,) = args.robot
        return (robot_config(listen, args.connect, args.tls, robot),
                f"robot {robot}'s own router, linked to {', '.join(args.connect)} over mutual "
                "TLS; open to this robot's local sessions")
    ros2 = None if args.ros2 is None else load_config(args.ros2)
    guard = (f"users from {args.users}, access control for robots {', '.join(args.robot)}"
             + (f" and the ROS 2 topics of {args.ros2}" if ros2 is not None else "")
             if args.users else "no authentication")
    (endpoint,) = listen
    return hub_config(endpoint, users=args.users, robots=args.robot, ros2=ros2,
                      **limits), guard


if __name__ == "__main__":
    sys.exit(main())
