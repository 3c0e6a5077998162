"""``aesop up`` (the whole stack on this machine) and ``aesop zenoh`` (the router's access
control for docker compose)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from tools.commands import CliError, control_scenario, ros2_config


def register(sub: argparse._SubParsersAction) -> None:
    zn = sub.add_parser("zenoh", help="the router's access control for docker compose")
    zsub = zn.add_subparsers(dest="zenoh_command", required=True)
    rc = zsub.add_parser("router-config", help="print the router config (the stack's ACL)")
    rc.add_argument("--robot", action="append", default=None,
                    help="a robot that may publish its observations (repeatable; robot0)")
    rc.add_argument("--ros2", type=Path, default=None, metavar="CONFIG",
                    help="the ROS 2 bridge's config (deploy/ros2/quadrotor.yaml): the ros2 "
                         "user may use its topics")
    rc.set_defaults(func=cmd_zenoh_router_config)
    cr = zsub.add_parser("credentials", help="docker compose's secrets, made anew: a password "
                         "for every Zenoh user (the router's users.txt, <user>.password), "
                         "the admin token (admin-token), PostgreSQL's (postgres.password) and "
                         "the LLM server's key (llm.key), all 0600")
    cr.add_argument("folder", type=Path, help="e.g. deploy/secrets (compose reads it)")
    cr.add_argument("--robot", action="append", default=None,
                    help="a robot to make a user for (repeatable; robot0)")
    cr.add_argument("--owner", type=_owner, default=None, metavar="UID[:GID]",
                    help="chown the files to the containers' user, 10001 (root only): "
                         "compose mounts them with the host's owner and mode")
    cr.set_defaults(func=cmd_zenoh_credentials)
    ce = zsub.add_parser("certs", help="a CA and certificates for mutual TLS between a server "
                         "and its robots (aesop up --role server | robot): DIR/robot-<id>/ "
                         "is what to copy onto each robot")
    ce.add_argument("folder", type=Path, help="e.g. aesop-certs (kept: run it again to add "
                    "a robot; the CA and what it issued stay valid)")
    ce.add_argument("--robot", action="append", default=None,
                    help="a robot to make a certificate for (repeatable; AESOP_ROBOT)")
    ce.add_argument("--server-name", action="append", default=[], metavar="NAME",
                    help="a name or address robots reach the server by (repeatable; its "
                         "certificate also names localhost)")
    ce.add_argument("--ca-cert", type=Path, default=None, help="your CA's certificate "
                    "(with --ca-key): issue from it instead of a CA of the folder's own")
    ce.add_argument("--ca-key", type=Path, default=None, help="your CA's key (read, never "
                    "copied)")
    ce.add_argument("--service", action="append", default=[], metavar="NAME",
                    help="another session's certificate besides the server's services "
                         "(repeatable; compose's control-<robot>, for example)")
    ce.add_argument("--days", type=int, default=825,
                    help="validity of what is issued, in days (default 825)")
    ce.set_defaults(func=cmd_zenoh_certs)
    fc = zsub.add_parser("fleet-compose", help="a docker compose override for a fleet: a "
                         "control loop and simulated vehicle per robot, detector replicas "
                         "on PostgreSQL (deploy/compose.fleet.yml)")
    fc.add_argument("--robots", type=int, default=3, metavar="N",
                    help="robots (ids from AESOP_ROBOT: robot0, robot1, ...; default 3)")
    fc.add_argument("--replicas", type=int, default=1, metavar="M",
                    help="detector replicas; from 2 on with PostgreSQL (default 1)")
    fc.add_argument("--base", type=Path, default=Path("docker-compose.yml"),
                    help="the compose file it adds to (default ./docker-compose.yml)")
    fc.set_defaults(func=cmd_zenoh_fleet_compose)

    up = sub.add_parser("up", help="the whole stack on this machine as processes (Ctrl-C stops)")
    up.add_argument("--data-dir", type=Path, default=Path("aesop-data"),
                    help="one subdirectory per service (default ./aesop-data)")
    up.add_argument("--scenario", type=Path, default=None,
                    help="control scenario: a bundled name (paper, hardware) or a file "
                         "(default: AESOP_CONTROL_SCENARIO or the hardware scene)")
    up.add_argument("--random-ports", action="store_true",
                    help="free ports instead of 7447 (Zenoh) and 8001-8003, 8010, 8080")
    up.add_argument("--no-dashboard", action="store_true",
                    help="start no dashboard (the rest needs none)")
    up.add_argument("--ros2", type=Path, default=None, metavar="CONFIG",
                    help="fly a ROS 2 robot through the bridge (aesop ros2) with this config "
                         "(deploy/ros2/quadrotor.yaml) instead of the simulated vehicle")
    up.add_argument("--vehicle", choices=["sim", "external"], default="sim",
                    help="sim (default): a simulated vehicle per robot (aesop serve sim); "
                         "external: none, each robot's own vehicle joins the bus as "
                         "robot-<id> (the contract: docs/architecture.md 3a)")
    up.add_argument("--role", choices=["all", "server", "robot"], default="all",
                    help="all (default): everything on this machine; server: the router "
                         "robots link to, detectors, reasoner, LLM, dashboard; robot: its own "
                         "router, control loop and vehicle (docs/deployment.md)")
    up.add_argument("--tls", type=Path, default=None, metavar="DIR",
                    help="server: the folder `aesop zenoh certs` made; robot: its "
                         "robot-<id> folder, copied here")
    up.add_argument("--server", default=None, metavar="HOST[:PORT]",
                    help="robot: the server's router (port 7447 unless given)")
    up.add_argument("--robot", action="append", default=None, metavar="ID",
                    help="robot: this robot; server: a robot that links in (repeatable; "
                         "default AESOP_ROBOT)")
    up.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                    help="server: where robots reach its router (default tls/[::]:7447)")
    add_fleet_options(up)
    add_llm_options(up)
    up.set_defaults(func=cmd_up)


def add_fleet_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--robots", type=int, default=1, metavar="N",
                        help="robots flown at once, each with its control loop and simulated "
                             "vehicle (ids from AESOP_ROBOT: robot0, robot1, ...; default 1)")
    parser.add_argument("--replicas", type=int, default=1, metavar="M",
                        help="detector replicas sharing the robots; from 2 on they share a "
                             "PostgreSQL server the stack starts (default 1: SQLite)")


def add_llm_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--llm", choices=["fake", "local"], default=None,
                        help="the LLM the stack serves: the fake one (default, unless "
                             "AESOP_REASONER_LLM_BASE_URL names a server), or local: a trained "
                             "model (SmolLM2-135M-Instruct, installed by `make llama`) on "
                             "llama.cpp's server")
    parser.add_argument("--llm-model", type=Path, default=None, metavar="FILE",
                        help="a GGUF file for --llm local (implies it)")


def local_model(args: argparse.Namespace):
    """The model ``--llm local`` / ``--llm-model`` ask for (None: not local)."""
    from tools.local_llm import LocalModelError, bundled_model, model_file

    llm, path = getattr(args, "llm", None), getattr(args, "llm_model", None)
    if path is None and llm != "local":
        return None
    if llm == "fake":
        raise CliError("--llm-model serves a model with --llm local, not with --llm fake")
    if "AESOP_REASONER_LLM_BASE_URL" in os.environ:
        raise CliError("--llm local and AESOP_REASONER_LLM_BASE_URL both name the LLM: "
                       "unset the variable, or leave out --llm")
    try:
        return model_file(path) if path else bundled_model()
    except LocalModelError as exc:
        raise CliError(str(exc)) from None


def cmd_zenoh_router_config(args: argparse.Namespace) -> int:
    from tools.stack.acl import router_config_text

    ros2 = None if args.ros2 is None else ros2_config(args.ros2)
    print(router_config_text(args.robot or ["robot0"], ros2=ros2), end="")
    return 0


def cmd_zenoh_fleet_compose(args: argparse.Namespace) -> int:
    import yaml

    from shared.settings import BusSettings
    from tools.stack.compose import fleet_override_text
    from tools.stack.up import fleet

    if args.robots < 1 or args.replicas < 1:
        raise CliError("--robots and --replicas count from 1")
    try:
        base = yaml.safe_load(args.base.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise CliError(f"cannot read the compose file {args.base}: {exc}") from None
    if not isinstance(base, dict) or not {"control", "sim", "embedding"} <= set(
            base.get("services") or {}):
        raise CliError(f"{args.base} is not the stack's compose file (no control, sim and "
                       "embedding services)")
    print(fleet_override_text(base, fleet(BusSettings().robot, args.robots), args.replicas),
          end="")
    return 0


def cmd_zenoh_certs(args: argparse.Namespace) -> int:
    from shared.settings import BusSettings
    from tools.stack.acl import server_users
    from tools.stack.certs import write_certs

    if (args.ca_cert is None) != (args.ca_key is None):
        raise CliError("--ca-cert and --ca-key go together")
    robots = args.robot or [BusSettings().robot]
    try:
        layout = write_certs(args.folder, robots=robots,
                             services=list(dict.fromkeys([*server_users(), *args.service])),
                             server_names=args.server_name, ca_cert=args.ca_cert,
                             ca_key=args.ca_key, days=args.days)
    except (ValueError, OSError) as exc:
        raise CliError(f"aesop zenoh certs: {exc}") from None
    print(f"{args.folder}: the CA (ca.pem; its key ca-key.pem stays here), the server's "
          f"router and services' certificates; for each robot, the folder to copy onto it: "
          + ", ".join(str(layout.robot_folder(r)) for r in robots)
          + (f" (issued now: {', '.join(layout.issued)})" if layout.issued else
             " (all kept: nothing issued)"), file=sys.stderr)
    return 0


def _owner(text: str) -> tuple[int, int]:
    uid, _, gid = text.partition(":")
    if not uid.isdigit() or not (gid or uid).isdigit():
        raise argparse.ArgumentTypeError(f"--owner: {text!r} is not UID or UID:GID (numbers)")
    return int(uid), int(gid or uid)


def cmd_zenoh_credentials(args: argparse.Namespace) -> int:
    from tools.stack.compose import write_secrets

    try:
        users = write_secrets(args.folder, args.robot or ["robot0"], owner=args.owner)
    except PermissionError as exc:
        raise CliError(f"cannot chown the secrets in {args.folder} to {args.owner[0]}: "
                       f"{exc.strerror} (--owner needs root: run it with sudo)"
                       if args.owner else f"cannot write into {args.folder}: {exc}") from None
    except OSError as exc:
        raise CliError(f"cannot write the credentials into {args.folder}: {exc}") from None
    owned = f", owned by {args.owner[0]}:{args.owner[1]}" if args.owner else ""
    print(f"wrote {args.folder}/users.txt (the router's), a password file for each of "
          f"{', '.join(users)}, admin-token, postgres.password and llm.key (0600{owned})",
          file=sys.stderr)
    return 0


def stack_options(args: argparse.Namespace, data_dir: Path):
    import importlib.util

    from services.control.core.scenario import resolve_scenario
    from services.control.settings import ControlSettings
    from shared.settings import BusSettings
    from tools.stack.up import (
        DataDirInUse,
        Ports,
        StackOptions,
        child_names,
        data_dir_holder,
        fleet,
        hardware_scenario,
        loop_rate,
    )

    control = ControlSettings()  # what the environment asks of the control loop
    scenario_path = resolve_scenario(args.scenario or control.scenario or hardware_scenario())
    scenario = control_scenario(scenario_path)
    role = getattr(args, "role", "all")
    dashboard = not getattr(args, "no_dashboard", False) and role != "robot"
    if dashboard and importlib.util.find_spec("services.dashboard") is None:
        print("aesop: the dashboard is not in this checkout (services/dashboard): starting "
              "without it", file=sys.stderr)
        dashboard = False
    robots, replicas = getattr(args, "robots", 1), getattr(args, "replicas", 1)
    if robots < 1 or replicas < 1:
        raise CliError("--robots and --replicas count from 1")
    names = child_names(fleet(BusSettings().robot, robots), replicas)
    more = [n for kind in names.values() for n in kind[1:]]
    # refused before anything is written or loaded: a data dir another stack holds (its
    # passwords and token would be rewritten under it), then a port in use
    holder = data_dir_holder(data_dir)
    if holder is not None:
        raise CliError(str(DataDirInUse(data_dir, holder, _data_dir_flag(args))))
    ports = Ports.free(more) if args.random_ports else Ports()
    busy = ports.busy(_used_ports(role))
    if busy:
        raise CliError(f"ports already in use on this machine: {', '.join(busy)} (is another "
                       "`aesop up` running?); stop it, or pass --random-ports (free ports for "
                       "every service); nothing was started")
    rate = None if control.rate_hz is not None else loop_rate(1.0 / scenario.dt, robots)
    ros2 = getattr(args, "ros2", None)
    if ros2 is not None:
        ros2_config(ros2)  # a bad file stops here, naming the field
        ros2 = ros2.resolve()
    return StackOptions(data_dir=data_dir, ports=ports, scenario=scenario_path.resolve(),
                        rate_hz=rate, dashboard=dashboard, local_model=local_model(args),
                        ros2=ros2, robots=robots, replicas=replicas,
                        vehicle=getattr(args, "vehicle", "sim"),
                        **_role_options(args, role, ports.hub))


def _data_dir_flag(args: argparse.Namespace) -> str:
    """The option that picks the data dir: ``aesop demo`` keeps it under its --out."""
    return "--out" if getattr(args, "command", None) == "demo" else "--data-dir"


def _used_ports(role: str) -> tuple[str, ...] | None:
    """The ports a role listens on (None: all of them)."""
    return {"robot": ("hub", "control", "sim"),
            "server": ("hub", "embedding", "reasoner", "dashboard", "fake_llm", "postgres")
            }.get(role)


def _role_options(args: argparse.Namespace, role: str, port: int) -> dict:
    """What ``--role server`` and ``--role robot`` add, checked: the certificates are there
    (a missing one named with the command that makes it), the server's address parses."""
    from tools.stack.acl import robot_user, server_users
    from tools.stack.certs import ROUTER, load_identity
    from tools.stack.router import default_listen

    robot_ids = getattr(args, "robot", None) or []
    tls, server, listen = getattr(args, "tls", None), getattr(args, "server", None), \
        getattr(args, "listen", None)
    if role == "all":
        if tls or server or listen or robot_ids:
            raise CliError("--tls, --server, --listen and --robot go with --role server or "
                           "--role robot")
        return {}
    if tls is None:
        raise CliError(f"--role {role} needs --tls DIR: the certificates `aesop zenoh certs` "
                       "made (docs/deployment.md)")
    try:
        if role == "robot":
            if len(robot_ids) > 1 or server is None or listen:
                raise CliError("--role robot flies one --robot and needs --server HOST[:PORT] "
                               "(no --listen: its router is open on this machine's loopback)")
            load_identity(tls, robot_user(robot_ids[0] if robot_ids else _env_robot()))
            return {"role": role, "tls": tls.resolve(), "server": _host_port(server)}
        if server is not None:
            raise CliError("--server goes with --role robot")
        for name in (ROUTER, *server_users()):
            load_identity(tls, name)
    except FileNotFoundError as exc:
        raise CliError(str(exc)) from None
    return {"role": role, "tls": tls.resolve(), "linked": tuple(robot_ids),
            "listen": tuple(listen or default_listen(port))}


def _env_robot() -> str:
    from shared.settings import BusSettings

    return BusSettings().robot


def _host_port(server: str, default_port: int = 7447) -> str:
    """``HOST[:PORT]`` as ``host:port`` (an IPv6 address in brackets)."""
    host, sep, port = server.rpartition(":")
    if not sep or host.endswith(":") or (host.startswith("[") != host.endswith("]")):
        host, port = server, str(default_port)  # no port, or a bare IPv6 address
    if ":" in host and not host.startswith("["):
        host = f"[{host}]"
    if not host.strip("[]") or not port.isdigit() or not 0 < int(port) < 65536:
        raise CliError(f"--server {server!r}: give HOST or HOST:PORT")
    return f"{host}:{port}"


def cmd_up(args: argparse.Namespace) -> int:
    from tools.stack.up import PlanError, run_up

    environ = dict(os.environ)
    if getattr(args, "role", "all") == "robot" and args.robot:
        environ["AESOP_ROBOT"] = args.robot[0]
    try:
        return run_up(stack_options(args, args.data_dir.resolve()), environ)
    except PlanError as exc:
        raise CliError(str(exc)) from None
