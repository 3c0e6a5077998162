"""Docker compose's inputs that code writes: the secrets and a fleet's override.

The secrets (``aesop zenoh credentials``, :func:`write_secrets`) and a fleet's override
(``aesop zenoh fleet-compose``, :func:`fleet_override`, pure: the base file in, the override
out).

The base ``docker-compose.yml`` runs one robot (``control`` and ``sim``, ``AESOP_ROBOT``) and
one detector. The override adds, for every further robot, its control loop and simulated
vehicle (``control-<id>``, ``sim-<id>``: the base services with that robot's id, their own
Zenoh users, ``control-<id>`` and ``robot-<id>``, secrets and Zenoh IDs, the host ports 100
apart; every loop at the fleet's rate), and from two detector replicas on, the replicas
(``embedding-<j>``, each with its own volume) and PostgreSQL (``aesop-postgres:15``, made
offline by ``make image``, or ``AESOP_POSTGRES_IMAGE``; its password a secret file) they
share; the router mounts the fleet's ACL::

    aesop zenoh fleet-compose --robots 3 --replicas 2 > deploy/compose.fleet.yml
    aesop zenoh router-config --robot robot0 --robot robot1 --robot robot2 \\
        > deploy/zenoh/router.fleet.json5
    sudo aesop zenoh credentials deploy/secrets --owner 10001 \\
        --robot robot0 --robot robot1 --robot robot2
    docker compose -f docker-compose.yml -f deploy/compose.fleet.yml up -d
"""

from __future__ import annotations

import copy
import os
import secrets
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from .acl import new_passwords, users_of, write_credentials, write_private

FLEET_ROUTER = "./deploy/zenoh/router.fleet.json5"
SECRETS = "${AESOP_SECRETS:-./deploy/secrets}"  # as docker-compose.yml names the folder
# the password as files: the server's (POSTGRES_PASSWORD_FILE), the replicas' (libpq's passfile)
STORE = "postgresql://aesop@postgres:5432/aesop?passfile=/run/secrets/postgres-pgpass"
# made offline by `make image` (deploy/docker/base-image.sh --postgres): Debian's PostgreSQL 15
# as uid 10001, no capability needed; postgres:15 from Docker Hub serves too, given the
# capabilities its entrypoint uses (CHOWN, DAC_OVERRIDE, FOWNER, SETGID, SETUID) back
POSTGRES_IMAGE = "${AESOP_POSTGRES_IMAGE:-aesop-postgres:15}"
STEP = 100  # host ports of the next robot or replica
FLEET_RATE_HZ = 10  # every robot's loop, as `aesop up --robots N` (tools/stack/up.py)
IMAGE_UID = 10001  # the image's user (deploy/docker/Dockerfile)
TOKEN_FILE = "admin-token"  # every service's admin token, AESOP_ADMIN_TOKEN_FILE
TOKEN_SECRET = "admin-token"  # its name in docker-compose.yml
POSTGRES_FILE = "postgres.password"  # the detectors' PostgreSQL (compose.fleet)
PGPASS_FILE = "postgres.pgpass"  # the same, as libpq reads it (passfile)
LLM_KEY_FILE = "llm.key"  # the key the reasoner presents to its LLM server


def write_secrets(folder: Path, robots: Sequence[str], *,
                  owner: tuple[int, int] | None = None) -> list[str]:
    """Everything compose mounts as a secret, made anew in ``folder``: the Zenoh router's
    dictionary and each user's password (:func:`.acl.write_credentials`), the admin token
    and PostgreSQL's password, each 0600; with ``owner`` (uid, gid) chowned to it, so that
    the image's user reads them (compose bind-mounts a file secret with the host's owner and
    mode), and the key the reasoner presents to the LLM server (the fake LLM and llama.cpp's
    want it; for a cloud server, write its key there instead). Returns the Zenoh users.
    ``PermissionError`` when the chown is not allowed."""
    users = users_of(robots, ros2=True)  # the shipped router has the bridge
    write_credentials(folder, new_passwords(users))
    write_private(folder / TOKEN_FILE, secrets.token_urlsafe(32) + "\n")
    postgres = secrets.token_urlsafe(24)
    write_private(folder / POSTGRES_FILE, postgres + "\n")
    write_private(folder / PGPASS_FILE, f"*:*:*:aesop:{postgres}\n")
    write_private(folder / LLM_KEY_FILE, secrets.token_urlsafe(32) + "\n")
    if owner is not None:
        names = ["users.txt", TOKEN_FILE, POSTGRES_FILE, PGPASS_FILE, LLM_KEY_FILE,
                 *(f"{u}.password" for u in users)]
        for name in names:
            os.chown(folder / name, *owner)
    return users


def _published(port: int, container: int) -> list[str]:
    return [f"127.0.0.1:{port}:{container}"]


def _zenoh_id(port: int) -> str:
    """A generated service's own Zenoh ID (one session per ID at a router), from its host
    port; the base file's services have theirs in their client files (ae5xxx)."""
    return f"ae5{port}"


