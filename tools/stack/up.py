"""``aesop up``: the stack as child processes, on one machine or in two roles.

A Zenoh hub (:mod:`tools.stack.router`, router mode on loopback), then the LLM server
(the fake one; with ``--llm local`` llama.cpp's serving a trained GGUF model,
:mod:`tools.local_llm`; none when ``AESOP_REASONER_LLM_BASE_URL`` names a backend), the vector-cache
(embedding), the slow reasoner, the control loop, the simulated quadrotor it flies
(``serve sim``, as the robot's user: a vehicle like any other; with ``--ros2 CONFIG`` the
bridge to a ROS 2 robot instead, ``serve ros2`` as the ``ros2`` user) and the dashboard, all
as ``python -m tools.cli serve ...`` clients of the hub.
Every Zenoh session authenticates to the hub with its own user and a password
generated per start (:mod:`.acl`; kept in ``<data-dir>/zenoh``, 0600), and the hub's
access-control list lets each publish only its own keys.

The same pieces run on two machines (``--role``, docs/deployment.md): ``server`` (its
router listening for robots over mutual TLS, every session with a certificate of the
stack's CA, :mod:`.certs`; the LLM server, the detectors, the reasoner, the dashboard,
PostgreSQL) and ``robot`` (a router of the robot's own, open on its loopback and linked
to the server's; the control loop and the vehicle or bridge, its clients).

* :func:`plan_stack` is pure: environment and options in, the child specs out.
* :class:`Stack` first claims the data directory (an ``flock`` on
  ``<data-dir>/aesop-up.lock``, held for the stack's life: one stack per data directory)
  and checks that every port it will listen on is free, refusing before it writes a
  credential or starts anything; then it starts the children
  (:class:`shared.process.Child`, each in its
  own process group, its output forwarded to a sink: ``[control] ...``), waits
  for every ``/readyz`` (a TCP accept for the hub), and stops them all: SIGTERM
  to every group, SIGKILL to what is left after a grace period, the hub last.
* :func:`run_up` is the command: it generates an admin token when
  ``AESOP_ADMIN_TOKEN`` is unset (kept in a 0600 file, not printed), prints the
  URLs and serves until SIGINT/SIGTERM or until a service dies (a hub or an LLM server
  that dies is started again: meanwhile the services' clients reconnect, and the
  reasoner answers with its fallback).
"""

from __future__ import annotations

import fcntl
import os
import secrets
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from services.control.core.scenario import bundled_path, load_scenario, resolve_scenario
from services.control.settings import ControlSettings
from services.dashboard.settings import DashboardSettings
from services.embedding.settings import EmbeddingSettings
from services.reasoner.settings import ReasonerSettings
from services.ros2.config import ConfigError, load_config
from services.ros2.settings import Ros2Settings
from services.sim.settings import SimSettings
from shared.process import (
    Child,
    ChildSpec,
    ServiceFailed,
    Sink,
    await_ready,
    free_port,
    port_in_use,
    stderr_sink,
    stop_on,
)
from shared.settings import BusSettings, ServiceSettings, read_settings, to_env
from tools.fakes.llm import FakeLLMServiceSettings, FakeLLMSettings
from tools.local_llm import REASONER_SETTINGS, STACK_THREADS, LocalModel, server_argv

from .acl import (
    ROS2,
    ROS2_BRIDGE,
    control_user,
    new_passwords,
    robot_user,
    ros2_session_config,
    users_of,
    write_credentials,
    write_private,
)
from .postgres import PostgresServer

DETECTOR_CACHE = "quadrotor"
LOCAL_LLM = "llm"  # the name of --llm local's server among the children
POSTGRES = "postgres"  # the detector replicas' PostgreSQL server among the children
# children started again when they die, like the hub
# a child that dies is started again (Stack.watch), after a delay doubling from 1 s; one that
# exits more than MAX_RESTARTS times in RESTART_WINDOW_S stops the stack
MAX_RESTARTS = 5
RESTART_WINDOW_S = 60.0
MAX_RESTART_DELAY_S = 30.0
FAKE_LLM_LATENCY_S = 3.1  # the paper's mean GPT-3.5-turbo CoT latency (Table "jetson timings")
# Environment a child must not inherit: each service listens on its own port
# and joins the hub, whatever the calling shell says.


def hardware_scenario() -> Path:
    """The bundled scene of the paper's hardware experiment."""
    return bundled_path("hardware")


@dataclass(frozen=True)
class Ports:
    hub: int = 7447
    embedding: int = 8001  # the first detector replica's
    reasoner: int = 8002
    control: int = 8003  # the first robot's
    dashboard: int = 8080
    fake_llm: int = 8010  # the LLM server the stack starts: the fake, or --llm local's
    sim: int = 8004  # the vehicle's: the simulator, or with --ros2 the bridge to the robot
    postgres: int = 8432  # with --replicas: the detectors' PostgreSQL
    # the ports of the children past the first robot and replica, by child name; one not
    # named here is its kind's port + 100 per robot (or replica) before it
    more: tuple[tuple[str, int], ...] = ()

    @classmethod
    def free(cls, more: Sequence[str] = ()) -> Ports:
        """Distinct free ports: the eight, and one for each child named in ``more``."""
        ports: list[int] = []
        while len(ports) < 8 + len(more):
            port = free_port()
            if port not in ports:
                ports.append(port)
        hub, embedding, reasoner, control, dashboard, llm, sim, postgres = ports[:8]
        return cls(hub, embedding, reasoner, control, dashboard, llm, sim, postgres,
                   more=tuple(zip(more, ports[8:], strict=True)))

    def of(self, child: str, kind: str, index: int) -> int:
        """The port of ``child``, the ``index``-th (0: the first) of its ``kind``."""
        base = int(getattr(self, kind))
        return base if index == 0 else dict(self.more).get(child, base + 100 * index)

    def busy(self, only: Sequence[str] | None = None) -> list[str]:
        """``name:port`` of every port (of those named in ``only``, if given) a service could
        not bind on loopback now: something listens there or holds it bound."""
        out = []
        named = [(k, v) for k, v in vars(self).items() if k != "more"] + list(self.more)
        for name, port in named:
            if only is not None and name not in only:
                continue
            if port_in_use(port):
                out.append(f"{name}:{port}")
        return out


