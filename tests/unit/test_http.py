"""The HTTP pieces every service shares: error bodies, documented errors and limits."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi import FastAPI, WebSocket
from fastapi.testclient import TestClient
from prometheus_client import CollectorRegistry
from pydantic import BaseModel, SecretStr
from starlette.websockets import WebSocketDisconnect

from shared.http import (
    REQUEST_ERRORS,
    document_limits,
    errors,
    field_path,
    install_error_handlers,
    service_app,
)


class Body(BaseModel):
    names: list[str] | None = None


def app() -> FastAPI:
    app = FastAPI(responses=errors(*REQUEST_ERRORS))
    install_error_handlers(app)
    document_limits(app, {"Body": {"names": {"maxItems": 3, "items": {"maxLength": 9}}}})

    @app.get("/things/{name}")
    async def get_thing(name: str) -> dict[str, str]:
        return {"name": name}

    @app.delete("/things/{name}", responses=errors(404))
    async def delete_thing(name: str) -> dict[str, str]:
        return {"name": name}

    @app.post("/things")
    async def post_things(body: Body) -> Body:
        return body

    return app


def test_a_wrong_method_is_405_with_every_allowed_method_of_the_path() -> None:
    with TestClient(app()) as client:
        r = client.request("OPTIONS", "/things/a")
    assert r.status_code == 405
    assert r.headers["Allow"] == "DELETE, GET"  # from both routes of the path
    assert r.json()["error"]["code"] == "method_not_allowed"


def test_starlettes_own_errors_use_the_error_body() -> None:
    with TestClient(app()) as client:
        missing = client.get("/nowhere")
        unparsable = client.post("/things", content=b"\xff\xfe",
                                 headers={"Content-Type": "application/json"})
    assert missing.status_code == 404 and missing.json()["error"]["code"] == "not_found"
    assert unparsable.status_code == 400
    assert unparsable.json()["error"]["field"] == "body"


def test_errors_and_limits_are_published() -> None:
    schema = app().openapi()
    post = schema["paths"]["/things"]["post"]["responses"]
    assert set(post) >= {"200", "400", "413", "415", "422"}
    assert post["422"]["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorBody")
    assert "404" in schema["paths"]["/things/{name}"]["delete"]["responses"]
    names = schema["components"]["schemas"]["Body"]["properties"]["names"]["anyOf"]
    array = next(b for b in names if b.get("type") == "array")
    assert array["maxItems"] == 3 and array["items"]["maxLength"] == 9
    assert {"type": "null"} in names  # the null branch is left alone


def test_field_paths_leave_out_the_union_member_pydantic_tried() -> None:
    assert field_path(("body", "items", 3, "text")) == "items[3].text"
    assert field_path(("body", "texts", "list[constrained-str]", 0)) == "texts[0]"
    assert field_path(("body",)) == "body"


# --- the guard every service app has (issue 14: auth before the body, a real body limit) ---

GUARD_TOKEN = "t" * 24


def guarded(token: str | None = GUARD_TOKEN, max_body_bytes: int = 1024,
            public: tuple[str, ...] = ()) -> FastAPI:
    app = service_app("test", service="test", lifespan=None, registry=CollectorRegistry(),
                      ready=lambda: None, admin_token=SecretStr(token) if token else None,
                      max_body_bytes=max_body_bytes, public=public)

    @app.post("/things")
    async def post_things(body: Body) -> Body:
        return body

    @app.get("/things")
    async def list_things() -> Body:
        return Body(names=["a"])

    return app


def chunks(total: int, size: int = 4096) -> Iterator[bytes]:
    """A JSON body sent chunked, without Content-Length."""
    yield b'{"names": ["'
    sent = 0
    while sent < total:
        yield b"x" * size
        sent += size
    yield b'"]}'


AUTH = {"Authorization": f"Bearer {GUARD_TOKEN}", "Content-Type": "application/json"}


def test_a_chunked_body_past_the_limit_is_413() -> None:
    with TestClient(guarded()) as client:
        r = client.post("/things", content=chunks(40_000), headers=AUTH)
    assert "content-length" not in r.request.headers  # the old check saw nothing
    assert r.status_code == 413, r.text
    assert r.json()["error"] == {"code": "too_large", "field": "body",
                                 "message": "request body is over the limit of 1024 bytes "
                                            "(AESOP_TEST_MAX_BODY_BYTES)"}


def test_a_body_within_the_limit_still_arrives_whole() -> None:
    with TestClient(guarded()) as client:
        r = client.post("/things", content=chunks(500, size=100), headers=AUTH)
    assert r.status_code == 200, r.text
    assert r.json()["names"] == ["x" * 500]


def test_the_token_is_checked_before_the_body_is_read() -> None:
    with TestClient(guarded()) as client:
        bad_json = client.post("/things", content=b"{not json",
                               headers={"Content-Type": "application/json"})
        too_big = client.post("/things", content=chunks(40_000),
                              headers={"Content-Type": "application/json"})
        not_json = client.post("/things", content=b"x", headers={"Content-Type": "text/plain"})
    for r in (bad_json, too_big, not_json):
        assert r.status_code == 401, r.text
        assert r.json()["error"]["field"] == "Authorization"


def test_with_a_token_every_route_but_the_ops_ones_needs_it() -> None:
    with TestClient(guarded(public=("/open",))) as client:
        assert client.get("/things").status_code == 401
        assert client.get("/things", headers=AUTH).status_code == 200
        for path in ("/healthz", "/readyz", "/metrics"):
            assert client.get(path).status_code == 200, path
        assert client.get("/open").status_code == 404  # public, and simply not there


def test_without_a_token_only_loopback_host_names_are_served() -> None:
    """DNS rebinding: a page on evil.example whose name now points at 127.0.0.1 sends
    'Host: evil.example'."""
    with TestClient(guarded(token=None), base_url="http://127.0.0.1:8001") as client:
        assert client.get("/things").status_code == 200
        for host in ("localhost:8001", "[::1]:8001", "127.0.0.1"):
            assert client.get("/things", headers={"Host": host}).status_code == 200, host
        r = client.get("/things", headers={"Host": "evil.example:8001"})
    assert r.status_code == 400
    assert r.json()["error"]["field"] == "Host"


def test_a_cross_site_request_is_refused() -> None:
    """A web page may POST to a loopback service without a token: the browser sends its
    Origin, which is not the service's own."""
    with TestClient(guarded(token=None), base_url="http://127.0.0.1:8001") as client:
        r = client.post("/things", content=b"", headers={"Origin": "http://evil.example"})
        same = client.post("/things", json={"names": []},
                           headers={"Origin": "http://127.0.0.1:8001"})
    assert r.status_code == 403
    assert r.json()["error"]["field"] == "Origin"
    assert same.status_code == 200


