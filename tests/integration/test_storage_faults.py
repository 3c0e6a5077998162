"""The vector-cache store under faults: a full disk, a size limit.

A 2xx means durable; a write that cannot be stored is answered 507 and leaves nothing
behind, in memory or on disk; a failed index save never fails the write it follows.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from tests.integration.test_api import AUTH, make_client

FULL_DISK = Path(__file__).with_name("full_disk.py")


def user_namespaces() -> bool:
    if shutil.which("unshare") is None:
        return False
    return subprocess.run(["unshare", "-rm", "true"], capture_output=True).returncode == 0


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.skipif(not user_namespaces(), reason="mounting a small tmpfs (a real full disk) "
                    "needs unprivileged user namespaces, which this kernel does not allow")
def test_a_full_disk_refuses_writes_whole_and_never_fails_a_committed_one(
        tmp_path: Path) -> None:
    mount = tmp_path / "mnt"
    mount.mkdir()
    run = subprocess.run(["unshare", "-rm", sys.executable, str(FULL_DISK), str(mount)],
                         capture_output=True, text=True, timeout=280,
                         cwd=Path(__file__).parents[2])
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout)
    statuses = out["statuses"]
    # writes went through until the disk was full, then one was refused with 507
    assert statuses[-1] == 507 and set(statuses[:-1]) == {200}, statuses
    assert out["refused"]["error"]["code"] == "storage_full"
    # index saves met ENOSPC first, and the writes they followed were still answered 200
    assert out["ok_while_save_failed"] >= 1
    assert any("No space left on device" in w for w in out["warnings"])
    # the refused write left nothing: not in memory, not after a restart
    assert out["size_after_refusal"] == out["acked"] - 20
    assert out["after_room_status"] == 200  # the same process writes on once there is room
    assert out["tmp_files_left"] == []
    assert out["size_after_restart"] == out["acked"]
    assert out["found_themselves"]


def test_a_write_past_the_database_limit_is_507_and_changes_nothing(tmp_path: Path) -> None:
    def post(client: TestClient, n: int) -> int:
        vectors = [[float(i == j % 32) + n for i in range(32)] for j in range(20)]
        ids = [f"b{n}-{j}" for j in range(20)]
        r = client.post("/v1/caches/lim/experiences", headers=AUTH,
                        json={"vectors": vectors, "ids": ids})
        return r.status_code

    with make_client(tmp_path, max_db_bytes=128 * 1024) as client:
        assert client.put("/v1/caches/lim", json={"model": None, "dim": 32},
                          headers=AUTH).status_code == 201
        statuses = [post(client, n) for n in range(100)]
        assert 507 in statuses
        refused = statuses.index(507)
        assert set(statuses[:refused]) == {200}
        size = client.get("/v1/caches/lim").json()["size"]
        assert size == 20 * refused
        r = client.post("/v1/caches/lim/experiences", headers=AUTH,
                        json={"vectors": [[1.0] * 32] * 200})
        assert r.status_code == 507
        assert r.json()["error"]["code"] == "storage_full"
        assert "not written" in r.json()["error"]["message"]
    with make_client(tmp_path) as client:  # no limit now: all acknowledged, nothing else
        assert client.get("/v1/caches/lim").json()["size"] == size
        assert post(client, 1000) == 200


@pytest.mark.parametrize("name", ["abc%0A", "a" * 65, ".hidden", "a%2Fb"])
def test_cache_names_are_matched_whole(tmp_path: Path, name: str) -> None:
    with make_client(tmp_path) as client:
        r = client.put(f"/v1/caches/{name}", json={"model": None, "dim": 4}, headers=AUTH)
        assert r.status_code in (404, 422), r.text
        assert client.get("/v1/caches").json()["caches"] == []
