"""Who may do what on the stack's Zenoh router: users, and the access-control list.

Every session authenticates, by user name and password (Zenoh ``usrpwd``: ``aesop up`` on
one machine, compose) or by a certificate of the stack's CA (mutual TLS: ``aesop up --role
server``, :mod:`.certs`); the router's ACL then allows, per subject, only what that part of
the stack does (docs/architecture.md, "Zenoh key expressions"). Everything else is denied:

- everyone may subscribe to ``aesop/**`` (messages, liveliness) and learns of every
  subscriber and health token; the services and ``monitor`` receive every robot's messages,
  a robot's sessions only their own robot's (``aesop/<id>/**``);
- each service may publish only its own keys (its events on ``aesop/*/event/<service>``)
  and declare only its own health token;
- a robot's control loop ``control-<id>`` may publish only its own robot's plan, state,
  regions, requests, events and set-points, and ask its own vehicle's clock;
- a robot ``robot-<id>`` (its vehicle, its camera) may publish only its own observations,
  events and vehicle state (``aesop/<id>/observation``, ``aesop/<id>/event/robot``,
  ``aesop/<id>/vehicle/state``, a simulator's ``aesop/<id>/vehicle/truth``), answer
  queries of its own clock and reset (``aesop/<id>/vehicle/clock``, ``.../vehicle/reset``),
  ask its own reset (``aesop demo``, as the robot's camera) and declare a vehicle's health
  token (``aesop/health/sim`` or ``aesop/health/vehicle``); so no user may put two robots'
  vehicle keys;
- a robot linked through a router of its own (``aesop up --role robot``) is one subject
  ``robot-<id>`` at the server: what its control loop, vehicle and ROS 2 bridge may do;
- ``monitor`` (``aesop watch``, a recorder) only reads;
- ``ros2`` (the ROS 2 robot's rmw_zenoh sessions on one machine), when a bridge config is
  given: the ROS keys of its domain and mapped topics (data keys of any type, rmw_zenoh's
  ``@adv`` keys under them, the graph's ``@ros2_lv/<domain>/**`` tokens) both ways, and
  none of the stack's keys: a ROS node reaches the stack only through the bridge's checks;
- ``ros2-bridge`` (``aesop ros2``, the bridge): the same ROS keys, and of the stack's keys
  only its robot's inputs (observations, vehicle state, its events), its robot's keys to
  receive and its health token.

The router also passes on at most ``max_observation_hz`` observations per second
from each session (its ``downsampling``), so a robot flooding its own key loads the
network and the detector no more than a robot at that rate.

An ACL is enforced on what passes through the router, so sessions must be clients
of it (``AESOP_ZENOH_MODE=client``): peers would open direct links around it. A
message larger than ``max_message_bytes`` is dropped by the router.
"""

from __future__ import annotations

import json
import os
import secrets
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

from services.ros2 import wire
from services.ros2.config import BridgeConfig
from shared import topics

ALL = "aesop/**"
HEALTH = "aesop/health/**"
Identity = Literal["usrpwd", "tls"]  # how the router knows a session: user name, or certificate
# what each service puts, for every robot (its robot-wide keys)
SERVICE_PUTS: Mapping[str, tuple[str, ...]] = {
    "embedding": ("aesop/*/anomaly", "aesop/*/event/embedding"),
    "reasoner": ("aesop/*/reasoner/decision", "aesop/*/event/reasoner"),
    "dashboard": ("aesop/*/event/dashboard",),
}
# what a robot's control loop (``control-<id>``) and vehicle (``robot-<id>``) put, under
# ``aesop/<id>/``: their own robot's keys and no other's
CONTROL_PUTS = ("state", "plan", "reasoner/request", "regions", "event/control",
                "vehicle/setpoint")
ROBOT_PUTS = ("observation", f"event/{topics.ROBOT_SOURCE}", "vehicle/state", "vehicle/truth")
CONTROL = "control"  # the control loops' health token and the stem of their users
MONITOR = "monitor"
MAX_MESSAGE_BYTES = 1024 * 1024  # the largest message the router passes on
# observations per second the router passes on from one session (a robot): a floor of
# 20 ms between two, twice the detector's own per-robot rate (AESOP_EMBEDDING_LIMITS__
# ROBOT_HZ, 25, a token bucket that lets a second's burst through), so a flood is cut
# before it crosses the network and a camera's jitter is not
MAX_OBSERVATION_HZ = 50.0