def test_a_cross_site_websocket_is_refused() -> None:
    app = guarded(token=None)

    @app.websocket("/ws")
    async def ws(websocket: WebSocket) -> None:
        await websocket.accept()
        await websocket.send_text("hello")
        await websocket.close()

    with TestClient(app, base_url="http://127.0.0.1:8001") as client:
        host = {"Host": "127.0.0.1:8001"}
        with client.websocket_connect("/ws", headers={**host, "Origin": "http://127.0.0.1:8001"}
                                      ) as ws_:
            assert ws_.receive_text() == "hello"
        with pytest.raises(WebSocketDisconnect) as refused, \
                client.websocket_connect("/ws", headers={**host, "Origin": "http://evil.example"}):
            pass
    assert refused.value.code == 1008


def test_a_body_on_a_get_or_a_public_path_is_refused_before_it_is_read() -> None:
    """Issue 26, finding 2: `GET /healthz` with a 60 MiB body was read into memory before
    anything refused it. A body where none belongs is refused from the headers alone: a
    400 naming it, not the 413 of a body read up to the limit."""
    with TestClient(guarded(public=("/open",))) as client:
        for method, path, status in (("GET", "/healthz", 400), ("GET", "/things", 400),
                                     ("HEAD", "/readyz", 405),  # a GET route only
                                     ("POST", "/open", 404),  # public, and no route
                                     ("POST", "/metrics", 405)):  # as the router says
            r = client.request(method, path, content=chunks(40_000), headers=AUTH)
            assert r.status_code == status, (method, path, r.status_code)
            assert r.headers["connection"] == "close"
            if status == 400 and method != "HEAD":
                assert r.json()["error"]["code"] == "body_not_allowed", (method, path)
            if status == 405:
                assert r.headers["allow"] == "GET"
        assert client.post("/things", json={"names": ["a"]}, headers=AUTH).status_code == 200