def fleet_override(base: Mapping[str, Any], robots: Sequence[str], replicas: int
                   ) -> dict[str, Any]:
    """The override of ``base`` (the loaded ``docker-compose.yml``) for ``robots`` (the
    first is the base's own) and ``replicas`` detector replicas."""
    services = base["services"]
    out: dict[str, Any] = {"zenoh": {"volumes": [f"{FLEET_ROUTER}:/etc/zenoh/router.json5:ro"]}}
    secrets: dict[str, Any] = {}
    volumes: dict[str, Any] = {}
    # every robot's loop at the fleet's rate, each simulator as much slower than real time
    # (rate_hz * dt: 0.5 for the hardware scene's 20 Hz): several robots share the cores
    fleet_rate = {"AESOP_CONTROL_RATE_HZ": f"${{AESOP_CONTROL_RATE_HZ:-{FLEET_RATE_HZ}}}"}
    fleet_scale = {"AESOP_SIM_TIME_SCALE": "${AESOP_SIM_TIME_SCALE:-0.5}"}
    if len(robots) > 1:
        out |= {"control": {"environment": fleet_rate}, "sim": {"environment": fleet_scale}}
    for i, robot in enumerate(robots[1:], start=1):
        control = copy.deepcopy(services["control"])
        port = 8003 + STEP * i
        control["environment"] |= {
            "AESOP_ROBOT": robot, "AESOP_ZENOH_USER": f"control-{robot}",
            "AESOP_ZENOH_PASSWORD_FILE": f"/run/secrets/zenoh-control-{robot}",
            "AESOP_ZENOH_ID": _zenoh_id(port), **fleet_rate}
        control["secrets"] = [TOKEN_SECRET, f"zenoh-control-{robot}"]
        control["ports"] = _published(port, 8003)
        sim = copy.deepcopy(services["sim"])
        secret = f"zenoh-robot-{robot}"
        port = 8004 + STEP * i
        sim["environment"] |= {"AESOP_ROBOT": robot, "AESOP_ZENOH_USER": f"robot-{robot}",
                               "AESOP_ZENOH_PASSWORD_FILE": f"/run/secrets/{secret}",
                               "AESOP_ZENOH_ID": _zenoh_id(port), **fleet_scale}
        sim["secrets"] = [TOKEN_SECRET, secret]
        sim["ports"] = _published(port, 8004)
        out |= {f"control-{robot}": control, f"sim-{robot}": sim}
        secrets[secret] = {"file": f"{SECRETS}/robot-{robot}.password"}
        secrets[f"zenoh-control-{robot}"] = {"file": f"{SECRETS}/control-{robot}.password"}
    if replicas > 1:
        shared = {"AESOP_EMBEDDING_STORE": STORE}
        pg_secrets = [*services["embedding"]["secrets"], "postgres-pgpass"]
        out["embedding"] = {"depends_on": ["zenoh", "postgres"], "secrets": pg_secrets,
                            "environment": {**shared, "AESOP_EMBEDDING_REPLICA": "embedding"}}
        for j in range(2, replicas + 1):
            name = f"embedding-{j}"
            port = 8001 + STEP * (j - 1)
            replica = copy.deepcopy(services["embedding"])
            replica["environment"] |= {**shared, "AESOP_EMBEDDING_REPLICA": name,
                                       "AESOP_ZENOH_ID": _zenoh_id(port)}
            replica["depends_on"] = ["zenoh", "postgres"]
            replica["secrets"] = pg_secrets
            replica["ports"] = _published(port, 8001)
            replica["volumes"] = [v if not v.startswith("embedding-data:") else
                                  f"{name}-data:/data" for v in replica["volumes"]]
            out[name] = replica
            volumes[f"{name}-data"] = None
        out["postgres"] = {
            "image": POSTGRES_IMAGE, "pull_policy": "missing", "restart": "unless-stopped",
            "init": True, "cap_drop": ["ALL"], "security_opt": ["no-new-privileges:true"],
            "secrets": ["postgres-password"],
            "environment": {"POSTGRES_USER": "aesop", "POSTGRES_DB": "aesop",
                            "POSTGRES_PASSWORD_FILE": "/run/secrets/postgres-password"},
            "volumes": ["postgres-data:/var/lib/postgresql/data"],
            "healthcheck": {"test": ["CMD", "pg_isready", "-h", "127.0.0.1", "-U", "aesop",
                                     "-d", "aesop"],
                            "interval": "10s", "timeout": "5s", "retries": 3}}
        volumes["postgres-data"] = None
        secrets |= {"postgres-password": {"file": f"{SECRETS}/{POSTGRES_FILE}"},
                    "postgres-pgpass": {"file": f"{SECRETS}/{PGPASS_FILE}"}}
    return {"services": out, **({"secrets": secrets} if secrets else {}),
            **({"volumes": volumes} if volumes else {})}


def fleet_override_text(base: Mapping[str, Any], robots: Sequence[str], replicas: int) -> str:
    """The override as ``deploy/compose.fleet.yml`` holds it, with how to use it."""
    ids = " ".join(f"--robot {r}" for r in robots)
    head = (f"# {len(robots)} robots ({', '.join(robots)}) and {replicas} detector "
            f"replica(s), over docker-compose.yml:\n"
            f"#   aesop zenoh fleet-compose --robots {len(robots)} --replicas {replicas}"
            " > deploy/compose.fleet.yml\n"
            f"#   aesop zenoh router-config {ids} > deploy/zenoh/router.fleet.json5\n"
            f"#   sudo aesop zenoh credentials deploy/secrets --owner 10001 {ids}\n"
            "#   docker compose -f docker-compose.yml -f deploy/compose.fleet.yml up -d\n"
            "# Generated: edit the base file, then write this one again.\n")
    body = yaml.safe_dump(fleet_override(base, robots, replicas), sort_keys=False, width=100)
    return head + body