# a fleet's control loops on one machine, unless AESOP_CONTROL_RATE_HZ says otherwise (the
# simulated vehicles then run at half speed): three at the hardware scene's 20 Hz end as
# expected on 2 cores with a third of the margin (state age p99 24 ms of the 150 ms a stale
# state is; at 10 Hz 12 of 300), so a fleet sharing the machine with its detectors keeps 10
FLEET_RATE_HZ = 10.0


def loop_rate(scene_rate_hz: float, robots: int) -> float:
    """The control loops' rate for ``robots`` robots flying a scene made for ``scene_rate_hz``."""
    return scene_rate_hz if robots == 1 else min(scene_rate_hz, FLEET_RATE_HZ)


def fleet(robot: str, n: int) -> tuple[str, ...]:
    """The ids of ``n`` robots named after ``robot`` (itself when alone): its trailing
    number counted on ("robot0" -> robot0, robot1, robot2; "drone" -> drone0, drone1)."""
    if n == 1:
        return (robot,)
    stem = robot.rstrip("0123456789")
    first = int(robot[len(stem):] or 0)
    return tuple(f"{stem}{first + i}" for i in range(n))


def child_names(robots: Sequence[str], replicas: int, *, vehicle: str | None = "sim"
                ) -> dict[str, list[str]]:
    """The children of each kind that come in numbers: the detector replicas, the control
    loops and the vehicles (one of each per robot; ``vehicle``: their kind, ``sim`` or
    ``ros2``, None for vehicles of the robots' own); plain names for one."""
    alone = len(robots) == 1
    names = {"embedding": ["embedding", *(f"embedding-{j + 1}" for j in range(1, replicas))],
             "control": ["control" if alone else f"control-{r}" for r in robots]}
    if vehicle is not None:
        names[vehicle] = [vehicle if alone else f"{vehicle}-{r}" for r in robots]
    return names


def vehicle_kind(options: StackOptions) -> str | None:
    """The child each robot's vehicle is: the simulator, the ROS 2 bridge, or none (an
    external vehicle joins the bus on its own)."""
    if options.ros2 is not None:
        return ROS2
    return "sim" if options.vehicle == "sim" else None


Role = Literal["all", "server", "robot"]
ROBOT_LISTEN = ("tcp/127.0.0.1", "tcp/[::1]")  # a robot's router: open on its loopback only


class PlanError(ValueError):
    """Options that contradict each other or the environment (the message says how)."""


LOCK_FILE = "aesop-up.lock"  # in the data directory: flocked by the stack that uses it


class DataDirInUse(PlanError):
    """Another stack (``aesop up`` or ``aesop demo``, another process) holds the data
    directory."""

    def __init__(self, data_dir: Path, holder: str, flag: str = "--data-dir") -> None:
        super().__init__(f"the data dir {data_dir} is in use by another stack (pid {holder}, "
                         f"`aesop up` or `aesop demo`): stop that one first, or give this one "
                         f"another {flag}; nothing was changed")
        self.data_dir, self.holder = data_dir, holder