def robot_user(robot: str) -> str:
    """The user a robot's session authenticates as (its vehicle, its camera); with
    certificates, also the robot's own router linked to the server."""
    return f"robot-{robot}"


def control_user(robot: str) -> str:
    """The user of ``robot``'s control loop: it may put that robot's keys only."""
    return f"{CONTROL}-{robot}"


def users_of(robots: Iterable[str], *, ros2: bool = False) -> list[str]:
    robots = list(robots)
    return [*SERVICE_PUTS, MONITOR, *(control_user(r) for r in robots),
            *(robot_user(r) for r in robots), *([ROS2, ROS2_BRIDGE] if ros2 else [])]


def server_users() -> list[str]:
    """The sessions of a server (``aesop up --role server``): its services and the monitor;
    its robots come linked, each as ``robot-<id>``."""
    return [*SERVICE_PUTS, MONITOR]


def stack_acl(robots: Sequence[str], ros2: BridgeConfig | None = None, *,
              identity: Identity = "usrpwd", linked: Sequence[str] = ()) -> dict[str, Any]:
    """The router's ``access_control`` block: the services, ``monitor``, each robot's
    control loop (``control-<id>``) and vehicle (``robot-<id>``) of ``robots``, the ROS 2
    bridge of ``ros2``, and the ``linked`` robots, each reaching this router through a
    router of its own (``aesop up --role robot``) as one subject ``robot-<id>`` that may do
    what its control loop, vehicle and bridge do, for itself. A rule names its message kinds
    and the flows as the router sees them (ingress from a session, egress to it).

    ``identity``: subjects are user names (``usrpwd``), or certificates' common names
    (``tls``: mutual TLS, each session presenting a certificate of the stack's CA).
    Everyone may declare subscribers and liveliness subscribers on ``aesop/**`` and learns of
    every subscriber and health token; the services and the monitor receive every robot's
    messages, a robot's sessions only their own robot's."""
    rules: list[dict[str, Any]] = [
        _rule("subscribe", "ingress", ["declare_subscriber", "declare_liveliness_subscriber",
                                       "liveliness_query"], [ALL]),
        # subscriber declarations must reach the publishers too: a session drops a
        # put for which it knows no subscriber
        _rule("announce", "egress", ["declare_subscriber", "liveliness_token"], [ALL]),
        _rule("receive", "egress", ["put", "delete"], [ALL]),
    ]
    readers = [*SERVICE_PUTS, MONITOR]
    users = list(dict.fromkeys([
        *readers, *(u for r in robots for u in (control_user(r), robot_user(r))),
        *([ROS2, ROS2_BRIDGE] if ros2 is not None else []), *map(robot_user, linked)]))
    policies: list[dict[str, Any]] = [
        {"id": "everyone", "rules": ["subscribe", "announce"], "subjects": users},
        {"id": "readers", "rules": ["receive"], "subjects": readers}]
    for service, keys in SERVICE_PUTS.items():
        # a detector replica also announces itself as one of the replicas (its own name)
        health = [f"aesop/health/{service}", *([f"aesop/health/{service}/*"]
                                               if service == "embedding" else [])]
        rules += [_rule(f"{service}-puts", "ingress", ["put", "delete"], list(keys)),
                  _rule(f"{service}-health", "ingress", ["liveliness_token"], health)]
        policies.append({"id": service, "rules": [f"{service}-puts", f"{service}-health"],
                         "subjects": [service]})
    for robot in dict.fromkeys([*robots, *linked]):
        control, vehicle, shared = _robot_rules(robot)
        rules += [*control, *vehicle, *shared]
        control_ids, vehicle_ids, shared_ids = ([r["id"] for r in group]
                                                for group in (control, vehicle, shared))
        if robot in robots:
            policies += [{"id": control_user(robot), "rules": [*control_ids, *shared_ids],
                          "subjects": [control_user(robot)]},
                         {"id": robot_user(robot), "rules": [*vehicle_ids, *shared_ids],
                          "subjects": [robot_user(robot)]}]
        if robot in linked:  # its router: the robot's loop, vehicle and bridge, as one
            rules.append(_rule(f"{robot}-bridge", "ingress", ["put", "delete"],
                               [f"aesop/{robot}/event/{ROS2}"]))
            policies.append({"id": f"{robot}-linked",
                             "rules": [*control_ids, *vehicle_ids, *shared_ids,
                                       f"{robot}-bridge", "ros2-health"],
                             "subjects": [robot_user(robot)]})
    if linked:
        rules.append(_rule("ros2-health", "ingress", ["liveliness_token"],
                           [f"aesop/health/{ROS2}"]))
    if ros2 is not None:
        ros_rules, ros_policies = ros2_acl(ros2)
        rules += [r for r in ros_rules if r["id"] not in {x["id"] for x in rules}]
        policies += ros_policies
    field = "usernames" if identity == "usrpwd" else "cert_common_names"
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [{"id": user, field: [user]} for user in users],
        "policies": policies,
    }


