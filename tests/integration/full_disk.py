"""Child of the full-disk test: the vector-cache service on a tmpfs that fills up.

Run as ``unshare -rm python full_disk.py MOUNTPOINT`` (a user and mount namespace, so
an unprivileged user may mount a small tmpfs: a real disk that runs out of space).
Prints one JSON object describing what happened; the test asserts on it.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient

from services.embedding.api import create_app
from services.embedding.service import CacheService
from services.embedding.settings import EmbeddingSettings, EmbeddingTuning

TOKEN = "full-disk-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
DIM = 128
BATCH = 20


class Warnings(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def client(data: Path) -> TestClient:
    # every commit also saves the index file, so saves meet the full disk too
    settings = EmbeddingSettings(data_dir=data, admin_token=TOKEN, zenoh_worker=False,
                                 fsync=True, tuning=EmbeddingTuning(index_save_changes=1))
    return TestClient(create_app(settings, service=CacheService(settings)), headers=AUTH)


def batch(n: int) -> tuple[list[str], list[list[float]]]:
    rng = np.random.default_rng(n)
    return [f"b{n}-{i}" for i in range(BATCH)], rng.standard_normal((BATCH, DIM)).tolist()


def main(mount: Path) -> dict[str, object]:
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mount)], check=True)
    data, ballast = mount / "data", mount / "ballast"
    ballast.write_bytes(b"\0" * 512 * 1024)
    warnings = Warnings()
    logging.getLogger("services.embedding").addHandler(warnings)
    acked: dict[str, list[float]] = {}
    statuses: list[int] = []
    out: dict[str, object] = {}
    ok_while_save_failed = 0  # writes answered 200 although their index save failed
    with client(data) as c:
        assert c.put("/v1/caches/d", json={"model": None, "dim": DIM}, headers=AUTH).is_success
        for n in range(1000):
            failed_saves = sum("index not saved" in w for w in warnings.lines)
            ids, vecs = batch(n)
            r = c.post("/v1/caches/d/experiences", json={"ids": ids, "vectors": vecs},
                       headers=AUTH)
            statuses.append(r.status_code)
            if r.status_code != 200:
                out["refused"] = r.json()
                break
            acked.update(zip(ids, vecs, strict=True))
            ok_while_save_failed += sum("index not saved" in w for w in warnings.lines) \
                > failed_saves
        out["size_after_refusal"] = c.get("/v1/caches/d").json()["size"]
        ballast.unlink()  # room again: the same process writes on
        ids, vecs = batch(10_000)
        r = c.post("/v1/caches/d/experiences", json={"ids": ids, "vectors": vecs}, headers=AUTH)
        out["after_room_status"] = r.status_code
        if r.status_code == 200:
            acked.update(zip(ids, vecs, strict=True))
    out["tmp_files_left"] = [str(p) for p in data.rglob("*.tmp")]
    with client(data) as c:
        out["size_after_restart"] = c.get("/v1/caches/d").json()["size"]
        sample = list(acked.items())[::7]
        r = c.post("/v1/caches/d/score", json={"vectors": [v for _, v in sample], "k": 1})
        out["found_themselves"] = all(
            res["neighbors"][0]["id"] == ident
            for (ident, _), res in zip(sample, r.json()["results"], strict=True))
    out.update(statuses=statuses, acked=len(acked), warnings=warnings.lines,
               ok_while_save_failed=ok_while_save_failed)
    return out


if __name__ == "__main__":
    print(json.dumps(main(Path(sys.argv[1]))))