def data_dir_holder(data_dir: Path) -> str | None:
    """The pid (as its lock file says) of the process whose stack holds ``data_dir``, or
    None when no stack does. Touches nothing: no folder or file is made or written."""
    try:
        fd = os.open(data_dir / LOCK_FILE, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError:  # none there (nobody ever held it), or not a file we can read
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return os.read(fd, 32).decode(errors="replace").strip() or "unknown"
    finally:
        os.close(fd)  # releases the lock if this probe took it
    return None


class DataDirLock:
    """An exclusive ``flock`` on ``<data_dir>/aesop-up.lock`` while the stack is up, the
    holder's pid in the file (the embedding service's lock on its own folder, one level
    up). The kernel lets it go when the process dies, however it dies; the children do not
    inherit it (the descriptor is closed on exec)."""

    def __init__(self, data_dir: Path) -> None:
        self.data_dir = data_dir
        self.fd: int | None = None

    def acquire(self) -> None:
        """Hold it (again: a no-op), or :class:`DataDirInUse` naming the holder, the data
        directory left as it was."""
        if self.fd is not None:
            return
        self.data_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.data_dir / LOCK_FILE, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise DataDirInUse(self.data_dir, holder) from None
        except BaseException:
            os.close(fd)
            raise
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self.fd = fd

    def release(self) -> None:
        if self.fd is None:
            return
        fd, self.fd = self.fd, None
        try:
            os.ftruncate(fd, 0)  # no pid left behind in a lock nobody holds
        finally:
            os.close(fd)


@dataclass(frozen=True)
class StackOptions:
    data_dir: Path
    ports: Ports = field(default_factory=Ports)
    scenario: Path | None = None  # None: AESOP_CONTROL_SCENARIO, else the hardware scene
    rate_hz: float | None = None  # None: AESOP_CONTROL_RATE_HZ, else the control default
    dashboard: bool = True
    python: str = sys.executable
    local_model: LocalModel | None = None  # served by llama.cpp instead of the fake LLM
    ros2: Path | None = None  # a ROS 2 robot through the bridge with this config, not the sim
    # "external": no vehicle child; each robot's own vehicle joins the bus as robot-<id>
    vehicle: Literal["sim", "external"] = "sim"
    robots: int = 1  # robots flown at once, each with its control loop and simulated vehicle
    replicas: int = 1  # detector replicas; from 2 on they share the stack's PostgreSQL
    # where the parts run (docs/deployment.md): "all" on this machine; "server" (router,
    # detectors, reasoner, LLM, dashboard, PostgreSQL) and "robot" (its own router, its
    # control loop, its vehicle or ROS 2 bridge) on two machines, linked over mutual TLS
    role: Role = "all"
    tls: Path | None = None  # server: the stack's certificates; robot: its own folder of them
    server: str | None = None  # robot: the server's router, host:port
    linked: tuple[str, ...] = ()  # server: the robots that link in (none: AESOP_ROBOT)
    listen: tuple[str, ...] = ()  # server: the router's endpoints (none: tls/[::]:<hub port>)


@dataclass(frozen=True)
class StackPlan:
    hub: ChildSpec
    services: tuple[ChildSpec, ...]
    token: str
    token_generated: bool
    fake_llm: bool
    local_model: LocalModel | None  # the model the stack serves, if any
    robot: str  # the (first) robot the services serve
    scenario: Path  # the scene the control loop flies
    zenoh_dir: Path  # the hub's user dictionary and each user's password file
    data_dir: Path  # the stack's: one subdirectory per service, held while it is up
    passwords: Mapping[str, str] = field(repr=False)  # Zenoh user -> password
    # every robot flown (``robot`` first): its id, its control loop's and vehicle's child
    # ("" for an external vehicle)
    fleet: tuple[tuple[str, str, str], ...] = ()
    postgres: PostgresServer | None = None  # the detector replicas' store, with --replicas
    role: Role = "all"
    tls: Path | None = None  # the certificates the sessions present (server, robot roles)
    endpoint: str = ""  # where this machine's sessions join its router
    server: str | None = None  # robot: the server's router it links to, host:port
    linked: tuple[str, ...] = ()  # server: the robots that link in, each through its router

    def url(self, name: str) -> str | None:
        return next((s.url for s in self.services if s.name == name), None)

    @property
    def robots(self) -> tuple[str, ...]:
        return tuple(robot for robot, _, _ in self.fleet)

    def robot_urls(self, robot: str) -> tuple[str, str | None]:
        """The URLs of ``robot``'s control loop and vehicle (None: an external one)."""
        _, control, vehicle = next(f for f in self.fleet if f[0] == robot)
        url = self.url(control)
        assert url is not None
        return url, self.url(vehicle) if vehicle else None

    @property
    def ros2_session(self) -> Path:
        """With ``--ros2``: the Zenoh session config of the robot's rmw_zenoh nodes."""
        return self.zenoh_dir / "ros2-session.json5"

    def bus_settings(self, user: str, **fields: Any) -> BusSettings:
        """How a session of ``user`` (``monitor``, ``robot-<id>``, a service) joins this
        machine's router: a client with that user's password (one machine), its
        certificate (server), or nothing (a robot's own router)."""
        return BusSettings(zenoh_mode="client", zenoh_connect=[self.endpoint],
                           **_identity(self.role, user, self.tls,
                                       self.zenoh_dir / f"{user}.password"), **fields)


def plan_stack(options: StackOptions, environ: Mapping[str, str], token: str,
               passwords: Callable[[Sequence[str]], dict[str, str]] = new_passwords
               ) -> StackPlan:
    """The children of the stack and their environments (pure).

    Each service's settings are read from ``environ`` (as that service would read
    them), with what the stack decides forced on top: the router's endpoint, the
    ports, the data directories, the token (``token`` when ``environ`` has no
    ``AESOP_ADMIN_TOKEN``), the scene and the rate. A bad value fails here, naming
    the field (``pydantic.ValidationError``), not in a child. Each child's
    environment is the caller's without any ``AESOP_*`` variable, plus its settings.

    ``options.role`` says which parts run here, the same parts whatever the role:
    ``all`` (one machine: a hub every session joins with a user of its own, ``passwords``
    making one per user: the services, ``monitor``, each robot's ``control-<id>`` and
    ``robot-<id>``), ``server`` (its router listening for robots over mutual TLS, the
    detectors, the reasoner, the LLM server and the dashboard, each session with its
    certificate in ``options.tls``) or ``robot`` (its own router on its loopback, linked
    to ``options.server`` with the robot's certificate, and its control loop and vehicle).

    ``options.robots``: that many robots (ids from ``AESOP_ROBOT``, :func:`fleet`), each
    with its control loop and simulated vehicle as its own user; ``options.replicas``:
    that many detector replicas sharing the robots, on a PostgreSQL server of the stack's
    (``<data-dir>/postgres``, reached on its socket in that 0700 folder).
    """
    role, ports, py = options.role, options.ports, options.python
    given = environ.get("AESOP_ADMIN_TOKEN", "")
    endpoint = _endpoint(role, ports.hub, options.listen)
    common: dict[str, Any] = {"zenoh_connect": [endpoint], "zenoh_listen": [],
                              "zenoh_mode": "client", "zenoh_multicast": False,
                              "zenoh_config": None, "admin_token": given or token}
    robots = _check_fleet(options, read_settings(BusSettings, environ).robot)
    secret = passwords(users_of(robots, ros2=options.ros2 is not None)) if role == "all" else {}
    zenoh_dir = options.data_dir / "zenoh"

    def user(name: str) -> dict[str, Any]:  # a session's identity at its router
        return {**_identity(role, name, options.tls, None),
                **({"zenoh_password": secret[name]} if role == "all" else {})}

    def data(name: str) -> Path:
        return options.data_dir / name

    local = options.local_model if role != "robot" else None
    fake = role != "robot" and local is None and "AESOP_REASONER_LLM_BASE_URL" not in environ
    names = child_names(robots, options.replicas, vehicle=vehicle_kind(options))
    postgres = (PostgresServer(data("postgres"), ports.postgres)
                if options.replicas > 1 and role != "robot" else None)
    settings: list[tuple[str, str, ServiceSettings]] = []
    if role != "robot":
        _server(options, environ, names, postgres, fake, common, user, data, settings)
    fleet_children: tuple[tuple[str, str, str], ...] = ()
    scenario = options.scenario or hardware_scenario()
    if role != "server":
        fleet_children, scenario = _robots(options, environ, robots, names, common, user,
                                           data, settings)
    if options.dashboard and role != "robot":
        settings.append(("dashboard", "dashboard", read_settings(
            DashboardSettings, environ, **common, **user("dashboard"), port=ports.dashboard,
            data_dir=data("dashboard"),
            embedding_url=f"http://127.0.0.1:{ports.embedding}")))
    inherited = {k: v for k, v in environ.items() if not k.startswith("AESOP_")}
    fake_llm = to_env(read_settings(FakeLLMSettings, environ, defaults={
        "profile": "fixed", "fixed_s": FAKE_LLM_LATENCY_S}))

    def child(name: str, kind: str, service: ServiceSettings) -> ChildSpec:
        argv = (py, "-m", "tools.cli", "serve", kind)
        env = {**inherited, **to_env(service), **(fake_llm if kind == "fake-llm" else {})}
        return ChildSpec(name, argv, service.port, env)

    host, port = _ready_at(role, ports.hub, options.listen)
    hub = ChildSpec("hub" if role == "all" else "router",
                    (py, "-m", "tools.stack.router", *_router_args(options, robots, zenoh_dir)),
                    port, inherited, ready="tcp", host=host)
    children = tuple(child(*spec) for spec in settings)
    if postgres is not None:  # before the replicas: they open their store as they start
        children = (ChildSpec(POSTGRES, postgres.argv(), ports.postgres, inherited,
                              ready="tcp"), *children)
    if local is not None:  # it accepts connections once the model is loaded; its key (llama.cpp's
        # server reads API_KEY) is the stack's token, which the reasoner holds
        argv = server_argv(local, ports.fake_llm, threads=STACK_THREADS)
        children = (ChildSpec(LOCAL_LLM, argv, ports.fake_llm,
                              {**inherited, "API_KEY": given or token}, ready="tcp"),
                    *children)
    return StackPlan(hub=hub, services=children, token=given or token,
                     token_generated=not given, fake_llm=fake, local_model=local,
                     robot=robots[0], scenario=scenario, zenoh_dir=zenoh_dir,
                     data_dir=options.data_dir,
                     passwords=secret, fleet=fleet_children, postgres=postgres, role=role,
                     tls=options.tls, endpoint=endpoint, server=options.server,
                     linked=tuple(robots) if role == "server" else ())


def _ready_at(role: Role, port: int, listen: Sequence[str]) -> tuple[str, int]:
    """Where this machine's router accepts connections once it is up: the server's first
    listen endpoint (loopback when it listens on every address)."""
    if role != "server" or not listen:
        return "127.0.0.1", port
    host, _, at = listen[0].split("/", 1)[1].rpartition(":")
    return ("127.0.0.1" if host in ("[::]", "0.0.0.0") else host.strip("[]")), int(at)


def _endpoint(role: Role, port: int, listen: Sequence[str] = ()) -> str:
    """Where this machine's sessions join its router: the hub's or the robot's router on
    loopback; the server's router by the name its certificate carries for this machine."""
    if role != "server":
        return f"tcp/127.0.0.1:{port}"
    host, at = _ready_at(role, port, listen)
    name = "localhost" if host == "127.0.0.1" else f"[{host}]" if ":" in host else host
    return f"tls/{name}:{at}"


def _identity(role: Role, user: str, tls: Path | None, password_file: Path | None
              ) -> dict[str, Any]:
    """How ``user``'s session proves who it is to its router: a user name (one machine, the
    password given apart), a certificate of the stack's CA (the server's), or nothing (a
    robot's own router, open on its loopback to the robot's own processes); the other ways
    forced off, whatever the environment says."""
    out: dict[str, Any] = {"zenoh_user": None, "zenoh_password": None,
                           "zenoh_password_file": None, "zenoh_tls_ca": None,
                           "zenoh_tls_cert": None, "zenoh_tls_key": None}
    if role == "all":
        out |= {"zenoh_user": user, "zenoh_password_file": password_file}
    elif role == "server":
        assert tls is not None
        out |= {"zenoh_tls_ca": tls / "ca.pem", "zenoh_tls_cert": tls / f"{user}.pem",
                "zenoh_tls_key": tls / f"{user}-key.pem"}
    return out


def _router_args(options: StackOptions, robots: Sequence[str], zenoh_dir: Path
                 ) -> tuple[str, ...]:
    """The arguments of this machine's router (:mod:`.router`) for the role."""
    port = options.ports.hub
    if options.role == "server":
        listen = options.listen or (f"tls/[::]:{port}",)
        return ("--role", "server", "--tls", str(options.tls),
                *(a for e in listen for a in ("--listen", e)),
                *(a for r in robots for a in ("--linked", r)))
    if options.role == "robot":
        (robot,) = robots
        return ("--role", "robot", "--tls", str(options.tls), "--robot", robot,
                "--connect", f"tls/{options.server}",
                *(a for e in ROBOT_LISTEN for a in ("--listen", f"{e}:{port}")))
    return ("--users", str(zenoh_dir / "users.txt"),
            *(a for r in robots for a in ("--robot", r)), "--listen", f"tcp/127.0.0.1:{port}",
            *(("--ros2", str(options.ros2)) if options.ros2 else ()))


def _server(options: StackOptions, environ: Mapping[str, str],
            names: Mapping[str, Sequence[str]], postgres: PostgresServer | None, fake: bool,
            common: dict[str, Any], user: Callable[[str], dict[str, Any]],
            data: Callable[[str], Path], settings: list[tuple[str, str, ServiceSettings]]
            ) -> None:
    """The server's services, appended to ``settings``: the fake LLM (when no other), the
    detector replicas and the reasoner."""
    ports = options.ports
    if fake:
        settings.append(("fake-llm", "fake-llm", read_settings(
            FakeLLMServiceSettings, environ, **common, port=ports.fake_llm)))
    for j, name in enumerate(names["embedding"]):
        store = {} if postgres is None else {"store": postgres.socket_url, "replica": name}
        settings.append((name, "embedding", read_settings(
            EmbeddingSettings, environ, defaults={"detector_cache": DETECTOR_CACHE}, **common,
            **user("embedding"), port=ports.of(name, "embedding", j), data_dir=data(name),
            **store)))
    settings.append(("reasoner", "reasoner", _reasoner(
        environ, options.local_model, fake, ports,
        {**common, **user("reasoner"), "data_dir": data("reasoner")})))


def _check_fleet(options: StackOptions, robot: str) -> tuple[str, ...]:
    """The robots this machine flies (all, robot) or serves (server)."""
    if options.robots < 1 or options.replicas < 1:
        raise PlanError("--robots and --replicas count from 1")
    if options.vehicle == "external" and (options.ros2 is not None or options.role == "server"):
        raise PlanError("--vehicle external is the robot's own vehicle, on the robot: not "
                        "with --ros2 (the bridge is the vehicle) nor --role server")
    if options.role != "all":
        if options.tls is None:
            raise PlanError(f"--role {options.role} needs --tls DIR (aesop zenoh certs)")
        if options.role == "robot" and (options.robots > 1 or not options.server):
            raise PlanError("--role robot flies one robot and needs --server HOST:PORT")
        if options.role == "robot" and (options.replicas > 1 or options.local_model):
            raise PlanError("--replicas and --llm run on the server (--role server)")
        if options.role == "server":
            if options.ros2 is not None:
                raise PlanError("--ros2 runs on the robot (--role robot): its bridge and its "
                                "ROS 2 graph stay there")
            return options.linked or fleet(robot, options.robots)
    if options.ros2 is not None:
        if options.robots > 1:
            raise PlanError("--ros2 flies the one robot its config maps; --robots > 1 flies "
                            "simulated vehicles")
        if (mapped := load_config(options.ros2).robot) != robot:
            raise PlanError(f"{options.ros2} maps the topics of robot {mapped!r}, the stack "
                            f"serves {robot!r} (AESOP_ROBOT)")
    return fleet(robot, options.robots)


def _reasoner(environ: Mapping[str, str], local: LocalModel | None, fake: bool, ports: Ports,
              forced: dict[str, Any]) -> ReasonerSettings:
    """The reasoner's settings: how it reaches the LLM server the stack starts, if any."""
    llm: dict[str, Any] = {}
    if fake or local is not None:  # the stack's own server: its key is the stack's token
        llm["llm_base_url"] = f"http://127.0.0.1:{ports.fake_llm}/v1"
        llm["llm_api_key"] = forced["admin_token"]
    if local is not None:  # its model, asked as that server wants (the environment's knobs win)
        asked = read_settings(ReasonerSettings, environ).request.model_dump(exclude_unset=True)
        llm |= {"llm_model": local.alias, "request": {**REASONER_SETTINGS["request"], **asked}}
    defaults = ({"llm_model": "fake"} if fake else
                {"variant": REASONER_SETTINGS["variant"]} if local is not None else None)
    return read_settings(ReasonerSettings, environ, defaults=defaults, **forced,
                         port=ports.reasoner, **llm)


def _robots(options: StackOptions, environ: Mapping[str, str], robots: Sequence[str],
            names: Mapping[str, Sequence[str]], common: dict[str, Any],
            user: Callable[[str], dict[str, Any]], data: Callable[[str], Path],
            settings: list[tuple[str, str, ServiceSettings]]
            ) -> tuple[tuple[tuple[str, str, str], ...], Path]:
    """Each robot's control loop and vehicle (the simulator as the robot's own user, as
    fast as the loop flies the scene: real time at the scene's 1/dt; or the bridge to a
    ROS 2 robot, as the ros2 user; or none, for an external vehicle), appended to
    ``settings``; (robot, control, vehicle) child names, and the scene flown."""
    ports = options.ports
    kind = vehicle_kind(options)
    out = []
    scenario = options.scenario
    dt: float | None = None
    for i, robot in enumerate(robots):
        control_name = names["control"][i]
        vehicle_name = names[kind][i] if kind is not None else ""
        forced: dict[str, Any] = {**common, **user(control_user(robot)), "robot": robot,
                                  "port": ports.of(control_name, "control", i),
                                  "data_dir": data(control_name)}
        if options.rate_hz is not None:
            forced["rate_hz"] = options.rate_hz
        control = read_settings(ControlSettings, environ, **forced)
        scenario = scenario or resolve_scenario(control.scenario or hardware_scenario())
        control = control.model_copy(update={"scenario": scenario})  # resolved, existing
        if options.ros2 is not None:  # its states must be in control's frame, or all refused
            try:
                load_config(options.ros2, frame=control.vehicle.frame)
            except ConfigError as exc:
                raise PlanError(str(exc)) from None
        dt = dt or load_scenario(scenario).dt  # the one scene, read once
        settings.append((control_name, "control", control))
        out.append((robot, control_name, vehicle_name))
        if kind is None:
            continue  # the robot's own vehicle joins as robot-<id>
        vehicle_port = ports.of(vehicle_name, "sim", i)
        vehicle: ServiceSettings = (
            read_settings(SimSettings, environ, **common, **user(robot_user(robot)),
                          robot=robot, port=vehicle_port, data_dir=data(vehicle_name),
                          scenario=scenario,
                          time_scale=dt / control.period_s(dt))
            if options.ros2 is None else
            read_settings(Ros2Settings, environ, **common, **user(ROS2_BRIDGE), port=vehicle_port,
                          data_dir=data(vehicle_name), config=options.ros2))
        settings.insert(-1, (vehicle_name, kind, vehicle))  # before its control loop
    assert scenario is not None
    return tuple(out), scenario


# --------------------------------------------------------------------------- processes


class Stack:
    """Starts a :class:`StackPlan`'s children, watches them and stops them all."""

    def __init__(self, plan: StackPlan, sink: Sink, *, ready_timeout_s: float = 180.0,
                 stop_event: threading.Event | None = None,
                 restart_delay_s: float = 1.0) -> None:
        self.plan, self.sink = plan, sink
        self.hub = Child(plan.hub, sink)
        self.children = [Child(spec, sink) for spec in plan.services]
        self.ready_timeout_s = ready_timeout_s
        self.stopping = stop_event or threading.Event()
        self.restarts: dict[str, int] = {}  # child name -> times started again
        self.restart_delay_s = restart_delay_s  # a crashing child is not a busy loop
        self.lock = DataDirLock(plan.data_dir)

    @property
    def pids(self) -> dict[str, int]:
        return {c.name: c.pid for c in [self.hub, *self.children] if c.proc is not None}

    def claim(self) -> None:
        """Hold the data directory and check that every port the stack will listen on is
        free, before anything is written or started: :class:`DataDirInUse` when another
        stack holds the directory (it would rewrite that stack's Zenoh passwords and token),
        :class:`PlanError` naming a port in use (the directory let go again). Again once
        held: the ports only."""
        self.lock.acquire()
        busy = [(c.name, c.port) for c in [self.plan.hub, *self.plan.services]
                if port_in_use(c.port, c.host)]
        if busy:
            self.lock.release()
            raise PlanError(ports_in_use_text(self.plan, busy))

    def start(self) -> None:
        """:meth:`claim`, the Zenoh credentials, the hub, then every service at once;
        returns when all are ready."""
        self.claim()
        if self.plan.passwords:  # one machine: a password per user and start
            write_credentials(self.plan.zenoh_dir, self.plan.passwords)
        if ROS2 in self.plan.passwords:  # the robot's rmw_zenoh nodes join as the ros2 user
            write_private(self.plan.ros2_session,
                          ros2_session_config(self.plan.endpoint, self.plan.passwords[ROS2]))
        if self.plan.postgres is not None:
            self.plan.postgres.init()  # once per data directory
        first = [self.hub, *self._infrastructure]
        for child in first:
            child.start()
        self._await_ready(first)
        rest = [c for c in self.children if c not in first]
        for child in rest:
            child.start()
        self._await_ready(rest)

    @property
    def _infrastructure(self) -> list[Child]:
        """What the services need as they start and stop: PostgreSQL, with the hub."""
        return [c for c in self.children if c.name == POSTGRES]

    def _await_ready(self, children: Sequence[Child]) -> None:
        await_ready(children, self.ready_timeout_s, stopping=self.stopping,
                    on_ready=lambda c: self.sink("up", f"{c.name} ready on port {c.spec.port}"))

    def watch(self) -> str | None:
        """Block until ``stopping`` is set (None) or a child keeps dying (its description).
        Every child that exits, the hub, a service, an LLM server or PostgreSQL, is started
        again, as compose's restart policy or systemd's ``Restart=`` would, after a delay
        that doubles with each of its exits in the last :data:`RESTART_WINDOW_S` (from
        ``restart_delay_s`` up to :data:`MAX_RESTART_DELAY_S`); the others go on: the
        services are Zenoh clients that reconnect by themselves, the control loop takes a
        silent detector or vehicle as an anomaly, the reasoner answers with its labelled
        fallback. A child that exits more than :data:`MAX_RESTARTS` times in that window
        stops the stack."""
        exits: dict[str, deque[float]] = {}
        due: dict[str, float] = {}  # child name -> when it starts again
        while not self.stopping.wait(0.2):
            now = time.monotonic()
            for child in [self.hub, *self.children]:
                if child.name in due:
                    if now >= due[child.name]:
                        del due[child.name]
                        child.start()
                    continue
                status = child.exited()
                if status is None:
                    continue
                recent = exits.setdefault(child.name, deque())
                recent.append(now)
                while now - recent[0] > RESTART_WINDOW_S:
                    recent.popleft()
                if len(recent) > MAX_RESTARTS:
                    return (f"{child.name} exited with status {status} ({len(recent)} times "
                            f"in {RESTART_WINDOW_S:g} s)")
                delay = min(self.restart_delay_s * 2 ** (len(recent) - 1),
                            MAX_RESTART_DELAY_S)
                self.restarts[child.name] = self.restarts.get(child.name, 0) + 1
                self.sink("up", f"{child.name} exited with status {status}: starting it "
                          f"again in {delay:g} s")
                due[child.name] = now + delay
        return None

    def replace(self, spec: ChildSpec) -> None:
        """Stop the service named ``spec.name`` and start it again as ``spec`` says (new
        settings); returns once it is ready."""
        i = next(i for i, c in enumerate(self.children) if c.name == spec.name)
        self.children[i].stop()
        self.children[i] = Child(spec, self.sink)
        self.children[i].start()
        self._await_ready([self.children[i]])

    @property
    def hub_restarts(self) -> int:
        return self.restarts.get(self.hub.name, 0)

    def stop(self, grace_s: float = 10.0) -> None:
        """SIGTERM every service group, SIGKILL what is left after ``grace_s``; the hub
        and PostgreSQL last."""
        last = [*self._infrastructure, self.hub]
        for group in ([c for c in self.children if c not in last], last):
            for child in group:
                child.signal(signal.SIGTERM)
            deadline = time.monotonic() + grace_s
            for child in group:
                if not child.wait(max(0.0, deadline - time.monotonic())):
                    self.sink("up", f"{child.name} did not stop in {grace_s:g} s: killing it")
                    child.signal(signal.SIGKILL)
                    child.wait(5.0)
        self.lock.release()


def ports_in_use_text(plan: StackPlan, busy: Sequence[tuple[str, int]]) -> str:
    """Which ports are taken, by which child they were meant for, and how to change them."""
    ports = ", ".join(f"{port} ({name})" for name, port in busy)
    listen = plan.role == "server" and any(name == plan.hub.name for name, _ in busy)
    return (f"port{'s' if len(busy) > 1 else ''} {ports} already in use on this machine "
            f"(another `aesop up` or `aesop demo`?): stop what holds "
            f"{'them' if len(busy) > 1 else 'it'}, or pass --random-ports"
            + (" (the router's port: --listen)" if listen else "") + "; nothing was started")


# --------------------------------------------------------------------------- the command


def write_token(data_dir: Path, token: str) -> Path:
    """Keep a generated admin token in ``data_dir/admin-token``, readable by the owner only
    (never written through a link, never keeping an old file's mode)."""
    data_dir.mkdir(parents=True, exist_ok=True)
    path = data_dir / "admin-token"
    write_private(path, token + "\n")
    return path


def urls_text(plan: StackPlan, token_file: Path | None) -> str:
    lines = ["", "AESOP stack is up:"]
    lines += [f"  {s.name:<10} " + (s.url if s.name != POSTGRES else f"PostgreSQL on port "
                                    f"{s.port}, its socket in {plan.postgres.root}"
                                    if plan.postgres else "")
              for s in plan.services]
    if len(plan.robots) > 1:
        own = "" if any(not vehicle for _, _, vehicle in plan.fleet) else \
            " and simulated vehicle"
        lines.append(f"  robots     {', '.join(plan.robots)} (each with its control loop{own})")
    if plan.url("dashboard"):
        lines.append("  (open the dashboard once as <its url>/?token=<admin token>: "
                     "the browser keeps it as a cookie)")
    lines += _zenoh_lines(plan)
    lines += vehicle_lines(plan)
    if plan.url(ROS2) and plan.role == "all":
        lines.append(f"  ROS 2: start the robot's nodes with RMW_IMPLEMENTATION=rmw_zenoh_cpp "
                     f"ZENOH_SESSION_CONFIG_URI={plan.ros2_session} (the ros2 user); "
                     f"its topics: aesop ros2 keys --config <the --ros2 file>")
    fly = fly_command(plan)
    if fly:
        lines += ["  fly the hardware scenarios against it (add --scenario-name 2a for one):",
                  f"    {fly}"]
        if not plan.fake_llm and plan.url("reasoner"):  # a model nobody has timed here
            lines.append(f"  K measured on its model first: add --measure-k --reasoner-url "
                         f"{plan.url('reasoner')}")
    if plan.fake_llm:
        lines.append("  LLM: the fake OpenAI-compatible server (--llm local for a trained "
                     "model here, or AESOP_REASONER_LLM_BASE_URL for any server)")
    if plan.local_model is not None:
        lines.append(f"  LLM: {plan.local_model.alias} ({plan.local_model.path}), served by "
                     "llama.cpp's server")
    if token_file is not None:
        lines.append(f"  admin token: generated, in {token_file} (export AESOP_ADMIN_TOKEN="
                     f"$(cat {token_file}))")
    else:
        lines.append("  admin token: AESOP_ADMIN_TOKEN from the environment")
    lines.append("Ctrl-C stops everything.")
    return "\n".join(lines)


def fly_command(plan: StackPlan) -> str | None:
    """``aesop demo --attach`` for this stack's first robot (its simulated vehicle, or an
    external one: ``--vehicle bus``), when it flies one on this machine's hub."""
    if plan.role != "all" or not plan.fleet:
        return None
    control, vehicle = plan.robot_urls(plan.robots[0])
    external = not plan.fleet[0][2]
    if (not vehicle and not external) or plan.url("embedding") is None:
        return None  # the ROS 2 bridge's robot: reset and truth are the robot's own
    robot = "" if plan.robots[0] == "robot0" else f"AESOP_ROBOT={plan.robots[0]} "
    return (f"{robot}aesop demo --attach --data-dir {plan.data_dir} --connect {plan.endpoint} "
            f"--embedding-url {plan.url('embedding')} --control-url {control} "
            + ("--vehicle bus" if external else f"--sim-url {vehicle}"))


def vehicle_lines(plan: StackPlan) -> list[str]:
    """How each robot's external vehicle joins this machine's router (none: the stack
    runs its vehicles)."""
    external = [robot for robot, _, vehicle in plan.fleet if not vehicle]
    if not external:
        return []
    lines = ["  vehicles: none started; the control loop waits for each robot's own "
             "(docs/architecture.md 3a), joining as its robot's user:"]
    for robot in external:
        user = robot_user(robot)
        if plan.role == "all":
            identity = (f"AESOP_ZENOH_USER={user} "
                        f"AESOP_ZENOH_PASSWORD_FILE={plan.zenoh_dir / f'{user}.password'} ")
        else:  # the robot's own router, open on its loopback
            identity = ""
        lines.append(f"    AESOP_ROBOT={robot} AESOP_ZENOH_MODE=client "
                     f"AESOP_ZENOH_CONNECT={plan.endpoint} {identity}python my_vehicle.py")
    return lines


def _zenoh_lines(plan: StackPlan) -> list[str]:
    """What the router is, and how to watch the stack from this machine."""
    if plan.role == "robot":
        return [f"  {'zenoh':<10} {plan.endpoint}  (robot {plan.robot}'s own router, open on "
                f"this machine's loopback: its ROS 2 nodes join it with rmw_zenoh's default "
                f"config; linked to the server at {plan.server} over mutual TLS)",
                f"  watch it: AESOP_ZENOH_MODE=client aesop watch --connect {plan.endpoint}"]
    if plan.role == "server":
        assert plan.tls is not None
        monitor = (f"AESOP_ZENOH_TLS_CA={plan.tls / 'ca.pem'} AESOP_ZENOH_TLS_CERT="
                   f"{plan.tls / 'monitor.pem'} AESOP_ZENOH_TLS_KEY={plan.tls / 'monitor-key.pem'}")
        return [f"  {'zenoh':<10} {plan.hub.argv[plan.hub.argv.index('--listen') + 1]}  "
                f"(router: robots {', '.join(plan.linked)} link in over mutual TLS; services "
                f"join it at {plan.endpoint}, each with its certificate)",
                f"  watch it: AESOP_ZENOH_MODE=client {monitor} aesop watch --robot all "
                f"--connect {plan.endpoint}"]
    return [f"  {'zenoh':<10} {plan.endpoint}  (router; services are clients, each with "
            f"its own user)",
            f"  watch it: AESOP_ZENOH_MODE=client AESOP_ZENOH_USER=monitor "
            f"AESOP_ZENOH_PASSWORD_FILE={plan.zenoh_dir / 'monitor.password'} "
            f"aesop watch --connect {plan.endpoint}"]


def install_stop_handlers(stop: threading.Event) -> None:
    """SIGINT and SIGTERM set ``stop`` (the main thread then shuts the stack down)."""
    stop_on(stop)


def run_up(options: StackOptions, environ: Mapping[str, str]) -> int:
    plan = plan_stack(options, environ, secrets.token_urlsafe(24))
    if not options.dashboard and options.role == "all":
        print("aesop up: the dashboard is off (--no-dashboard)", file=sys.stderr)
    stop = threading.Event()
    stack = Stack(plan, stderr_sink(), stop_event=stop)
    stack.claim()  # the data directory and the ports, before a file is written
    install_stop_handlers(stop)
    status = 0
    try:
        token_file = write_token(options.data_dir, plan.token) if plan.token_generated else None
        stack.start()
        print(urls_text(plan, token_file), flush=True)
        died = stack.watch()
        if died is not None:
            print(f"aesop up: {died}; stopping the stack", file=sys.stderr)
            status = 1
    except ServiceFailed as exc:
        print(f"aesop up: {exc}", file=sys.stderr)
        status = 130 if stop.is_set() else 1
    finally:
        print("aesop up: stopping ...", file=sys.stderr, flush=True)
        stack.stop()
        print("aesop up: stopped", file=sys.stderr, flush=True)
    return status