def _robot_rules(robot: str) -> tuple[list[dict[str, Any]], ...]:
    """One robot's rules: what its control loop and its vehicle may put (each its own
    list), and what both share: the clock query between them (control asks, the vehicle
    answers) and what its sessions receive."""
    control, vehicle, mine = control_user(robot), robot_user(robot), f"aesop/{robot}"
    clock, reset = topics.vehicle_clock(robot), topics.vehicle_reset(robot)
    return ([_rule(f"{control}-puts", "ingress", ["put", "delete"],
                   [f"{mine}/{key}" for key in CONTROL_PUTS]),
             _rule(f"{control}-ask", "ingress", ["query"], [clock]),
             _rule(f"{control}-health", "ingress", ["liveliness_token"],
                   [topics.health(CONTROL)])],
            [_rule(f"{vehicle}-puts", "ingress", ["put", "delete"],
                   [f"{mine}/{key}" for key in ROBOT_PUTS]),
             _rule(f"{vehicle}-answer", "ingress", ["declare_queryable", "reply"],
                   [clock, reset]),
             _rule(f"{vehicle}-ask", "ingress", ["query"], [reset]),
             _rule(f"{vehicle}-health", "ingress", ["liveliness_token"],
                   ["aesop/health/sim", "aesop/health/vehicle"])],
            [_rule(f"{robot}-receive", "egress", ["put", "delete"], [f"{mine}/**"]),
             _rule(f"{robot}-clock", "egress", ["query", "reply", "declare_queryable"],
                   [clock, reset])])


ROS2 = "ros2"  # the user of the robot's rmw_zenoh sessions (and the bridge's service name)
ROS2_BRIDGE = "ros2-bridge"  # the user of the ROS 2 bridge
ROS_MESSAGES = ["put", "delete", "declare_subscriber", "declare_queryable", "query", "reply",
                "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"]


def ros_keys(config: BridgeConfig) -> list[str]:
    """The ROS keys of ``config``'s topics: every data key (any type and hash, so the
    bridge sees and refuses a wrong one), rmw_zenoh's advanced pub/sub keys under them,
    and the domain's graph tokens."""
    domain = config.domain_id
    keys = []
    for mapped in config.topics():
        data = wire.topic_keys(domain, mapped.name)
        keys += [data, f"{data}/@adv/**"]
    return [*keys, f"{wire.LIVELINESS}/{domain}/**"]


def ros2_session_config(endpoint: str, password: str) -> str:
    """A Zenoh session config for the ROS 2 robot's rmw_zenoh nodes on one machine
    (``ZENOH_SESSION_CONFIG_URI``): rmw_zenoh's own default (timestamping, its timeouts and
    lease: the file replaces it whole) with three changes: a client of the hub at
    ``endpoint``, as the ``ros2`` user (the password inline: keep the file private; logging
    in needs rmw_zenoh jazzy 0.2.6, kilted 0.6.3, rolling 0.8.2 or later)."""
    config = wire.session_config({
        "mode": "client", "connect": {"endpoints": [endpoint]},
        "transport": {"auth": {"usrpwd": {"user": ROS2, "password": password}}}})
    return ("// rmw_zenoh's session config for the robot's nodes, written by aesop up --ros2:\n"
            "// its DEFAULT_RMW_ZENOH_SESSION_CONFIG (jazzy 0.2.10), a client of the hub as\n"
            "// the ros2 user; export ZENOH_SESSION_CONFIG_URI=<this file>\n"
            + json.dumps(config, indent=2) + "\n")


