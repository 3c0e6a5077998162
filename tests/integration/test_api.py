"""The vector-cache HTTP admin API: shapes, validation, auth, persistence across restarts."""

from __future__ import annotations

import json
from collections.abc import Iterator
from functools import partial
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from services.embedding.api import create_app
from services.embedding.models.base import ModelNotFound
from services.embedding.models.loading import EmbedderPool
from services.embedding.service import CacheService
from services.embedding.settings import EmbeddingAdapt, EmbeddingLimits, EmbeddingSettings
from shared.messages import Detection, Observation
from tests.fakes.hash_embedder import HashEmbedder

TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
NOMINAL = [
    f"a {color} package on the conveyor belt next to a {thing}"
    for color in ("brown", "white", "small", "large", "taped", "flat")
    for thing in ("storage shelf", "pallet", "scanner", "worker")
]


def loader(model: str) -> HashEmbedder:
    if model == "missing-model":
        raise ModelNotFound("missing-model: looked in the test's imagination")
    return HashEmbedder(name=f"test/{model.split('/')[-1]}")


def make_client(data_dir: Path, token: str | None = TOKEN, **overrides: object) -> TestClient:
    settings = EmbeddingSettings(data_dir=data_dir, admin_token=token, zenoh_worker=False,
                                 fsync=False, **overrides)
    service = CacheService(settings, embedders=EmbedderPool(loader=loader))
    auth = {"Authorization": f"Bearer {token}"} if token else {}
    return TestClient(create_app(settings, service=service), headers=auth,
                      base_url="http://127.0.0.1:8001")


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with make_client(tmp_path) as c:
        yield c


def create(client: TestClient, name: str = "wm", **body: object) -> dict:
    r = client.put(f"/v1/caches/{name}", json=body, headers=AUTH)
    assert r.status_code in (200, 201), r.text
    return r.json()


def add_texts(client: TestClient, name: str, texts: list[str]) -> dict:
    r = client.post(f"/v1/caches/{name}/experiences", headers=AUTH,
                    json={"items": [{"text": t} for t in texts]})
    assert r.status_code == 200, r.text
    return r.json()


def test_cache_lifecycle_shapes(client: TestClient) -> None:
    r = client.put("/v1/caches/wm", json={"k": 3}, headers=AUTH)
    assert r.status_code == 201
    desc = r.json()
    assert {"name", "size", "dim", "model", "k", "score", "threshold", "calibration",
            "version"} <= desc.keys()
    assert desc["size"] == 0 and desc["dim"] == 64 and desc["k"] == 3
    assert desc["threshold"] is None and desc["calibration"] is None

    added = add_texts(client, "wm", NOMINAL)
    assert len(added["ids"]) == len(NOMINAL) and added["size"] == len(NOMINAL)
    assert added["version"] > desc["version"]

    cal = client.post("/v1/caches/wm/calibrate", headers=AUTH,
                      json={"method": "loo-quantile", "alpha": 0.9}).json()
    assert cal["method"] == "loo-quantile" and cal["alpha"] == 0.9 and cal["n"] == len(NOMINAL)
    got = client.get("/v1/caches/wm").json()
    assert got["threshold"] == cal["threshold"]
    assert got["calibration"]["stale"] is False and got["version"] == cal["version"]

    scored = client.post("/v1/caches/wm/score", json={
        "texts": [NOMINAL[0], "a smoking lithium battery leaking acid everywhere"]}).json()
    near, far = scored["results"]
    assert near["score"] == pytest.approx(-1.0 + 0.0, abs=0.5)  # an exact member is near -1
    assert near["neighbors"][0]["text"] == NOMINAL[0]
    assert near["neighbors"][0]["similarity"] == pytest.approx(1.0, abs=1e-5)
    assert far["score"] > near["score"]
    assert far["is_anomaly"] is True and near["is_anomaly"] is False
    assert scored["threshold"] == cal["threshold"] and scored["version"] == cal["version"]

    # adding experiences marks the calibration stale and changes the version
    more = add_texts(client, "wm", ["a blue package on the conveyor belt"])
    got = client.get("/v1/caches/wm").json()
    assert got["calibration"]["stale"] is True and got["version"] == more["version"]
    assert client.get("/v1/caches").json()["caches"][0]["name"] == "wm"


def test_put_is_idempotent_and_refuses_a_model_change(client: TestClient) -> None:
    assert client.put("/v1/caches/c", json={}, headers=AUTH).status_code == 201
    assert client.put("/v1/caches/c", json={}, headers=AUTH).status_code == 200
    r = client.put("/v1/caches/c", json={"model": "other-model"}, headers=AUTH)
    assert r.status_code == 409 and r.json()["error"]["field"] == "model"
    r = client.put("/v1/caches/d", json={"model": "missing-model"}, headers=AUTH)
    assert r.status_code == 422 and r.json()["error"]["field"] == "model"
    assert "imagination" in r.json()["error"]["message"]
    r = client.put("/v1/caches/bad name!", json={}, headers=AUTH)
    assert r.status_code == 422 and r.json()["error"]["field"] == "name"


