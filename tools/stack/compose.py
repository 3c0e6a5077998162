"""``aesop zenoh fleet-compose``: docker compose for a fleet (pure: the base file in, the
override out).

The base ``docker-compose.yml`` runs one robot (``control`` and ``sim``, ``AESOP_ROBOT``) and
one detector. The override adds, for every further robot, its control loop and simulated
vehicle (``control-<id>``, ``sim-<id>``: the base services with that robot's id, their own
Zenoh users, ``control-<id>`` and ``robot-<id>``, and secrets, the host ports 100 apart), and
from two detector replicas on, the replicas (``embedding-<j>``, each with its own volume)
and PostgreSQL (``postgres:15``, the password from ``AESOP_POSTGRES_PASSWORD``) they
share; the router mounts the fleet's ACL::

    aesop zenoh fleet-compose --robots 3 --replicas 2 > deploy/compose.fleet.yml
    aesop zenoh router-config --robot robot0 --robot robot1 --robot robot2 \\
        > deploy/zenoh/router.fleet.json5
    aesop zenoh credentials deploy/secrets --robot robot0 --robot robot1 --robot robot2
    docker compose -f docker-compose.yml -f deploy/compose.fleet.yml up --build
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from typing import Any

import yaml

FLEET_ROUTER = "./deploy/zenoh/router.fleet.json5"
PASSWORD = "${AESOP_POSTGRES_PASSWORD:?set AESOP_POSTGRES_PASSWORD for the detectors' PostgreSQL}"
STORE = f"postgresql://aesop:{PASSWORD}@postgres:5432/aesop"
STEP = 100  # host ports of the next robot or replica


def _published(port: int, container: int) -> list[str]:
    return [f"127.0.0.1:{port}:{container}"]


def fleet_override(base: Mapping[str, Any], robots: Sequence[str], replicas: int
                   ) -> dict[str, Any]:
    """The override of ``base`` (the loaded ``docker-compose.yml``) for ``robots`` (the
    first is the base's own) and ``replicas`` detector replicas."""
    services = base["services"]
    out: dict[str, Any] = {"zenoh": {"volumes": [f"{FLEET_ROUTER}:/etc/zenoh/router.json5:ro"]}}
    secrets: dict[str, Any] = {}
    volumes: dict[str, Any] = {}
    for i, robot in enumerate(robots[1:], start=1):
        control = copy.deepcopy(services["control"])
        control["environment"] |= {
            "AESOP_ROBOT": robot, "AESOP_ZENOH_USER": f"control-{robot}",
            "AESOP_ZENOH_PASSWORD_FILE": f"/run/secrets/zenoh-control-{robot}"}
        control["secrets"] = [f"zenoh-control-{robot}"]
        control["ports"] = _published(8003 + STEP * i, 8003)
        sim = copy.deepcopy(services["sim"])
        secret = f"zenoh-robot-{robot}"
        sim["environment"] |= {"AESOP_ROBOT": robot, "AESOP_ZENOH_USER": f"robot-{robot}",
                               "AESOP_ZENOH_PASSWORD_FILE": f"/run/secrets/{secret}"}
        sim["secrets"] = [secret]
        sim["ports"] = _published(8004 + STEP * i, 8004)
        out |= {f"control-{robot}": control, f"sim-{robot}": sim}
        secrets[secret] = {"file": f"./deploy/secrets/robot-{robot}.password"}
        secrets[f"zenoh-control-{robot}"] = {"file": f"./deploy/secrets/control-{robot}.password"}
    if replicas > 1:
        shared = {"AESOP_EMBEDDING_STORE": STORE}
        out["embedding"] = {"depends_on": ["zenoh", "postgres"],
                            "environment": {**shared, "AESOP_EMBEDDING_REPLICA": "embedding"}}
        for j in range(2, replicas + 1):
            name = f"embedding-{j}"
            replica = copy.deepcopy(services["embedding"])
            replica["environment"] |= {**shared, "AESOP_EMBEDDING_REPLICA": name}
            replica["depends_on"] = ["zenoh", "postgres"]
            replica["ports"] = _published(8001 + STEP * (j - 1), 8001)
            replica["volumes"] = [v if not v.startswith("embedding-data:") else
                                  f"{name}-data:/data" for v in replica["volumes"]]
            out[name] = replica
            volumes[f"{name}-data"] = None
        out["postgres"] = {
            "image": "postgres:15", "restart": "unless-stopped", "init": True,
            "environment": {"POSTGRES_USER": "aesop", "POSTGRES_DB": "aesop",
                            "POSTGRES_PASSWORD": PASSWORD},
            "volumes": ["postgres-data:/var/lib/postgresql/data"],
            "healthcheck": {"test": ["CMD", "pg_isready", "-U", "aesop", "-d", "aesop"],
                            "interval": "10s", "timeout": "5s", "retries": 3}}
        volumes["postgres-data"] = None
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
            f"#   aesop zenoh credentials deploy/secrets {ids}\n"
            "#   docker compose -f docker-compose.yml -f deploy/compose.fleet.yml up --build\n"
            "# (AESOP_POSTGRES_PASSWORD set, with two replicas or more). Generated: edit the\n"
            "# base file, then write this one again.\n")
    body = yaml.safe_dump(fleet_override(base, robots, replicas), sort_keys=False, width=100)
    return head + body