def ros2_acl(config: BridgeConfig) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The rules and the policies of the ``ros2`` user (the robot's nodes: the ROS keys both
    ways) and of the bridge's ``ros2-bridge`` (the same, and its robot's inputs, its robot's
    keys to receive and its health token)."""
    robot, keys = config.robot, ros_keys(config)
    rules = [
        _rule("ros2-ros-in", "ingress", ROS_MESSAGES, keys),
        _rule("ros2-ros-out", "egress", ROS_MESSAGES, keys),
        _rule("ros2-puts", "ingress", ["put", "delete"],
              [f"aesop/{robot}/observation", f"aesop/{robot}/vehicle/state",
               f"aesop/{robot}/event/{ROS2}"]),
        _rule("ros2-health", "ingress", ["liveliness_token"], [f"aesop/health/{ROS2}"]),
    ]
    ros = ["ros2-ros-in", "ros2-ros-out"]
    policies = [{"id": ROS2, "rules": ros, "subjects": [ROS2]},
                {"id": ROS2_BRIDGE, "rules": [*ros, "ros2-puts", "ros2-health",
                                              f"{robot}-receive"], "subjects": [ROS2_BRIDGE]}]
    return rules, policies


def size_cap(max_message_bytes: int = MAX_MESSAGE_BYTES) -> list[dict[str, Any]]:
    """The router's ``low_pass_filter``: drop what a session sends past the size."""
    return [{"id": "size-cap", "flows": ["ingress"],
             "messages": ["put", "delete", "query", "reply"], "key_exprs": [ALL],
             "size_limit": max_message_bytes}]


def rate_cap(max_observation_hz: float = MAX_OBSERVATION_HZ) -> list[dict[str, Any]]:
    """The router's ``downsampling``: observations from each session (it keeps a
    window per session and rule) at most this often; the rest are dropped."""
    return [{"id": "observation-rate", "flows": ["ingress"], "messages": ["put"],
             "rules": [{"key_expr": "aesop/*/observation", "freq": max_observation_hz}]}]


def new_passwords(users: Iterable[str]) -> dict[str, str]:
    return {user: secrets.token_urlsafe(24) for user in users}


def write_credentials(folder: Path, passwords: Mapping[str, str]) -> Path:
    """The router's dictionary ``users.txt`` (``user:password`` per line) and
    ``<user>.password`` for each session, all 0600 in ``folder`` (0700); returns the
    dictionary's path."""
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    folder.chmod(0o700)
    users = folder / "users.txt"
    write_private(users, "".join(f"{u}:{p}\n" for u, p in passwords.items()))
    for user, password in passwords.items():
        write_private(folder / f"{user}.password", password + "\n")
    return users


def write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` readable by the owner only (:func:`write_file`, 0600)."""
    write_file(path, text.encode(), 0o600)


def write_file(path: Path, data: bytes, mode: int) -> None:
    """Write ``data`` to ``path`` with ``mode``: a new file (``O_EXCL``, so never through a
    link) renamed over the old one, whose mode is not kept; a reader never sees half of it."""
    fresh = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fresh.unlink(missing_ok=True)
    fd = os.open(fresh, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, mode)
    with os.fdopen(fd, "wb") as f:
        os.fchmod(f.fileno(), mode)
        f.write(data)
    os.replace(fresh, path)


def _rule(rule_id: str, flow: str, messages: list[str], keys: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages,
            "key_exprs": keys}


ROUTER_HEADER = """\
// The Zenoh router of the compose stack (the eclipse-zenoh wheel's router in the stack's
// image, `python -m tools.stack.router --config`, or eclipse/zenoh of the wheel's
// version). Written by `aesop zenoh router-config --robot robot0 --ros2
// deploy/ros2/quadrotor.yaml`, from the same code as the ACL of `aesop up`'s hub
// (tools/stack/acl.py): regenerate it, do not edit it. Every session authenticates
// (user:password, the dictionary is the compose secret zenoh-users, made by `aesop zenoh
// credentials deploy/secrets`); each service may publish only its own keys, robot-<id>
// only its own observations, events and vehicle state (answer its clock and reset), ros2 (the
// robot's rmw_zenoh nodes) the mapped ROS topics only, ros2-bridge those and its robot's
// inputs, monitor only reads; a message past the size limit is dropped, and observations
// past the rate per session. See deploy/README.md.
"""


def router_config_text(robots: Sequence[str], *, ros2: BridgeConfig | None = None,
                       listen: str = "tcp/[::]:7447",
                       users_file: str = "/run/secrets/zenoh-users",
                       max_message_bytes: int = MAX_MESSAGE_BYTES,
                       max_observation_hz: float = MAX_OBSERVATION_HZ) -> str:
    """A router config file (JSON5: a comment, then JSON) with the stack's ACL."""
    config = {
        "mode": "router",
        "listen": {"endpoints": [listen]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"dictionary_file": users_file}}},
        "access_control": stack_acl(robots, ros2),
        "low_pass_filter": size_cap(max_message_bytes),
        "downsampling": rate_cap(max_observation_hz),
    }
    return ROUTER_HEADER + json.dumps(config, indent=2) + "\n"
