"""The dashboard's read-only browser session.

Issue 26, finding 4: the cookie was the admin token; it became a value derived from it.
Issue 43, finding 8: that derived value was sent to every app on 127.0.0.1 whatever its
port (browsers do not scope cookies by port), never expired, and could not be revoked
without changing the token; another local app that received it replayed it
(``/v1/snapshot`` 200). Now the cookie, named for the dashboard's port, holds a random
server-side session that expires (``session_s``), ends on logout, on ``DELETE
/v1/sessions`` and on a restart, is bound to the address that opened it, and the sessions
kept are capped (the oldest goes first).
"""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr, ValidationError
from starlette.websockets import WebSocketDisconnect

from services.dashboard.api import create_app
from services.dashboard.hub import Hub
from services.dashboard.settings import DashboardSettings
from shared.http import SESSION_COOKIE, session_value

TOKEN = "d" * 24
NAME = "aesop_dashboard_8080"  # the cookie of the dashboard on port 8080
BEARER = {"Authorization": f"Bearer {TOKEN}"}


class Clock:
    """A clock the test moves by hand (no sleeps)."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def app(base_url: str = "http://127.0.0.1:8080", *, clock: Clock | None = None,
        client: tuple[str, int] = ("127.0.0.1", 50000), **settings: object) -> TestClient:
    """The app without its lifespan (no bus): /v1/snapshot answers 503 once let in."""
    config = DashboardSettings(admin_token=SecretStr(TOKEN), **settings)  # type: ignore[arg-type]
    made = create_app(config, bus_factory=lambda: None,  # type: ignore[arg-type,return-value]
                      **({"clock": clock} if clock is not None else {}))
    return TestClient(made, base_url=base_url, client=client)


def login(client: TestClient) -> str:
    """Open the page with the token; the session id the cookie holds."""
    r = client.get(f"/?token={TOKEN}", follow_redirects=False)
    assert r.status_code == 303, r.text
    return r.cookies[NAME]


def let_in(client: TestClient, session: str, name: str = NAME) -> bool:
    """Whether ``session`` under cookie ``name`` opens the flight (503: let in, no bus)."""
    client.cookies.clear()
    status = client.get("/v1/snapshot", headers={"Cookie": f"{name}={session}"}).status_code
    assert status in (401, 503), status
    return status == 503


def test_the_cookie_is_named_for_the_port_and_expires() -> None:
    client = app()
    r = client.get(f"/?token={TOKEN}", follow_redirects=False)
    assert r.status_code == 303
    [cookie] = r.headers.get_list("set-cookie")
    assert cookie.startswith(f"{NAME}=")
    assert TOKEN not in cookie and session_value(SecretStr(TOKEN)) not in cookie
    assert "HttpOnly" in cookie and "SameSite=strict" in cookie and "Path=/" in cookie
    assert "Max-Age=43200" in cookie  # 12 h by default
    assert client.get("/v1/snapshot").status_code == 503  # the cookie lets it in
    client.cookies.clear()
    assert client.get("/v1/snapshot").status_code == 401


def test_the_lifetime_comes_from_the_settings() -> None:
    r = app(session_s=60).get(f"/?token={TOKEN}", follow_redirects=False)
    assert "Max-Age=60" in r.headers["set-cookie"]
    for bad in (0, -1, 400 * 86400):
        with pytest.raises(ValidationError):
            DashboardSettings(session_s=bad)


def test_each_login_is_a_new_random_session() -> None:
    client = app()
    first, second = login(client), login(client)
    assert first != second and len(first) >= 32
    assert let_in(client, first) and let_in(client, second)


def test_over_tls_the_cookie_is_host_only_and_secure() -> None:
    client = app("https://127.0.0.1:8080")
    cookie = client.get(f"/?token={TOKEN}", follow_redirects=False).headers["set-cookie"]
    assert cookie.startswith(f"__Host-{NAME}=") and "Secure" in cookie


def test_the_old_cookies_open_nothing() -> None:
    """What a browser (or another app) may still hold: the token itself (issue 26) and the
    value derived from it, which never expired (issue 43)."""
    client = app()
    assert not let_in(client, session_value(SecretStr(TOKEN)), SESSION_COOKIE)
    assert not let_in(client, session_value(SecretStr(TOKEN)), f"__Host-{SESSION_COOKIE}")
    assert not let_in(client, TOKEN, "aesop_token")
    assert not let_in(client, session_value(SecretStr(TOKEN)))  # under the new name


def test_a_cookie_replayed_after_logout_is_refused() -> None:
    client = app()
    session = login(client)
    assert let_in(client, session)
    r = client.post("/logout", headers={"Cookie": f"{NAME}={session}"})
    assert r.status_code == 200 and r.json() == {"ended": True}
    assert f'{NAME}=""' in r.headers["set-cookie"] and "Max-Age=0" in r.headers["set-cookie"]
    assert not let_in(client, session)


def test_a_session_expires() -> None:
    clock = Clock()
    client = app(clock=clock, session_s=60)
    session = login(client)
    clock.now += 59
    assert let_in(client, session)
    clock.now += 1
    assert not let_in(client, session)
    assert not let_in(client, session)  # and stays out


def test_the_token_revokes_every_session() -> None:
    client = app()
    sessions = [login(client) for _ in range(3)]
    client.cookies.clear()
    cookie = {"Cookie": f"{NAME}={sessions[0]}"}
    assert client.delete("/v1/sessions", headers=cookie).status_code == 401  # no write
    r = client.delete("/v1/sessions", headers=BEARER)
    assert r.status_code == 200 and r.json() == {"revoked": 3}
    assert not any(let_in(client, s) for s in sessions)
    assert client.delete("/v1/sessions", headers=BEARER).json() == {"revoked": 0}


def test_a_restart_ends_every_session() -> None:
    session = login(app())
    assert not let_in(app(), session)


def test_a_cookie_opens_only_the_dashboard_of_its_port() -> None:
    """Another dashboard on the same host (same token, another port) takes neither the
    cookie named for 8080 nor its session under its own name."""
    session = login(app())
    other = app("http://127.0.0.1:8081", port=8081)
    assert not let_in(other, session)
    assert not let_in(other, session, "aesop_dashboard_8081")


def test_a_session_is_bound_to_the_address_that_opened_it() -> None:
    clock = Clock()
    settings = DashboardSettings(admin_token=SecretStr(TOKEN))
    made = create_app(settings, bus_factory=lambda: None, clock=clock)  # type: ignore[arg-type,return-value]
    browser = TestClient(made, base_url="http://127.0.0.1:8080", client=("10.0.0.7", 50000))
    elsewhere = TestClient(made, base_url="http://127.0.0.1:8080", client=("10.0.0.9", 50000))
    session = login(browser)
    assert let_in(browser, session)
    assert not let_in(elsewhere, session)


def test_the_sessions_kept_are_capped_the_oldest_going_first() -> None:
    client = app(limits={"sessions": 2})
    first, second, third = login(client), login(client), login(client)
    assert not let_in(client, first)
    assert let_in(client, second) and let_in(client, third)


def closed_with(client: TestClient, headers: dict[str, str]) -> int:
    """The code ``/ws`` closes with: 1008 refused by the guard, 1013 let in (no bus)."""
    with pytest.raises(WebSocketDisconnect) as closed, \
            client.websocket_connect("/ws", headers=headers) as ws:
        ws.receive_text()
    return closed.value.code


def test_the_websocket_takes_the_session_until_logout() -> None:
    client = app()
    session = login(client)
    client.cookies.clear()
    cookie = {"Cookie": f"{NAME}={session}"}
    assert closed_with(client, cookie) == 1013
    client.post("/logout", headers=cookie)
    assert closed_with(client, cookie) == 1008


def streaming(clock: Clock | None = None) -> TestClient:
    """An app whose /ws streams (a stand-in service: a hub and a snapshot, no bus); an
    open WebSocket looks at its session every 10 ms."""
    client = app(clock=clock, session_s=60)
    state = client.app.state  # type: ignore[attr-defined]
    state.service = SimpleNamespace(hub=Hub(8), snapshot=lambda: {"robot": "r"})
    state.sessions.check_s = 0.01
    return client


@pytest.mark.parametrize("end", ["logout", "revoke", "expiry"])
def test_an_open_websocket_ends_with_its_session(end: str) -> None:
    """Else a replayed cookie would read the flight for as long as its socket stayed open,
    whatever the expiry or a revocation."""
    clock = Clock()
    client = streaming(clock)
    session = login(client)
    client.cookies.clear()
    cookie = {"Cookie": f"{NAME}={session}"}
    with client.websocket_connect("/ws", headers=cookie) as ws:
        assert ws.receive_json()["kind"] == "snapshot"
        if end == "logout":
            assert client.post("/logout", headers=cookie).json() == {"ended": True}
        elif end == "revoke":
            assert client.delete("/v1/sessions", headers=BEARER).json() == {"revoked": 1}
        else:
            clock.now += 60
        closed = ws.receive()
    assert closed == {"type": "websocket.close", "code": 1008,
                      "reason": "the session ended: open /?token= again"}


def test_a_websocket_opened_with_the_token_ignores_sessions() -> None:
    clock = Clock()
    client = streaming(clock)
    session = login(client)
    client.cookies.clear()
    both = {"Cookie": f"{NAME}={session}", **BEARER}
    with client.websocket_connect("/ws", headers=both) as ws:
        assert ws.receive_json()["kind"] == "snapshot"
        client.post("/logout", headers=both)
        clock.now += 3600
        hub = client.app.state.service.hub  # type: ignore[attr-defined]
        ws.portal.call(hub.publish, '{"kind": "event"}')  # on the app's loop
        assert ws.receive_json() == {"kind": "event"}  # still open


@pytest.mark.parametrize("cookie", [
    f"{NAME}=", f"{NAME}=x", f"{NAME}={'a' * 4000}", f"{NAME}=\"quoted\"", f"{NAME}",
    f"{NAME}=é€", "=;;=;", f"{NAME}=a; {NAME}=b", "garbage",
])
def test_a_bad_cookie_is_401_never_500(cookie: str) -> None:
    client = app()
    raw = {"Cookie": cookie.encode()}  # as bytes: httpx sends them as they are
    assert client.get("/v1/snapshot", headers=raw).status_code == 401
    assert client.post("/logout", headers=raw).json() == {"ended": False}


def test_logout_without_a_session_and_bad_logins_are_4xx() -> None:
    client = app()
    assert client.post("/logout").json() == {"ended": False}
    assert client.get("/?token=wrong", follow_redirects=False).status_code == 401
    assert client.get("/logout").status_code == 405
    assert client.post("/logout", json={"a": 1}).status_code == 400  # a public path: no body
    no_token = TestClient(create_app(DashboardSettings(), bus_factory=lambda: None),  # type: ignore[arg-type,return-value]
                          base_url="http://127.0.0.1:8080")
    assert no_token.get(f"/?token={TOKEN}", follow_redirects=False).status_code == 401
