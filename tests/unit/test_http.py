"""The HTTP pieces every service shares: error bodies, documented errors and limits."""

from __future__ import annotations

from fastapi import FastAPI
from fastapi.testclient import TestClient
from pydantic import BaseModel

from shared.http import REQUEST_ERRORS, document_limits, errors, field_path, install_error_handlers


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