def test_made_up_methods_share_one_metrics_label() -> None:
    """Issue 26, finding 3: every made-up method was a label of its own (8,000 of them made
    /metrics 16.9 MB)."""
    with TestClient(guarded()) as client:
        for i in range(20):
            client.request(f"FOO{i}", "/things")
        text = client.get("/metrics").text
    assert "FOO" not in text
    assert 'method="other"' in text


def test_metrics_are_rendered_off_the_event_loop() -> None:
    """Issue 26, finding 3: a scrape rendered on the loop that also serves the verdicts."""
    import asyncio

    from prometheus_client.registry import Collector

    seen: list[bool] = []

    class Probe(Collector):
        def collect(self):  # type: ignore[no-untyped-def]
            try:
                asyncio.get_running_loop()
                seen.append(True)
            except RuntimeError:
                seen.append(False)
            return iter(())

    registry = CollectorRegistry()
    app = service_app("test", service="test", lifespan=None, registry=registry,
                      ready=lambda: None, max_body_bytes=1024)
    registry.register(Probe())
    seen.clear()
    with TestClient(app, base_url="http://127.0.0.1:8001") as client:
        assert client.get("/metrics").status_code == 200
    assert seen == [False]


def test_no_service_takes_the_admin_token_from_a_cookie() -> None:
    """Issue 26, finding 4: the dashboard's cookie was the admin token, scoped to the host
    (not the port), and every service accepted it: a browser that had opened the dashboard
    sent it to the embedding service too, which created a cache on it alone."""
    with TestClient(guarded()) as client:
        r = client.post("/things", json={"names": []},
                        headers={"Cookie": f"aesop_token={GUARD_TOKEN}"})
        assert r.status_code == 401


def test_the_read_only_session_cookie_opens_reads_only_where_allowed() -> None:
    from shared.http import SESSION_COOKIE, session_value

    session = session_value(SecretStr(GUARD_TOKEN))
    assert session != GUARD_TOKEN and GUARD_TOKEN not in session
    cookie = {"Cookie": f"{SESSION_COOKIE}={session}"}
    reads = service_app("test", service="test", lifespan=None, registry=CollectorRegistry(),
                        ready=lambda: None, admin_token=SecretStr(GUARD_TOKEN),
                        max_body_bytes=1024, session_reads=True)

    @reads.get("/things")
    async def list_things() -> Body:
        return Body(names=["a"])

    @reads.post("/things")
    async def post_things(body: Body) -> Body:
        return body

    with TestClient(reads) as client:
        assert client.get("/things", headers=cookie).status_code == 200
        assert client.post("/things", json={"names": []}, headers=cookie).status_code == 401
        wrong = {"Cookie": f"{SESSION_COOKIE}={session[:-1]}0"}
        assert client.get("/things", headers=wrong).status_code == 401
    with TestClient(guarded()) as client:  # a service without session reads: none
        assert client.get("/things", headers=cookie).status_code == 401
