"""docker compose up, for real (issue 42): a Docker engine (installed and started by
``deploy/docker/engine.sh`` when none answers), the image built offline as ``make image``
builds it, the shipped ``docker-compose.yml`` brought up with secrets made by ``aesop zenoh
credentials --owner 10001`` as the docs say, every service healthy, scenario 2a flown
against it by ``aesop demo --attach`` and judged on the simulator's truth, ``down``/``up``
keeping the cache, a killed service restarted by the engine, the shipped fleet file's three
robots and two detector replicas (on PostgreSQL) all connected, the smollm2 override's image
built offline and its server answering a chat completion with the reasoner's key; then
everything it made is removed, and an engine it started is stopped, its iptables rules and
bridges put back.

Needs root (the engine, debootstrap), as ``make test`` runs on these machines, and ``make
llama``'s wheel of llama-cpp-python (``make test`` builds it first); the project's ports
(7447, 8001-8004, 8080, 8101-8204) must be free."""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import zenoh

from tests.compose_stack import FLEET, IMAGE_UID, ROOT, SMOLLM2, Compose, build, build_smollm2, run

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]

ROBOTS = ("robot0", "robot1", "robot2")
AESOP = str(Path(sys.executable).with_name("aesop"))  # the project's CLI, as installed here


@pytest.fixture(scope="module")
def secrets(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("compose") / "secrets"
    run([AESOP, "zenoh", "credentials", folder, "--owner", str(IMAGE_UID),
         *(a for r in ROBOTS for a in ("--robot", r))])
    return folder


@pytest.fixture(scope="module")
def engine() -> Iterator[list[str]]:
    """The engine and the images; afterwards, the images this run made are removed, the
    build cache too (3.5 GB after ``make image`` and the smollm2 build: the rest of the
    suite needs the disk more than a later build needs the cache; ``make test`` again
    rebuilds the image from its wheelhouse in about 3 minutes), and an engine it (or ``make
    image`` before it) started is stopped."""
    run([ROOT / "deploy" / "docker" / "engine.sh", "up"], timeout=900)
    started = time.monotonic()
    made = build()
    print(f"images ready in {time.monotonic() - started:.0f} s (made: {made or 'none'})")
    yield made
    if made:
        run(["docker", "image", "rm", *made], check=False)
    run(["docker", "image", "prune", "-f"], check=False)  # the build's dangling layers
    run(["docker", "builder", "prune", "-af"], check=False)
    run([ROOT / "deploy" / "docker" / "engine.sh", "down"], timeout=300)


@pytest.fixture(scope="module")
def stack(engine: list[str], secrets: Path) -> Iterator[Compose]:
    stack = Compose("aesop-test42", secrets)
    try:
        started = time.monotonic()
        stack.compose("up", "-d")
        healthy = stack.wait_healthy()
        print(f"docker compose up: every service healthy {time.monotonic() - started:.0f} s "
              f"after `up` ({healthy:.0f} s of waiting for health)")
        yield stack
    finally:
        stack.compose("down", "--volumes", "--remove-orphans", check=False)


def caches(stack: Compose) -> dict[str, int]:
    reply = httpx.get("http://127.0.0.1:8001/v1/caches", timeout=30,
                      headers={"Authorization": f"Bearer {stack.token()}"})
    reply.raise_for_status()
    return {c["name"]: c["size"] for c in reply.json()["caches"]}


def test_engine_sh_fetches_compose_v2_where_it_is_missing(engine: list[str],
                                                          tmp_path: Path) -> None:
    """As on a fresh machine: no Compose plugin in this HOME, so engine.sh fetches Debian
    13's (an engine answers already: the fixture's)."""
    home = {**os.environ, "HOME": str(tmp_path)}
    run([ROOT / "deploy" / "docker" / "engine.sh", "up"], env=home, timeout=300)
    assert (tmp_path / ".docker" / "cli-plugins" / "docker-compose").is_file()
    version = run(["docker", "compose", "version", "--short"], env=home).stdout
    assert int(version.split(".")[0]) >= 2, version


def test_the_secrets_are_the_images_user_s_and_no_one_else_s(secrets: Path) -> None:
    for path in secrets.iterdir():
        info = path.stat()
        assert (info.st_uid, info.st_gid, info.st_mode & 0o777) == (IMAGE_UID, IMAGE_UID, 0o600), \
            path.name


def test_scenario_2a_flown_against_compose_ends_on_the_blue_box(stack: Compose,
                                                                 tmp_path: Path) -> None:
    done = run([AESOP, "demo", "--attach", "--scenario-name", "2a", "--json",
                "--secrets", stack.secrets, "--out", tmp_path / "report"],
               env={k: v for k, v in os.environ.items() if not k.startswith("AESOP_")})
    (row,) = json.loads(done.stdout.splitlines()[-1])["scenarios"]
    print(row)
    assert row["outcome"] == "ok", row
    assert row["ended_in"] == "blue-box"  # the simulator's truth, not the loop's belief
    assert row["constraint_violations"] == 0
    assert row["decision"] == "alternative landing site"


def test_the_llm_server_answers_only_the_reasoners_key(stack: Compose) -> None:
    """Issue 43: the fake LLM wants the key in llm.key (the reasoner's decision above came
    from it: `decision_source` llm); another container on the network without it gets 401."""
    ask = ("import sys, urllib.request as u, urllib.error as e\n"
           "try: u.urlopen('http://fake-llm:8010/v1/models', timeout=8)\n"
           "except e.HTTPError as x: sys.exit(0 if x.code == 401 else 1)\n"
           "sys.exit(2)")
    done = stack.compose("exec", "-T", "dashboard", "python", "-c", ask, check=False)
    assert done.returncode == 0, (done.returncode, done.stdout, done.stderr)


def test_down_and_up_keeps_the_cache(stack: Compose) -> None:
    before = caches(stack)
    assert before.get("quadrotor", 0) > 0, before  # the flight above built it over REST
    stack.compose("down")
    stack.compose("up", "-d")
    stack.wait_healthy()
    assert caches(stack) == before


def test_a_killed_service_is_restarted_by_the_engine(stack: Compose) -> None:
    """The service's own process SIGKILLed from the host, as the OOM killer would (`docker
    kill` is a stop by hand, which no restart policy undoes)."""
    before = stack.container("control")
    init = before["State"]["Pid"]  # docker-init (init: true), the service its child
    service = run(["pgrep", "-P", str(init)]).stdout.split()
    assert service, "no service process under the container's init"
    run(["kill", "-KILL", *service])
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        now = stack.container("control")
        if now["RestartCount"] > before["RestartCount"] and now["State"]["Running"]:
            break
        time.sleep(1)
    else:
        raise AssertionError("control was not restarted")
    print(f"control restarted ({now['RestartCount']} restarts)")
    stack.wait_healthy()


def test_the_fleet_file_connects_every_robot_and_replica(stack: Compose) -> None:
    stack.compose("down")
    fleet = Compose(stack.project, stack.secrets, files=[FLEET])
    started = time.monotonic()
    fleet.compose("up", "-d")
    try:
        fleet.wait_healthy()
        print(f"fleet: every service healthy {time.monotonic() - started:.0f} s after `up`")
        seen = fleet_sessions(stack.secrets)
    finally:
        fleet.compose("down", "--volumes", "--remove-orphans", check=False)
    for robot in ROBOTS:  # its control loop and its simulated vehicle, each its own session
        assert f"aesop/{robot}/state" in seen, seen
        assert f"aesop/{robot}/vehicle/state" in seen, seen
    for replica in ("embedding", "embedding-2"):
        assert f"aesop/health/embedding/{replica}" in seen, seen


# a chat completion asked inside the smollm2 container, with the key it was given and without
ASK_SMOLLM2 = """
import json, urllib.request as u, urllib.error as e
key = open("/run/secrets/llm-key").read().strip()
body = json.dumps({"model": "smollm2-135m", "max_tokens": 32, "temperature": 0, "messages":
                   [{"role": "user", "content": "Name the capital of France in one word."}]})
def ask(headers):
    headers = {"Content-Type": "application/json", **headers}
    request = u.Request("http://127.0.0.1:8010/v1/chat/completions", body.encode(), headers)
    return json.load(u.urlopen(request, timeout=120))
try:
    ask({})
    without = 200
except e.HTTPError as x:
    without = x.code
print(json.dumps({"without_key": without,
                  "reply": ask({"Authorization": "Bearer " + key})}))
"""


def test_the_smollm2_image_builds_offline_and_answers_with_the_reasoners_key(
        engine: list[str], secrets: Path) -> None:
    """The smollm2 override's image as `make image-smollm2` builds it (`make llama`'s wheel,
    the locked wheels from the host, `network: none` for the build), its server started by
    compose with the reasoner's key (the image's entrypoint reads the secret): SmolLM2
    answers a chat completion that carries the key, and 401 to one that does not."""
    started = time.monotonic()
    made = build_smollm2()
    print(f"smollm2 image ready in {time.monotonic() - started:.0f} s (made: {made or 'none'})")
    server = Compose("aesop-test42-smollm2", secrets, files=[SMOLLM2], profiles=[])
    try:
        server.compose("up", "-d", "smollm2")
        server.wait_healthy(timeout_s=180)
        asked = json.loads(server.compose("exec", "-T", "smollm2", "python", "-c",
                                          ASK_SMOLLM2).stdout)
    finally:
        server.compose("down", "--remove-orphans", check=False)
        if made:
            run(["docker", "image", "rm", *made], check=False)
    print(asked)
    assert asked["without_key"] == 401
    reply = asked["reply"]
    (choice,) = reply["choices"]
    assert reply["model"] == "smollm2-135m" and reply["usage"]["completion_tokens"] > 0
    assert choice["message"]["content"].strip() and choice["finish_reason"] in {"stop", "length"}


def fleet_sessions(secrets: Path, listen_s: float = 3.0) -> set[str]:
    """What a monitor session of the compose router sees: the replicas' health tokens and
    every robot's control state and vehicle state."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", '["tcp/127.0.0.1:7447"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    password = (secrets / "monitor.password").read_text().strip()
    conf.insert_json5("transport/auth/usrpwd",
                      json.dumps({"user": "monitor", "password": password}))
    seen: set[str] = set()
    with zenoh.open(conf) as session:
        for reply in session.liveliness().get("aesop/health/**", timeout=10):
            if reply.ok is not None:
                seen.add(str(reply.ok.key_expr))
        with session.declare_subscriber("aesop/*/state", lambda s: seen.add(str(s.key_expr))), \
                session.declare_subscriber("aesop/*/vehicle/state",
                                           lambda s: seen.add(str(s.key_expr))):
            time.sleep(listen_s)
    return seen