def test_experience_get_and_delete(client: TestClient) -> None:
    create(client)
    ids = add_texts(client, "wm", NOMINAL[:3])["ids"]
    r = client.post("/v1/caches/wm/experiences", headers=AUTH, json={
        "items": [{"text": "a pallet", "id": "pallet-1", "metadata": {"run": 7}}]})
    assert r.json()["ids"] == ["pallet-1"]
    assert client.get("/v1/caches/wm/experiences/pallet-1").json() == {
        "id": "pallet-1", "text": "a pallet", "metadata": {"run": 7}, "detections": []}
    r = client.delete(f"/v1/caches/wm/experiences/{ids[0]}", headers=AUTH)
    assert r.status_code == 200 and r.json()["size"] == 3
    assert client.get(f"/v1/caches/wm/experiences/{ids[0]}").status_code == 404
    assert client.delete(f"/v1/caches/wm/experiences/{ids[0]}", headers=AUTH).status_code == 404


BAD_REQUESTS = [
    # (method, path, body, status, field)
    ("post", "/v1/caches/wm/experiences", {"items": [{"text": ""}]}, 422, "items[0].text"),
    ("post", "/v1/caches/wm/experiences", {"items": [{"text": "ok"}, {"text": "   "}]}, 422,
     "items[1].text"),
    ("post", "/v1/caches/wm/experiences", {"items": [{"text": "x" * 5000}]}, 422,
     "items[0].text"),
    ("post", "/v1/caches/wm/experiences", {"items": []}, 422, "items"),
    ("post", "/v1/caches/wm/experiences", {"items": [{"text": "a"}] * 101}, 413, "items"),
    # a vector of another dimension conflicts with the cache's pinned one
    ("post", "/v1/caches/wm/experiences", {"vectors": [[0.1] * 63]}, 409, "vectors[0]"),
    ("post", "/v1/caches/wm/experiences", {"vectors": [[0.0] * 64]}, 422, "vectors[0]"),
    ("post", "/v1/caches/wm/experiences", {"vectors": [[1.0] * 64], "items": []}, 422, "items"),
    ("post", "/v1/caches/wm/experiences", {"vectors": [[1.0] * 64], "items": [{"text": "a"}]},
     422, "body"),
    ("post", "/v1/caches/wm/experiences", {"vectors": [[1.0] * 64], "ids": None}, 422, "body"),
    ("post", "/v1/caches/wm/experiences", {"items": [{"text": "a", "id": "e0"},
                                                      {"text": "b", "id": "e0"}]}, 422,
     "items[1].id"),
    ("post", "/v1/caches/wm/experiences", {"items": [{"text": "a", "id": "known"}]}, 409,
     "items[0].id"),
    ("post", "/v1/caches/nope/experiences", {"items": [{"text": "a"}]}, 404, "name"),
    ("post", "/v1/caches/wm/calibrate", {"method": "loo-quantile", "alpha": 1.0}, 422, "alpha"),
    ("post", "/v1/caches/wm/calibrate", {"method": "loo-quantile", "alpha": 0}, 422, "alpha"),
    ("post", "/v1/caches/wm/calibrate", {"method": "magic"}, 422, "method"),
    ("post", "/v1/caches/wm/calibrate", {"method": "conformal"}, 422, "calibration"),
    ("post", "/v1/caches/wm/calibrate", {"method": "tpr-target", "calibration": [
        {"text": "a package", "label": "nominal"}]}, 422, "calibration"),
    ("post", "/v1/caches/wm/calibrate", {"method": "conformal", "alpha": 0.99, "calibration": [
        {"text": f"a package {i}", "label": "nominal"} for i in range(10)]}, 422, "alpha"),
    ("post", "/v1/caches/wm/score", {"texts": ["a"], "k": 50}, 409, "k"),  # the cache is smaller
    ("post", "/v1/caches/wm/score", {"texts": []}, 422, "texts"),
    ("post", "/v1/caches/wm/score", {"vectors": [[1.0] * 3]}, 409, "vectors[0]"),
    ("post", "/v1/caches/wm/score", {"texts": ["a"], "vectors": [[1.0] * 64]}, 422, "body"),
    ("post", "/v1/caches/nope/score", {"texts": ["a"]}, 404, "name"),
    ("put", "/v1/caches/wm", {"k": 0}, 422, "k"),
    ("put", "/v1/caches/wm", {"score": "cosine"}, 422, "score"),
]


