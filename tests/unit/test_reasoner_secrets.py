"""What the reasoner shows of its backends never carries their credentials (issue 14)."""

from __future__ import annotations

from services.reasoner.backends import BackendConfig, error_snippet, redact_url


def test_a_url_loses_its_user_info_and_query() -> None:
    assert redact_url("http://user:pw@llm.local:8010/v1?api-key=k3y") == \
        "http://***@llm.local:8010/v1?***"
    assert redact_url("https://api.openai.com/v1") == "https://api.openai.com/v1"


def test_the_config_shows_only_the_public_url() -> None:
    config = BackendConfig(name="p", base_url="https://u:secret@h/v1", model="m", api_key="sk-x")
    assert "secret" not in repr(config) and "sk-x" not in repr(config)
    assert config.public_url == "https://***@h/v1"


def test_an_error_body_that_echoes_a_key_is_scrubbed() -> None:
    body = ('{"error": {"message": "Incorrect API key provided: sk-proj-AbC123xyz987. '
            'You passed Bearer abc.def.ghi", "type": "invalid_request_error"}}')
    snippet = error_snippet(body)
    assert "AbC123xyz987" not in snippet and "abc.def.ghi" not in snippet
    assert "Incorrect API key provided: ***" in snippet
    assert error_snippet("key was my-own-key!", ("my-own-key",)) == "key was ***!"
    assert len(error_snippet("x" * 10_000)) == 200
