"""A real ``aesop serve embedding`` process killed with SIGKILL in the middle of writes.

Every experience acknowledged with a 2xx must be there after a restart, with its
vector intact; the restarted service keeps accepting writes.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from services.embedding.storage.store import DB_NAME
from shared.process import ServiceFailed, ServiceProcess, free_port

pytestmark = [pytest.mark.timeout(180), pytest.mark.slow]

TOKEN = "crash-test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
DIM = 8


def server(data_dir: Path, port: int) -> ServiceProcess:
    env = {"AESOP_ADMIN_TOKEN": TOKEN, "AESOP_EMBEDDING_ZENOH_WORKER": "false",
           "AESOP_EMBEDDING_TUNING__INDEX_SAVE_CHANGES": "200"}  # small: index saves mid-run too
    return ServiceProcess(["serve", "embedding", "--port", str(port), "--data-dir", str(data_dir)],
                          port=port, env=env, log_path=data_dir / f"server-{port}.log")


def vector(i: int) -> list[float]:
    return np.random.default_rng(i).standard_normal(DIM).tolist()


def writer(base: str, start: int, acked: dict[str, list[float]], stop: threading.Event) -> None:
    i = start
    with httpx.Client(base_url=base, headers=AUTH, timeout=10) as client:
        while not stop.is_set():
            ids = [f"w{start}-{i + j}" for j in range(5)]
            vecs = [vector(i + j) for j in range(5)]
            try:
                r = client.post("/v1/caches/crash/experiences", json={"vectors": vecs, "ids": ids})
            except httpx.TransportError:
                return  # the server died: this batch was never acknowledged
            if r.status_code == 200:
                acked.update(zip(ids, vecs, strict=True))
            i += 5


def test_acknowledged_experiences_survive_sigkill(tmp_path: Path) -> None:
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    acked: dict[str, list[float]] = {}
    with server(tmp_path, port) as proc:
        r = httpx.put(f"{base}/v1/caches/crash", json={"model": None, "dim": DIM}, headers=AUTH)
        assert r.status_code == 201, r.text
        stop = threading.Event()
        threads = [threading.Thread(target=writer, args=(base, n * 1_000_000, acked, stop))
                   for n in range(3)]
        for t in threads:
            t.start()
        deadline = time.monotonic() + 60
        while len(acked) < 600 and time.monotonic() < deadline:
            time.sleep(0.01)
        proc.kill()  # SIGKILL while the writers are still writing
        stop.set()
        for t in threads:
            t.join(10)
    assert len(acked) >= 600

    port = free_port()
    with server(tmp_path, port), \
            httpx.Client(base_url=f"http://127.0.0.1:{port}", headers=AUTH) as client:
        desc = client.get("/v1/caches/crash").json()
        assert desc["size"] >= len(acked)
        for ident in acked:
            assert client.get(f"/v1/caches/crash/experiences/{ident}").status_code == 200
        # vectors are intact: each acknowledged vector finds itself
        sample = list(acked.items())[::50]
        r = client.post("/v1/caches/crash/score", json={"vectors": [v for _, v in sample],
                                                       "k": 1})
        for (ident, _), res in zip(sample, r.json()["results"], strict=True):
            assert res["neighbors"][0]["id"] == ident
            assert res["score"] == pytest.approx(-1.0, abs=1e-5)
        r = client.post("/v1/caches/crash/experiences",
                        json={"vectors": [vector(999_999_999)], "ids": ["after"]})
        assert r.status_code == 200 and r.json()["size"] == desc["size"] + 1


def test_a_corrupt_database_stops_the_service_naming_the_file(tmp_path: Path) -> None:
    port = free_port()
    with server(tmp_path, port):
        r = httpx.put(f"http://127.0.0.1:{port}/v1/caches/c", json={"model": None, "dim": 3},
                      headers=AUTH)
        assert r.status_code == 201
    database = tmp_path / DB_NAME
    data = bytearray(database.read_bytes())
    data[:16] = b"not a database!!"
    database.write_bytes(bytes(data))
    proc = server(tmp_path, free_port())
    with pytest.raises(ServiceFailed) as failed:
        proc.start()
    assert str(database) in str(failed.value)
    assert f"refusing to start: {database}" in proc.log_path.read_text()
    assert proc.proc is not None and proc.proc.returncode != 0
    assert database.read_bytes() == bytes(data)  # never overwritten


def test_a_new_cache_is_durable_once_its_2xx_is_sent(tmp_path: Path) -> None:
    """Issue 14: a cache acknowledged by PUT and killed at once is there after a restart
    (its row is committed, with synchronous=FULL, before the 201 is sent)."""
    port = free_port()
    with server(tmp_path, port) as proc:
        for name in ("fresh-a", "fresh-b"):
            r = httpx.put(f"http://127.0.0.1:{port}/v1/caches/{name}",
                          json={"model": None, "dim": DIM}, headers=AUTH)
            assert r.status_code == 201, r.text
        proc.kill()  # right after the last 201: no clean shutdown, no index save
    port = free_port()
    with server(tmp_path, port), \
            httpx.Client(base_url=f"http://127.0.0.1:{port}", headers=AUTH) as client:
        names = [c["name"] for c in client.get("/v1/caches").json()["caches"]]
        assert {"fresh-a", "fresh-b"} <= set(names)
        assert client.get("/v1/caches/fresh-b").json()["dim"] == DIM
