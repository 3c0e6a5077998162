"""The stack's own PostgreSQL server (``aesop up --replicas``; issue 43, finding 5): its
folder is private whatever was there before, and the detectors' role is no superuser (the
socket's trust then opens nothing a detector could not already do)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import psycopg
import pytest

from shared.process import free_port
from tools.stack.postgres import PostgresServer

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]


def test_an_existing_folder_is_made_private_before_the_server_uses_it() -> None:
    root = Path(tempfile.mkdtemp(prefix="aesop-pg-"))
    try:
        root.chmod(0o711)
        folder = root / "pg"
        folder.mkdir(mode=0o755)  # a careless operator's, or left by another tool
        server = PostgresServer(folder, free_port(), fsync=False)
        server.init()
        assert folder.stat().st_mode & 0o777 == 0o700
        folder.chmod(0o755)  # opened again after the first start
        server.init()  # what aesop up does at every start
        assert folder.stat().st_mode & 0o777 == 0o700
    finally:
        shutil.rmtree(root, ignore_errors=True)


def test_the_detectors_role_is_not_a_superuser(postgres_server: PostgresServer,
                                               postgres_url: str) -> None:
    for url in (postgres_server.socket_url, postgres_server.url, postgres_url):
        with psycopg.connect(url) as db:
            row = db.execute("SELECT rolsuper, rolcreaterole FROM pg_roles "
                             "WHERE rolname = current_user").fetchone()
            assert row == (False, False), url.split("@")[-1]
            with pytest.raises(psycopg.errors.InsufficientPrivilege):
                db.execute("COPY (SELECT 1) TO PROGRAM 'true'")  # a superuser's power