@pytest.mark.parametrize(("method", "path", "body", "status", "field"), BAD_REQUESTS)
def test_bad_input_names_the_field_and_changes_nothing(
    tmp_path: Path, method: str, path: str, body: dict, status: int, field: str
) -> None:
    with make_client(tmp_path, limits=EmbeddingLimits(max_items=100)) as client:
        create(client, k=3)
        add_texts(client, "wm", NOMINAL[:10])
        client.post("/v1/caches/wm/experiences", headers=AUTH,
                    json={"items": [{"text": "known thing", "id": "known"}]})
        before = client.get("/v1/caches/wm").json()
        r = getattr(client, method)(path, json=body, headers=AUTH)
        assert r.status_code == status, r.text
        error = r.json()["error"]
        assert error["field"] == field and error["message"] and error["code"]
        assert client.get("/v1/caches/wm").json() == before


@pytest.mark.parametrize("payload", [
    b'{"items": [{"text": "a"}',  # truncated
    b'{"vectors": [[NaN, 1.0]]}',  # NaN is not JSON
    b'{"vectors": [[Infinity, 1.0]]}',
])
def test_malformed_json_and_non_finite_numbers(client: TestClient, payload: bytes) -> None:
    create(client)
    before = client.get("/v1/caches/wm").json()
    r = client.post("/v1/caches/wm/experiences", content=payload,
                    headers={**AUTH, "Content-Type": "application/json"})
    assert r.status_code in (400, 422)
    assert r.json()["error"]["field"].startswith(("body", "vectors"))
    assert client.get("/v1/caches/wm").json() == before


def test_a_body_that_is_not_json_is_refused_with_415(client: TestClient) -> None:
    r = client.put("/v1/caches/wm", content=b'{"k": 1}', headers={
        **AUTH, "Content-Type": "application/x-www-form-urlencoded"})
    assert r.status_code == 415 and r.json()["error"]["field"] == "Content-Type"
    assert client.get("/v1/caches/wm").status_code == 404


def test_a_limit_refused_names_the_setting_that_raises_it(tmp_path: Path) -> None:
    """docs/operations.md, "Limits": each refusal names the variable to change."""
    with make_client(tmp_path, max_body_bytes=8192) as client:
        create(client, k=3)
        r = client.post("/v1/caches/wm/experiences", headers=AUTH,
                        json={"items": [{"text": "a package " * 100}] * 10})
        assert r.status_code == 413, r.text
        assert r.json()["error"] == {
            "code": "too_large", "field": "body",
            "message": "request body is over the limit of 8192 bytes "
                       "(AESOP_EMBEDDING_MAX_BODY_BYTES)"}
        for path, body, field in [
                ("/v1/caches/wm/experiences", {"items": [{"text": "x" * 4001}]},
                 "items[0].text"),
                ("/v1/caches/wm/score", {"texts": ["x" * 4001]}, "texts[0]"),
                ("/v1/caches/wm/calibrate", {"method": "loo-quantile", "calibration": [
                    {"text": "x" * 4001, "label": "nominal"}]}, "calibration[0].text")]:
            r = client.post(path, headers=AUTH, json=body)
            assert r.status_code == 422, r.text
            assert r.json()["error"]["field"] == field
            assert r.json()["error"]["message"] == (
                "text has 4001 characters; the limit is 4000 "
                "(AESOP_EMBEDDING_LIMITS__MAX_TEXT_CHARS)"), r.text


def test_vectors_of_huge_or_tiny_numbers_keep_their_direction(client: TestClient) -> None:
    """Scaled to unit length in float64 before float32: neither overflows nor vanishes."""
    create(client, "raw", model=None, dim=2)
    r = client.post("/v1/caches/raw/experiences", headers=AUTH,
                    json={"vectors": [[1e300, 0.0], [0.0, 1e-300]], "ids": ["x", "y"]})
    assert r.status_code == 200, r.text
    r = client.post("/v1/caches/raw/score", json={"vectors": [[3e-310, 0.0]], "k": 1})
    assert r.json()["results"][0]["neighbors"][0]["id"] == "x"
    assert r.json()["results"][0]["score"] == pytest.approx(-1.0)


def test_every_route_but_the_ops_ones_needs_the_token(client: TestClient) -> None:
    """Issue 14: scoring was open to anyone (and shares the compute with the bus verdicts)."""
    create(client)
    del client.headers["Authorization"]
    assert client.put("/v1/caches/wm", json={}).status_code == 401
    bad = {"Authorization": "Bearer wrong-token-0123456789"}
    r = client.put("/v1/caches/wm", json={}, headers=bad)
    assert r.status_code == 401 and r.json()["error"]["field"] == "Authorization"
    for method, path, body in [
        ("post", "/v1/caches/wm/experiences", {"items": [{"text": "a"}]}),
        ("post", "/v1/caches/wm/calibrate", {"method": "loo-quantile"}),
        ("delete", "/v1/caches/wm/experiences/x", None),
        ("post", "/v1/caches/wm/score", {"texts": ["a"]}),
        ("get", "/v1/caches/wm", None),
        ("get", "/v1/caches", None),
        ("get", "/v1/jobs/j1", None),
    ]:
        kwargs = {"json": body} if body is not None else {}
        assert getattr(client, method)(path, **kwargs).status_code == 401, path
    for path in ("/healthz", "/readyz", "/metrics"):
        assert client.get(path).status_code == 200, path


