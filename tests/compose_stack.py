"""docker compose, driven as a user drives it, for tests/integration/test_compose.py: the
repository's own ``docker-compose.yml`` (and ``deploy/compose.fleet.yml``) under a project
name of the tests' own, its secrets in a folder of the tests' own (``AESOP_SECRETS``), the
image built offline as ``make image`` builds it (``deploy/docker/``)."""

from __future__ import annotations

import json
import os
import subprocess
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DOCKER = ROOT / "deploy" / "docker"
BASE_IMAGE = "aesop-base:bookworm"
POSTGRES_IMAGE = "aesop-postgres:15"
IMAGE = "aesop-stack:0.1.0"
SMOLLM2_IMAGE = "aesop-smollm2:0.1.2"
FLEET = ROOT / "deploy" / "compose.fleet.yml"
SMOLLM2 = ROOT / "deploy" / "compose.smollm2.yml"
IMAGE_UID = 10001


def run(cmd: Sequence[str | Path], *, env: Mapping[str, str] | None = None,
        timeout: float = 900, check: bool = True) -> subprocess.CompletedProcess[str]:
    """``cmd`` in the repository's root, its output kept (and shown when it fails)."""
    done = subprocess.run([str(c) for c in cmd], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)
    if check and done.returncode != 0:
        raise AssertionError(f"{' '.join(map(str, cmd))} exited {done.returncode}:\n"
                             f"{done.stdout[-4000:]}\n{done.stderr[-4000:]}")
    return done


def image_exists(name: str) -> bool:
    return run(["docker", "image", "inspect", name], check=False).returncode == 0


@dataclass
class Compose:
    """One compose project: ``files`` over the base file, with ``profiles``."""

    project: str
    secrets: Path
    files: list[Path] = field(default_factory=list)
    profiles: list[str] = field(default_factory=lambda: ["demo"])

    def env(self) -> dict[str, str]:
        return {**os.environ, "AESOP_SECRETS": str(self.secrets),
                "AESOP_POSTGRES_IMAGE": POSTGRES_IMAGE}

    def compose(self, *args: str, timeout: float = 900, check: bool = True
                ) -> subprocess.CompletedProcess[str]:
        files = [a for f in [ROOT / "docker-compose.yml", *self.files] for a in ("-f", str(f))]
        profiles = [a for p in self.profiles for a in ("--profile", p)]
        return run(["docker", "compose", "-p", self.project, *files, *profiles, *args],
                   env=self.env(), timeout=timeout, check=check)

    def services(self) -> list[dict[str, Any]]:
        """``docker compose ps``: each container's service, state and health."""
        out = self.compose("ps", "--all", "--format", "json").stdout
        lines = [line for line in out.splitlines() if line.strip()]
        if len(lines) == 1 and lines[0].startswith("["):  # older Compose: one JSON array
            return list(json.loads(lines[0]))
        return [json.loads(line) for line in lines]

    def wait_healthy(self, timeout_s: float = 420) -> float:
        """Seconds until every container is running and healthy (AssertionError naming the
        ones that are not, with their last log lines, after ``timeout_s``)."""
        started = time.monotonic()
        while True:
            rows = self.services()
            sick = [r["Service"] for r in rows
                    if r.get("State") != "running" or r.get("Health") not in ("healthy",)]
            if rows and not sick:
                return time.monotonic() - started
            if time.monotonic() - started > timeout_s:
                logs = self.compose("logs", "--tail", "20", *sick, check=False).stdout
                raise AssertionError(f"not healthy after {timeout_s:.0f} s: {sick}\n{logs}")
            time.sleep(3)

    def container(self, service: str) -> dict[str, Any]:
        ident = self.compose("ps", "--all", "-q", service).stdout.split()[0]
        return dict(json.loads(run(["docker", "inspect", ident]).stdout)[0])

    def token(self) -> str:
        return (self.secrets / "admin-token").read_text().strip()


def build(owner: int = IMAGE_UID) -> list[str]:
    """The images as ``make image`` makes them (what exists is kept: a second build with
    nothing changed is the layer cache's); returns the images this call made, to remove."""
    made = []
    bases = [BASE_IMAGE, "--postgres", POSTGRES_IMAGE]
    if run([DOCKER / "base-image.sh", "--check", *bases], check=False).returncode != 0:
        had = [name for name in (BASE_IMAGE, POSTGRES_IMAGE) if image_exists(name)]
        run([DOCKER / "base-image.sh", *bases])
        made += [name for name in (BASE_IMAGE, POSTGRES_IMAGE) if name not in had]
    run([DOCKER / "wheelhouse.sh"], env={**os.environ, "PYTHON": "python3"})
    had = image_exists(IMAGE)
    run(["docker", "compose", "build"], env={**os.environ, "AESOP_BASE_IMAGE": BASE_IMAGE},
        timeout=1800)
    if not had:
        made.append(IMAGE)
    return made


def build_smollm2() -> list[str]:
    """The smollm2 override's image as ``make image-smollm2`` makes it (after ``make llama``,
    whose wheel it takes): its wheels on the host, then the build, which reaches no network;
    returns the images this call made."""
    run([DOCKER / "wheelhouse.sh", "--smollm2"], env={**os.environ, "PYTHON": "python3"})
    had = image_exists(SMOLLM2_IMAGE)
    files = ["-f", ROOT / "docker-compose.yml", "-f", SMOLLM2]
    run(["docker", "compose", *files, "build", "smollm2"],
        env={**os.environ, "AESOP_BASE_IMAGE": BASE_IMAGE}, timeout=900)
    return [] if had else [SMOLLM2_IMAGE]
