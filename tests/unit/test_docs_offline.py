"""Each service's ``/docs`` (Swagger UI) and ``/redoc`` work on an offline robot (issue 44,
item 9): the pages, their JavaScript, CSS and icon come from the service itself, never a
CDN, and the pages and ``/openapi.json`` open without the admin token (they describe the
API and hold no data), while every operation still needs it ("Try it out" sends it once
Swagger's Authorize button has it: the schema declares the bearer scheme)."""

from __future__ import annotations

import re
from collections.abc import Callable
from urllib.parse import urljoin, urlsplit

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from prometheus_client import CollectorRegistry
from pydantic import SecretStr

from shared.http import service_app

TOKEN = "d" * 24


def shared_app() -> FastAPI:
    app = service_app("test", service="test", lifespan=None, registry=CollectorRegistry(),
                      ready=lambda: None, admin_token=SecretStr(TOKEN), max_body_bytes=1024)

    @app.get("/things")
    async def things() -> list[str]:
        return ["a"]

    return app


def dashboard_app() -> FastAPI:
    """A real service: its own public paths, static files and session middleware."""
    from services.dashboard.api import create_app
    from services.dashboard.settings import DashboardSettings
    return create_app(DashboardSettings(admin_token=SecretStr(TOKEN)),
                      bus_factory=lambda: None)  # type: ignore[arg-type,return-value]


APPS = {"service_app": shared_app, "dashboard": dashboard_app}
URL = re.compile(r"""(?:src|href)\s*=\s*["']([^"']+)["']|url\s*:\s*["']([^"']+)["']|"""
                 r"""(https?://[^\s"'<>)]+)""")


def referenced(html: str) -> list[str]:
    """Every address a page names: src=, href=, the spec's url:, and any absolute URL."""
    return sorted({next(g for g in m.groups() if g) for m in URL.finditer(html)})


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
@pytest.mark.parametrize("make", APPS.values(), ids=list(APPS))
def test_the_api_pages_load_everything_from_the_service_without_the_token(
        make: Callable[[], FastAPI], page: str) -> None:
    client = TestClient(make())  # no Authorization header
    answer = client.get(page)
    assert answer.status_code == 200, answer.text
    assert answer.headers["content-type"].startswith("text/html")
    urls = referenced(answer.text)
    assert urls, answer.text
    base = f"http://testserver{page}"
    outside = [u for u in urls if urlsplit(urljoin(base, u)).netloc != "testserver"]
    assert outside == [], f"{page} loads from outside the service: {outside}"
    assets = [u for u in urls if re.search(r"\.(js|css|png|ico)$", urlsplit(u).path)]
    assert any(a.endswith(".js") for a in assets), urls
    if page == "/docs":
        assert any(a.endswith(".css") for a in assets), urls
        # Swagger UI's default validator badge is an image from validator.swagger.io
        assert '"validatorUrl": null' in answer.text
    for asset in assets:
        served = client.get(urljoin(base, asset))
        assert served.status_code == 200, f"{asset}: {served.status_code}"
        assert len(served.content) > 100, asset


@pytest.mark.parametrize("make", APPS.values(), ids=list(APPS))
def test_the_schema_opens_without_the_token_and_declares_the_bearer_scheme(
        make: Callable[[], FastAPI]) -> None:
    client = TestClient(make())
    answer = client.get("/openapi.json")
    assert answer.status_code == 200, answer.text
    schema = answer.json()
    schemes = schema["components"]["securitySchemes"]
    assert {"type": "http", "scheme": "bearer"}.items() <= schemes["bearer"].items()
    # the operations still need it: Swagger's Authorize button fills it in for "Try it out"
    guarded = [op for ops in schema["paths"].values() for op in ops.values()
               if op.get("security") == [{"bearer": []}]]
    assert guarded


def test_the_pages_open_no_route_of_the_service() -> None:
    client = TestClient(shared_app())
    assert client.get("/things").status_code == 401
    # the assets' public prefix reaches the files alone (Starlette does not fold '..')
    assert client.get("/docs/assets/%2e%2e/%2e%2e/things").status_code == 404
    assert client.get("/docs/assets/nothing-here.js").status_code == 404
    assert client.get("/things", headers={"Authorization": f"Bearer {TOKEN}"}).json() == ["a"]