def test_state_survives_a_restart(tmp_path: Path) -> None:
    with make_client(tmp_path) as client:
        create(client, k=2)
        add_texts(client, "wm", NOMINAL)
        client.post("/v1/caches/wm/calibrate", headers=AUTH, json={"method": "loo-quantile"})
        ident = add_texts(client, "wm", ["one more"])["ids"][0]
        client.delete(f"/v1/caches/wm/experiences/{ident}", headers=AUTH)
        before = client.get("/v1/caches/wm").json()
        scores = client.post("/v1/caches/wm/score", json={"texts": NOMINAL[:3]}).json()
    with make_client(tmp_path) as client:
        assert client.get("/v1/caches/wm").json() == before
        again = client.post("/v1/caches/wm/score", json={"texts": NOMINAL[:3]}).json()
        assert again == scores


def test_async_build_reports_progress_through_a_job(client: TestClient) -> None:
    create(client)
    r = client.post("/v1/caches/wm/experiences?wait=false", headers=AUTH,
                    json={"items": [{"text": t} for t in NOMINAL]})
    assert r.status_code == 202
    job_id = r.json()["job"]
    for _ in range(200):
        job = client.get(f"/v1/jobs/{job_id}").json()
        if job["state"] != "running":
            break
    assert job["state"] == "succeeded", job
    assert job["done"] == job["total"] == len(NOMINAL)
    assert len(job["result"]["ids"]) == len(NOMINAL)
    assert client.get("/v1/caches/wm").json()["size"] == len(NOMINAL)
    assert client.get("/v1/jobs/unknown").status_code == 404


def test_tpr_target_and_conformal(client: TestClient) -> None:
    create(client, k=1)
    add_texts(client, "wm", NOMINAL)
    labelled = [{"text": t + " today", "label": "nominal"} for t in NOMINAL[:12]] + [
        {"text": t, "label": "anomaly"} for t in (
            "a leaking bleach bottle", "two forklifts in collision", "a fire near the dock",
            "a smoking lithium battery")]
    r = client.post("/v1/caches/wm/calibrate", headers=AUTH,
                    json={"method": "tpr-target", "tpr": 0.75, "calibration": labelled})
    assert r.status_code == 200, r.text
    cal = r.json()
    assert cal["method"] == "tpr-target" and cal["tpr"] >= 0.75 and 0 <= cal["auroc"] <= 1
    roc = cal["roc"]
    assert roc["fpr"][0] == roc["tpr"][0] == 0.0 and roc["fpr"][-1] == roc["tpr"][-1] == 1.0
    assert roc["thresholds"][0] is None and len(roc["fpr"]) == len(roc["thresholds"])
    r = client.post("/v1/caches/wm/calibrate", headers=AUTH,
                    json={"method": "conformal", "alpha": 0.9, "calibration": labelled})
    assert r.status_code == 200, r.text
    assert r.json()["n"] == 12 and r.json()["method"] == "conformal"


