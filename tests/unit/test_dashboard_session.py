"""Issue 26, finding 4: the dashboard's cookie is a read-only session derived from the
token, never the token; it opens the dashboard's reads, nothing else."""

from __future__ import annotations

from fastapi.testclient import TestClient
from pydantic import SecretStr

from services.dashboard.api import create_app
from services.dashboard.settings import DashboardSettings
from shared.http import SECURE_SESSION_COOKIE, SESSION_COOKIE, session_value

TOKEN = "d" * 24


def app(base_url: str = "http://127.0.0.1:8080") -> TestClient:
    """The app without its lifespan (no bus): /v1/snapshot answers 503 once let in."""
    settings = DashboardSettings(admin_token=SecretStr(TOKEN))
    return TestClient(create_app(settings, bus_factory=lambda: None),  # type: ignore[arg-type,return-value]
                      base_url=base_url)


def test_the_page_sets_a_session_not_the_token() -> None:
    client = app()
    r = client.get(f"/?token={TOKEN}", follow_redirects=False)
    assert r.status_code == 303
    cookie = r.headers["set-cookie"]
    assert TOKEN not in cookie
    assert cookie.startswith(f"{SESSION_COOKIE}={session_value(SecretStr(TOKEN))};")
    assert "HttpOnly" in cookie and "SameSite=strict" in cookie and "Path=/" in cookie
    assert client.get("/v1/snapshot").status_code == 503  # the cookie lets it in
    client.cookies.clear()
    assert client.get("/v1/snapshot").status_code == 401
    raw = {"Cookie": f"aesop_token={TOKEN}"}  # the old cookie: no longer taken
    assert client.get("/v1/snapshot", headers=raw).status_code == 401


def test_over_tls_the_cookie_is_host_only_and_secure() -> None:
    client = app("https://127.0.0.1:8080")
    cookie = client.get(f"/?token={TOKEN}", follow_redirects=False).headers["set-cookie"]
    assert cookie.startswith(f"{SECURE_SESSION_COOKIE}=") and "Secure" in cookie
