"""A real PostgreSQL server for the suite (Debian's PostgreSQL 15, tools/stack/postgres.py):
one per test run, in a directory of its own on a free port, and a fresh database per test.

As root (CI) the server runs as the ``postgres`` user, so its directory is made under /tmp
with every folder above it searchable (pytest's own tmp folders are not)."""

from __future__ import annotations

import shutil
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from shared.process import free_port
from tools.stack.postgres import PostgresServer


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[PostgresServer]:
    root = Path(tempfile.mkdtemp(prefix="aesop-pg-"))
    root.chmod(0o711)
    server = PostgresServer(root / "pg", free_port(), fsync=False)
    try:
        server.init()
        server.start()
        yield server
    finally:
        server.stop(immediate=True)
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture
def postgres_url(postgres_server: PostgresServer) -> str:
    """The URL of a new, empty database on the suite's server (running)."""
    if not postgres_server.running():
        postgres_server.start()
    return postgres_server.create_database(f"t_{uuid.uuid4().hex[:16]}")