def test_ops_routes(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.get("/readyz").status_code == 200
    create(client)
    add_texts(client, "wm", NOMINAL[:4])
    text = client.get("/metrics").text
    assert 'aesop_embedding_cache_size{cache="wm"} 4.0' in text
    assert "aesop_http_requests_total" in text


def test_vectors_only_cache(client: TestClient) -> None:
    r = client.put("/v1/caches/raw", json={"model": None, "dim": 3}, headers=AUTH)
    assert r.status_code == 201 and r.json()["model"] is None
    r = client.post("/v1/caches/raw/experiences", headers=AUTH,
                    json={"vectors": [[1, 0, 0], [0, 1, 0], [0, 0, 2]], "ids": ["x", "y", "z"]})
    assert r.json()["ids"] == ["x", "y", "z"]
    r = client.post("/v1/caches/raw/score", json={"vectors": [[0, 0, 5]], "k": 1})
    assert r.json()["results"][0]["score"] == pytest.approx(-1.0)
    assert r.json()["results"][0]["neighbors"][0]["id"] == "z"
    r = client.post("/v1/caches/raw/experiences", headers=AUTH, json={"items": [{"text": "a"}]})
    assert r.status_code == 409 and r.json()["error"]["field"] == "items"
    assert json.loads(client.get("/v1/caches/raw").text)["dim"] == 3


@pytest.mark.parametrize("model", ["m" * 500, "no/such-model", "/no/such/directory"])
def test_a_model_this_machine_lacks_is_422_naming_the_field(tmp_path: Path, model: str) -> None:
    """The real model lookup (no test loader): a name too long for the file system is
    looked up like any other (it was a 500: OSError, file name too long)."""
    settings = EmbeddingSettings(data_dir=tmp_path, admin_token=TOKEN, zenoh_worker=False,
                                 fsync=False)
    with TestClient(create_app(settings, service=CacheService(settings))) as client:
        r = client.put("/v1/caches/c", json={"model": model}, headers=AUTH)
        assert r.status_code == 422, r.text
        assert r.json()["error"]["field"] == "model"
        assert client.get("/v1/caches", headers=AUTH).json()["caches"] == []


# -- detections ----------------------------------------------------------------------

THINGS = ["a pallet", "a scanner", "a storage shelf", "a worker", "a brown package"]


def scene(i: int) -> dict:
    held = [THINGS[j % len(THINGS)] for j in (i, i + 1, i + 2)]
    return {"text": f"scene {i}: " + ", ".join(held), "id": f"s{i}",
            "detections": [{"label": x, "where": "on the belt"} for x in held]}


def test_experiences_with_detections_name_the_odd_one_in_a_verdict(tmp_path: Path) -> None:
    with make_client(tmp_path) as client:
        create(client, k=1)
        r = client.post("/v1/caches/wm/experiences", headers=AUTH,
                        json={"items": [scene(i) for i in range(40)]})
        assert r.status_code == 200, r.text
        info = client.get("/v1/caches/wm").json()
        assert info["detections"] == len(THINGS)
        exp = client.get("/v1/caches/wm/experiences/s0").json()
        assert [{k: d[k] for k in ("label", "where")} for d in exp["detections"]] \
            == scene(0)["detections"]
        r = client.post("/v1/caches/wm/calibrate", headers=AUTH,
                        json={"method": "loo-quantile", "alpha": 0.9})
        assert r.status_code == 200, r.text
        odd = [{"label": "a pallet", "where": "on the belt"},
               {"label": "a burning battery", "where": "on the belt"}]
        body = {"queries": [{"text": scene(3)["text"], "detections": scene(3)["detections"]},
                            {"text": scene(3)["text"], "detections": odd}]}
        first = client.post("/v1/caches/wm/score", json=body).json()
    nominal, anomalous = first["results"]
    assert nominal["is_anomaly"] is False and nominal["p_value"] == 1.0
    assert nominal["detections"] == []
    assert anomalous["is_anomaly"] is True and anomalous["p_value"] < 0.1
    (named,) = anomalous["detections"]
    assert named["detection"] == "a burning battery on the belt"
    assert named["nearest"] in [f"{x} on the belt" for x in THINGS]
    assert named["similarity"] < 1 and named["p_value"] is not None
    with make_client(tmp_path) as client:  # the detections and the calibration are kept
        assert client.post("/v1/caches/wm/score", json=body).json() == first


@pytest.mark.parametrize(("body", "field"), [
    ({"texts": ["a"], "queries": [{"text": "a"}]}, "body"),
    ({"queries": [{"text": "a", "detections": [{"where": "on the belt"}]}]},
     "queries[0].detections[0].label"),
    ({"queries": [{"text": "a", "detections": [{"label": "x" * 201}]}]},
     "queries[0].detections[0].label"),
    ({"queries": [{"text": "a" * 5000}]}, "queries[0].text"),
])
def test_bad_detections_in_a_score_request_are_422_naming_the_field(
        client: TestClient, body: dict, field: str) -> None:
    create(client, k=1)
    add_texts(client, "wm", NOMINAL[:3])
    r = client.post("/v1/caches/wm/score", json=body)
    assert r.status_code == 422, r.text
    assert r.json()["error"]["field"].startswith(field)


def test_detections_on_a_cache_without_a_model_are_refused(client: TestClient) -> None:
    create(client, "raw", model=None, dim=2)
    r = client.post("/v1/caches/raw/experiences", headers=AUTH,
                    json={"items": [scene(0)]})
    assert r.status_code == 409 and r.json()["error"]["field"] == "items"
    assert client.get("/v1/caches/raw").json()["size"] == 0


def test_too_few_scenes_with_detections_to_ever_flag_is_refused(client: TestClient) -> None:
    create(client, k=1)
    client.post("/v1/caches/wm/experiences", headers=AUTH,
                json={"items": [scene(i) for i in range(12)]})
    r = client.post("/v1/caches/wm/calibrate", headers=AUTH,
                    json={"method": "loo-quantile", "alpha": 0.95})
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["field"] == "alpha" and "at least 40" in error["message"]
    assert client.get("/v1/caches/wm").json()["calibration"] is None


def neighbours(i: int) -> dict:
    """A scene of two things next to each other in THINGS (a ring): a pallet is seen
    with a scanner and with a brown package, never with a storage shelf."""
    held = [THINGS[i % len(THINGS)], THINGS[(i + 1) % len(THINGS)]]
    return {"text": f"scene {i}: " + ", ".join(held), "id": f"n{i}",
            "detections": [{"label": x, "where": "on the belt"} for x in held]}


def test_two_things_never_seen_together_are_named_when_pairs_are_calibrated(
        tmp_path: Path) -> None:
    with make_client(tmp_path) as client:
        create(client, k=1)
        client.post("/v1/caches/wm/experiences", headers=AUTH,
                    json={"items": [neighbours(i) for i in range(40)]})
        # the text of a nominal scene: only the pair can tell
        odd = {"text": neighbours(0)["text"], "detections": [
            {"label": "a pallet", "where": "on the belt"},
            {"label": "a storage shelf", "where": "on the belt"}]}
        body = {"queries": [odd, {"text": neighbours(0)["text"],
                                  "detections": neighbours(0)["detections"]}]}
        r = client.post("/v1/caches/wm/calibrate", headers=AUTH,
                        json={"method": "loo-quantile", "alpha": 0.9})
        assert r.status_code == 200 and r.json()["pairs"] is False
        before = client.post("/v1/caches/wm/score", json=body).json()["results"][0]
        assert before["is_anomaly"] is False and before["pair"] is None  # each is nominal
        r = client.post("/v1/caches/wm/calibrate", headers=AUTH,
                        json={"method": "loo-quantile", "alpha": 0.9, "pairs": True})
        assert r.status_code == 200 and r.json()["pairs"] is True
        assert client.get("/v1/caches/wm").json()["calibration"]["pairs"] is True
        first = client.post("/v1/caches/wm/score", json=body).json()
    flagged, nominal = first["results"]
    assert flagged["is_anomaly"] is True and flagged["detections"] == []
    assert flagged["pair"]["detections"] == ["a pallet on the belt",
                                             "a storage shelf on the belt"]
    assert flagged["pair"]["similarity"] < 1 and flagged["pair"]["p_value"] < 0.1
    assert nominal["is_anomaly"] is False and nominal["pair"] is None
    with make_client(tmp_path) as client:  # the pair scores are kept
        assert client.post("/v1/caches/wm/score", json=body).json() == first


@pytest.mark.parametrize(("body", "status"), [
    ({"method": "loo-quantile", "pairs": "yes"}, 422),
    ({"method": "tpr-target", "pairs": True,
      "calibration": [{"text": "a", "label": "nominal"}, {"text": "b", "label": "anomaly"}]},
     422),
    ({"method": "loo-quantile", "pairs": True}, 409),  # no scene holds two things
])
def test_pairs_that_cannot_be_calibrated_are_refused_naming_pairs(
        client: TestClient, body: dict, status: int) -> None:
    create(client, k=1)
    client.post("/v1/caches/wm/experiences", headers=AUTH, json={"items": [
        {"text": f"scene {i}", "detections": [{"label": THINGS[i % 5]}]} for i in range(40)]})
    r = client.post("/v1/caches/wm/calibrate", headers=AUTH, json=body)
    assert r.status_code == status, r.text
    assert r.json()["error"]["field"] == "pairs"
    assert client.get("/v1/caches/wm").json()["calibration"] is None


# -- proposals -------------------------------------------------------------------------


def propose(client: TestClient, label: str, seq: int = 1) -> str:
    """What the Zenoh worker does when the reasoner answers "continue" for a flagged
    scene (tests/integration/test_worker.py drives it over Zenoh)."""
    service = client.app.state.service  # type: ignore[attr-defined]
    obs = Observation(robot="drone7", seq=seq, text=f"a pallet\n{label}", detections=(
        Detection(label="a pallet", where="on the belt"),
        Detection(label=label, where="on the belt")))
    made = client.portal.call(partial(  # type: ignore[union-attr]
        service.review.propose, "wm", obs, request_id=f"r{seq}", model="llm", rationale="harmless",
        score=-0.5, p_value=0.01, now=100.0 + seq))
    assert made is not None
    return str(made.id)


def test_proposals_are_listed_and_accepted_or_rejected_with_the_token(
        tmp_path: Path) -> None:
    with make_client(tmp_path) as client:
        create(client, k=1)
        client.post("/v1/caches/wm/experiences", headers=AUTH,
                    json={"items": [scene(i) for i in range(40)]})
        client.post("/v1/caches/wm/calibrate", headers=AUTH, json={"method": "loo-quantile"})
        assert client.get("/v1/caches/wm/proposals").json() == {
            "cache": "wm", "policy": "review", "proposals": []}
        keep, drop = propose(client, "a mop"), propose(client, "a cat", seq=2)
        listed = client.get("/v1/caches/wm/proposals").json()["proposals"]
        assert [(p["id"], p["state"], p["count"]) for p in listed] == [
            (keep, "pending", 1), (drop, "pending", 1)]
        assert listed[0]["text"] == "a pallet\na mop" and listed[0]["rationale"] == "harmless"
        before = client.get("/v1/caches/wm").json()

        anonymous = {"Authorization": ""}
        assert client.post(f"/v1/caches/wm/proposals/{keep}/accept",
                           headers=anonymous).status_code == 401
        r = client.post(f"/v1/caches/wm/proposals/{keep}/accept", headers=AUTH)
        assert r.status_code == 200, r.text
        assert r.json()["state"] == "accepted" and r.json()["decided_at"] is not None
        after = client.get("/v1/caches/wm").json()
        assert after["size"] == before["size"] + 1 and after["version"] == before["version"] + 1
        assert after["calibration"]["stale"] is True
        exp = client.get(f"/v1/caches/wm/experiences/{keep}").json()
        assert exp["text"] == "a pallet\na mop" and exp["metadata"]["proposal"]["robot"] == "drone7"
        r = client.post(f"/v1/caches/wm/proposals/{keep}/reject", headers=AUTH)
        assert r.status_code == 409 and r.json()["error"]["field"] == "id"

        r = client.post(f"/v1/caches/wm/proposals/{drop}/reject", headers=AUTH)
        assert r.status_code == 200 and r.json()["state"] == "rejected"
        assert client.get("/v1/caches/wm").json()["size"] == after["size"]
        assert propose(client, "a cat", seq=3) == drop  # proposed again: counted, rejected
        pending = client.get("/v1/caches/wm/proposals?state=pending").json()["proposals"]
        assert pending == []
        rejected = client.get("/v1/caches/wm/proposals?state=rejected").json()["proposals"]
        assert [(p["id"], p["count"]) for p in rejected] == [(drop, 2)]
        r = client.post("/v1/caches/wm/proposals/rec-nothing/accept", headers=AUTH)
        assert r.status_code == 404 and r.json()["error"]["field"] == "id"
        r = client.get("/v1/caches/wm/proposals?state=maybe")
        assert r.status_code == 422 and r.json()["error"]["field"] == "state"
    with make_client(tmp_path) as client:  # kept across a restart
        got = client.get("/v1/caches/wm/proposals").json()["proposals"]
        assert [(p["id"], p["state"]) for p in got] == [(keep, "accepted"), (drop, "rejected")]


def test_the_proposal_policy_is_set_with_put_and_kept(tmp_path: Path) -> None:
    with make_client(tmp_path) as client:
        assert create(client)["proposals"] == "review"
        calibrated = client.post("/v1/caches/wm/experiences", headers=AUTH,
                                 json={"items": [scene(i) for i in range(40)]})
        assert calibrated.status_code == 200
        client.post("/v1/caches/wm/calibrate", headers=AUTH, json={"method": "loo-quantile"})
        assert create(client, proposals="auto")["proposals"] == "auto"
        info = client.get("/v1/caches/wm").json()
        assert info["calibration"]["stale"] is False  # the policy is not the score
        r = client.put("/v1/caches/wm", json={"proposals": None}, headers=AUTH)
        assert r.status_code == 422 and r.json()["error"]["field"] == "body"
        r = client.put("/v1/caches/wm", json={"proposals": "sometimes"}, headers=AUTH)
        assert r.status_code == 422 and r.json()["error"]["field"] == "proposals"
        made = propose(client, "a mop")
        assert client.get("/v1/caches/wm/proposals").json()["proposals"][0]["state"] == \
            "accepted"
        assert client.get(f"/v1/caches/wm/experiences/{made}").status_code == 200
    with make_client(tmp_path) as client:
        assert client.get("/v1/caches/wm").json()["proposals"] == "auto"


def test_a_put_naming_one_field_changes_only_that_field(tmp_path: Path) -> None:
    """docs/embedding.md's ``PUT caches/scene {"proposals": "auto"}`` on a cache made with
    k=1 and calibrated (issue 44): the policy changes, and nothing it did not name (k, the
    score, the calibration and whether it is stale) does."""
    with make_client(tmp_path) as client:
        create(client, k=1, score="mahalanobis")
        r = client.post("/v1/caches/wm/experiences", headers=AUTH,
                        json={"items": [scene(i) for i in range(40)]})
        assert r.status_code == 200, r.text
        r = client.post("/v1/caches/wm/calibrate", headers=AUTH, json={"method": "loo-quantile"})
        assert r.status_code == 200, r.text
        before = client.get("/v1/caches/wm").json()
        assert before["k"] == 1 and before["calibration"]["stale"] is False

        after = create(client, proposals="auto")
        assert after["proposals"] == "auto"
        assert after == client.get("/v1/caches/wm").json()
        unchanged = {key for key in before if key not in ("proposals", "version")}
        assert {key: after[key] for key in unchanged} == {key: before[key] for key in unchanged}
        assert after["k"] == 1 and after["score"] == "mahalanobis"
        assert after["calibration"] == before["calibration"]  # still fresh, same tau


def test_a_put_without_a_model_leaves_a_cache_of_another_model_alone(tmp_path: Path) -> None:
    """A cache pinned to a model other than the service's default: a PUT that names no model
    is no request to change it (no 409), and changes what it names."""
    with make_client(tmp_path) as client:
        assert create(client, model="other-model", k=1)["model"] == "test/other-model"
        r = client.put("/v1/caches/wm", json={"proposals": "auto"}, headers=AUTH)
        assert r.status_code == 200, r.text
        assert r.json()["model"] == "test/other-model" and r.json()["k"] == 1
        assert r.json()["proposals"] == "auto"


def test_a_batch_review_accepts_in_order_recalibrates_on_the_accepted_and_checks_first(
        tmp_path: Path) -> None:
    """Select many, accept: each scene added, then, under the policy ``window``, the
    calibration recomputed on the accepted scenes alone (their leave-one-out scores,
    split-conformal, the same alpha); a batch naming a bad id changes nothing."""
    with make_client(tmp_path) as client:
        create(client, k=1)
        client.post("/v1/caches/wm/experiences", headers=AUTH,
                    json={"items": [scene(i) for i in range(40)]})
        client.post("/v1/caches/wm/calibrate", headers=AUTH,
                    json={"method": "loo-quantile", "alpha": 0.95})
        ids = [propose(client, f"a crate number {i}", seq=i) for i in range(45)]
        before = client.get("/v1/caches/wm").json()

        for body, status, field in (
                ({"ids": [ids[0], "rec-nothing"]}, 404, "ids[1]"),
                ({"ids": [ids[0], ids[0]]}, 422, "ids[1]"),
                ({"ids": []}, 422, "ids"),
                ({"id": ids[0]}, 422, "ids")):
            r = client.post("/v1/caches/wm/proposals/accept", headers=AUTH, json=body)
            assert r.status_code == status, r.text
            assert r.json()["error"]["field"] == field
        assert client.get("/v1/caches/wm").json() == before  # nothing changed
        assert client.post("/v1/caches/wm/proposals/accept", json={"ids": ids[:1]},
                           headers={"Authorization": ""}).status_code == 401

        r = client.post("/v1/caches/wm/proposals/accept", headers=AUTH, json={"ids": ids})
        assert r.status_code == 200, r.text
        got = r.json()
        assert [p["id"] for p in got["proposals"]] == ids
        assert {p["state"] for p in got["proposals"]} == {"accepted"}
        cache = got["cache"]
        assert cache["size"] == before["size"] + 45
        assert cache["calibration"]["method"] == "conformal"
        assert cache["calibration"]["alpha"] == 0.95 and cache["calibration"]["n"] == 45
        assert cache["calibration"]["stale"] is False
        first = client.get(f"/v1/caches/wm/experiences/{ids[0]}").json()["metadata"]
        assert first["proposal"]["robot"] == "drone7"  # what marks an accepted scene
        r = client.post("/v1/caches/wm/proposals/reject", headers=AUTH, json={"ids": ids[:1]})
        assert r.status_code == 409 and r.json()["error"]["field"] == "ids[0]"
    with make_client(tmp_path) as client:  # the recalibration is kept
        assert client.get("/v1/caches/wm").json()["calibration"]["method"] == "conformal"


def test_under_the_policy_stale_a_batch_review_keeps_the_calibration(tmp_path: Path) -> None:
    with make_client(tmp_path, adapt=EmbeddingAdapt(recalibrate="stale")) as client:
        create(client, k=1)
        client.post("/v1/caches/wm/experiences", headers=AUTH,
                    json={"items": [scene(i) for i in range(40)]})
        client.post("/v1/caches/wm/calibrate", headers=AUTH, json={"method": "loo-quantile"})
        ids = [propose(client, f"a crate number {i}", seq=i) for i in range(45)]
        r = client.post("/v1/caches/wm/proposals/reject", headers=AUTH, json={"ids": ids[:2]})
        assert [p["state"] for p in r.json()["proposals"]] == ["rejected", "rejected"]
        r = client.post("/v1/caches/wm/proposals/accept", headers=AUTH, json={"ids": ids[2:]})
        calibration = r.json()["cache"]["calibration"]
        assert calibration["method"] == "loo-quantile" and calibration["stale"] is True
