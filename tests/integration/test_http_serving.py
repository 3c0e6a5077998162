"""Issue 26, findings 2 and 7, against a real uvicorn server on loopback: connections
whose headers never finish are closed, connections past the limit are answered 503, a
body that stalls is answered 408, and bodies being read at once are bounded (503)."""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Iterator

import httpx
import pytest
from fastapi import FastAPI
from prometheus_client import CollectorRegistry
from pydantic import BaseModel

from shared.http import service_app
from shared.process import free_port
from shared.serving import server

pytestmark = pytest.mark.timeout(60)

LIMIT = 4  # connections
MAX_BODY = 1024 * 1024


class Body(BaseModel):
    names: list[str]


def app() -> FastAPI:
    app = service_app("test", service="test", lifespan=None, registry=CollectorRegistry(),
                      ready=lambda: None, max_body_bytes=MAX_BODY, body_idle_s=0.5)

    @app.post("/things")
    async def post_things(body: Body) -> dict[str, int]:
        return {"names": len(body.names)}

    return app


@pytest.fixture
def url() -> Iterator[tuple[str, int]]:
    port = free_port()
    srv = server(app(), "127.0.0.1", port, log_level="warning", header_timeout_s=0.5,
                 limit_concurrency=LIMIT)
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not srv.started:
        assert time.monotonic() < deadline, "the server did not start"
        time.sleep(0.01)
    yield "127.0.0.1", port
    srv.should_exit = True
    thread.join(10)


def connect(addr: tuple[str, int]) -> socket.socket:
    """A raw connection whose reads give up after 15 s (the server's timeouts here are
    0.5 s: a read that gives up means the server held the connection)."""
    sock = socket.create_connection(addr, timeout=15)
    sock.settimeout(15)
    return sock


def read_all(sock: socket.socket) -> bytes:
    """Everything until the server closes (or the read gives up: socket.timeout)."""
    out = b""
    while chunk := sock.recv(65536):
        out += chunk
    return out


def test_a_connection_whose_headers_never_finish_is_closed(url: tuple[str, int]) -> None:
    with contextlib.closing(connect(url)) as slow, contextlib.closing(connect(url)) as idle:
        slow.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # and no end
        # closed without an answer (a server that held it would leave recv to time out)
        assert read_all(slow) == b""
        assert read_all(idle) == b""  # one that sends nothing at all, too
    assert httpx.get(f"http://{url[0]}:{url[1]}/healthz").status_code == 200


def test_connections_past_the_limit_are_answered_503(url: tuple[str, int]) -> None:
    held = [connect(url) for _ in range(LIMIT)]
    try:
        time.sleep(0.2)
        r = httpx.get(f"http://{url[0]}:{url[1]}/healthz")
        assert r.status_code == 503
    finally:
        for sock in held:
            sock.close()


def post_head(length: int) -> bytes:
    return (f"POST /things HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
            f"Content-Length: {length}\r\n\r\n").encode()


def test_a_body_that_stalls_is_answered_408_and_the_connection_closed(
        url: tuple[str, int]) -> None:
    with contextlib.closing(connect(url)) as sock:
        sock.sendall(post_head(100) + b'{"names": [')
        answer = read_all(sock)
    assert answer.startswith(b"HTTP/1.1 408"), answer[:80]
    assert b"body_timeout" in answer


def test_bodies_being_read_at_once_are_bounded(url: tuple[str, int]) -> None:
    part = b"x" * (800 * 1024)
    first, second = connect(url), connect(url)
    try:
        for sock in (first, second):  # 1.6 MiB being read, of a 2 MiB budget
            sock.sendall(post_head(MAX_BODY - 100) + b'{"names": ["' + part)
        time.sleep(0.2)
        r = httpx.post(f"http://{url[0]}:{url[1]}/things",
                       content=b'{"names": ["' + b"y" * (600 * 1024) + b'"]}',
                       headers={"Content-Type": "application/json"})
        assert r.status_code == 503 and r.json()["error"]["code"] == "busy"
    finally:
        first.close()
        second.close()
    time.sleep(0.7)  # their reads end (408, or the client left): the budget is back
    r = httpx.post(f"http://{url[0]}:{url[1]}/things", json={"names": ["a"] * 1000})
    assert r.status_code == 200 and r.json() == {"names": 1000}
