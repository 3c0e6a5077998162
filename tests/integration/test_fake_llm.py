"""The fake OpenAI-compatible LLM: the rule-based model, the latency sampler, and a real
server process spoken to over HTTP."""

from __future__ import annotations

import json
import random
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from shared.process import free_port
from tools.fakes.llm import (
    FakeLLMConfig,
    FakeLLMSettings,
    UnknownModel,
    config_for_model,
    decide,
    parse_prompt,
    sample_latency,
)

OPTIONS = """Options:
0: continue — proceed with landing on the red box
1: alternative landing site — land on the blue box instead
2: holding zone — hover in the designated holding zone"""


def prompt(*observations: str, options: str = OPTIONS, extra: str = "") -> str:
    lines = "\n".join(f"> {o}" for o in observations)
    return (
        "You are monitoring a quadrotor that delivers a package.\n"
        "Task: land on the red box\n"
        f"Observation:\n{lines}\n{options}\n"
        "Think about each object and whether it endangers the task.\n"
        f"{extra}"
        "End your answer with one line exactly: FINAL ANSWER: <option number>"
    )


NOMINAL = ("a bicycle tire on the ground", "a soccer ball on the ground", "a drill",
           "a red box", "a blue box")


def final_answers(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("FINAL ANSWER:")]


# --------------------------------------------------------------------------- decide()


def test_nominal_clutter_continues() -> None:
    choice, text = decide(prompt(*NOMINAL))
    assert choice == 0
    assert final_answers(text) == ["FINAL ANSWER: 0"]
    assert text.splitlines()[-1] == "FINAL ANSWER: 0"


def test_quadrotor_on_red_box_goes_to_alternative_site() -> None:
    choice, text = decide(prompt(*NOMINAL[:3], "a quadrotor on the red box"))
    assert choice == 1
    assert text.endswith("FINAL ANSWER: 1")
    assert "red box" in text


def test_quadrotors_on_both_boxes_go_to_holding_zone() -> None:
    choice, text = decide(prompt("a quadrotor on the red box", "a drone on top of the blue box",
                                 "a soccer ball on the ground"))
    assert choice == 2
    assert final_answers(text) == ["FINAL ANSWER: 2"]


def test_the_task_phrase_landing_on_the_red_box_is_no_obstruction() -> None:
    brief = "The quadrotor is landing on the red box and observes: a soccer ball on the ground"
    assert decide(prompt(brief))[0] == 0
    occupied = "The quadrotor is landing on the red box and observes: a drone landed on the red box"
    assert decide(prompt(occupied))[0] == 1


def test_keyboard_on_the_ground_continues() -> None:
    choice, _ = decide(prompt(*NOMINAL, "a keyboard on the ground"))
    assert choice == 0


def test_options_found_by_description_in_any_order() -> None:
    options = ("Options:\n0: land — proceed as planned\n1: hover — wait in the holding zone\n"
               "2: divert — land on the blue box")
    assert decide(prompt("a quadrotor on the red box", options=options))[0] == 2
    both = prompt("a drone on the red box", "a quadrotor on the blue box", options=options)
    assert decide(both)[0] == 1


def test_warehouse_hazard_picks_recovery() -> None:
    options = ("Options:\n0: continue — keep driving the pallet to dock 3\n"
               "1: stop — stop in place and wait\n2: reroute — take aisle 5 instead")
    text = ("Task: move the pallet to dock 3\nObservation:\n> a pallet rack\n"
            "> smoke rising from a forklift charger\n" + options +
            "\nEnd your answer with one line exactly: FINAL ANSWER: <option number>")
    assert decide(text)[0] == 1
    blocked = text.replace("smoke rising from a forklift charger", "aisle 4 blocked by boxes")
    assert decide(blocked)[0] == 2  # a better keyword match than the first recovery


def test_single_token_prompt_answers_only_the_final_line() -> None:
    choice, text = decide(prompt("a quadrotor on the red box",
                                 extra="Answer with a single token, no explanation.\n"))
    assert (choice, text) == (1, "FINAL ANSWER: 1")


def test_no_options_is_a_refusal_without_final_answer() -> None:
    choice, text = decide("Task: land\nObservation:\n> a keyboard\nWhat should I do?")
    assert choice == -1
    assert "FINAL ANSWER" not in text


def test_parse_prompt_reads_the_layout() -> None:
    parsed = parse_prompt(prompt("a keyboard on the ground"))
    assert parsed.task == "land on the red box"
    assert parsed.observations == ("a keyboard on the ground",)
    assert [(o.index, o.label) for o in parsed.options] == [
        (0, "continue"), (1, "alternative landing site"), (2, "holding zone")]
    assert parsed.options[2].description == "hover in the designated holding zone"


# --------------------------------------------------------------------------- latency and names


def test_bimodal_profile_matches_the_paper() -> None:
    rng = random.Random(1234)
    cfg = FakeLLMConfig(profile="bimodal")
    xs = sorted(sample_latency(cfg, rng) for _ in range(20000))
    assert statistics.fmean(xs) == pytest.approx(3.1, abs=0.05)
    assert statistics.pstdev(xs) == pytest.approx(0.85, abs=0.05)
    assert xs[int(0.95 * len(xs))] == pytest.approx(4.3, abs=0.15)  # the paper's K
    assert xs[0] > 0 and xs[-1] <= 6.0


def test_fixed_and_normal_profiles() -> None:
    rng = random.Random(7)
    assert sample_latency(FakeLLMConfig(profile="fixed", fixed_s=0.2), rng) == 0.2
    cfg = FakeLLMConfig(profile="normal", mean_s=1.0, std_s=0.2)
    xs = [sample_latency(cfg, rng) for _ in range(20000)]
    assert statistics.fmean(xs) == pytest.approx(1.0, abs=0.02)
    assert statistics.pstdev(xs) == pytest.approx(0.2, abs=0.02)
    truncated = FakeLLMConfig(profile="normal", mean_s=0.0, std_s=1.0)
    assert min(sample_latency(truncated, rng) for _ in range(1000)) >= 0.0
    assert sample_latency(FakeLLMConfig(profile="stall"), rng) == float("inf")


def test_sampler_is_reproducible() -> None:
    cfg = FakeLLMConfig(profile="bimodal")
    a = [sample_latency(cfg, random.Random(5)) for _ in range(3)]
    assert a == [sample_latency(cfg, random.Random(5)) for _ in range(3)]


def test_model_name_grammar() -> None:
    base = FakeLLMConfig(time_scale=0.5)
    assert config_for_model("gpt-4o", base) == base
    cfg = config_for_model("fake-normal-1.5-0.25-scale-0.1", base)
    assert (cfg.profile, cfg.mean_s, cfg.std_s, cfg.time_scale) == ("normal", 1.5, 0.25, 0.1)
    assert config_for_model("fake-fixed-0.2", base).fixed_s == 0.2
    assert config_for_model("fake-503", base).error_status == 503
    assert config_for_model("fake-garbage-two", base).garbage == "two"
    assert config_for_model("fake-garbage", base).garbage == "random"
    assert config_for_model("fake-stall", base).profile == "stall"
    for bad in ("fake-fixed", "fake-warp", "fake-normal-1"):
        with pytest.raises(UnknownModel):
            config_for_model(bad, base)


def test_settings_from_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AESOP_FAKE_LLM_PROFILE", "bimodal")
    monkeypatch.setenv("AESOP_FAKE_LLM_TIME_SCALE", "0.1")
    cfg = FakeLLMSettings(seed=3).to_config()
    assert (cfg.profile, cfg.time_scale, cfg.seed) == ("bimodal", 0.1, 3)
    with pytest.raises(ValueError):
        FakeLLMConfig(rate_429=2.0)


# --------------------------------------------------------------------------- a real server


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    port = free_port()
    log = tmp_path_factory.mktemp("fake_llm") / "server.log"
    root = Path(__file__).resolve().parents[2]
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "tools.fakes.llm", "--port", str(port),
             "--profile", "fixed", "--fixed-s", "0.05", "--time-scale", "0.1", "--seed", "1",
             "--log-level", "warning"],
            cwd=root, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            assert proc.poll() is None, log.read_text(errors="replace")
            try:
                if httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, "fake LLM never became ready"
            time.sleep(0.05)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


def test_with_a_key_every_route_but_the_ops_ones_wants_it() -> None:
    """Issue 43: the fake LLM answered anyone; with its token it wants the key the reasoner
    holds, as OpenAI's API does."""
    from fastapi.testclient import TestClient
    from pydantic import SecretStr

    from tools.fakes.llm import FakeLLMConfig, create_app

    body = {"model": "fake-fixed-0", "messages": [{"role": "user", "content": "hi"}]}
    with TestClient(create_app(FakeLLMConfig(), SecretStr("k" * 20))) as client:
        for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "k" * 20}):
            refused = client.post("/v1/chat/completions", json=body, headers=headers)
            assert refused.status_code == 401 and \
                refused.json()["error"]["code"] == "invalid_api_key"
            assert client.get("/v1/models", headers=headers).status_code == 401
        key = {"Authorization": f"Bearer {'k' * 20}"}
        assert client.post("/v1/chat/completions", json=body, headers=key).status_code == 200
        assert client.get("/readyz").status_code == 200  # health stays open
    with TestClient(create_app(FakeLLMConfig())) as client:  # no key: as before
        assert client.post("/v1/chat/completions", json=body).status_code == 200


def chat(url: str, model: str, content: str, **extra: object) -> httpx.Response:
    body = {"model": model, "messages": [{"role": "system", "content": "You are a monitor."},
                                         {"role": "user", "content": content}], **extra}
    return httpx.post(f"{url}/v1/chat/completions", json=body, timeout=30)


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_completion_has_the_openai_shape(server: str) -> None:
    r = chat(server, "fake-fixed-0.2", prompt("a quadrotor on the red box"), max_tokens=256,
             temperature=0)
    assert r.status_code == 200
    body = r.json()
    assert body["object"] == "chat.completion" and body["model"] == "fake-fixed-0.2"
    assert body["id"] and isinstance(body["created"], int)
    (choice,) = body["choices"]
    assert choice["index"] == 0 and choice["finish_reason"] == "stop"
    assert choice["message"]["role"] == "assistant"
    assert choice["message"]["content"].splitlines()[-1] == "FINAL ANSWER: 1"
    usage = body["usage"]
    assert usage["total_tokens"] == usage["prompt_tokens"] + usage["completion_tokens"] > 0
    models = httpx.get(f"{server}/v1/models").json()
    assert "fake-bimodal" in [m["id"] for m in models["data"]]
    assert httpx.get(f"{server}/healthz").json() == {"status": "ok"}


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_streaming_equals_the_plain_answer(server: str) -> None:
    text = prompt("a quadrotor on the red box", "a drone on the blue box")
    plain = chat(server, "fake", text).json()["choices"][0]["message"]["content"]
    body = {"model": "fake", "stream": True, "messages": [{"role": "user", "content": text}]}
    lines: list[str] = []
    with httpx.stream("POST", f"{server}/v1/chat/completions", json=body, timeout=30) as r:
        assert r.status_code == 200
        assert r.headers["content-type"].startswith("text/event-stream")
        lines = [line for line in r.iter_lines() if line.startswith("data: ")]
    assert lines[-1] == "data: [DONE]"
    chunks = [json.loads(line[6:]) for line in lines[:-1]]
    assert all(c["object"] == "chat.completion.chunk" for c in chunks)
    streamed = "".join(c["choices"][0]["delta"].get("content", "") for c in chunks)
    assert streamed == plain and plain.endswith("FINAL ANSWER: 2")
    assert sum(1 for c in chunks if c["choices"][0]["delta"].get("content")) > 2
    assert chunks[-1]["choices"][0]["finish_reason"] == "stop"


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_injected_failures_by_model_name(server: str) -> None:
    r = chat(server, "fake-429", prompt("a keyboard"))
    assert r.status_code == 429 and int(r.headers["retry-after"]) >= 0
    assert r.json()["error"]["code"] == "rate_limit_exceeded"
    assert chat(server, "fake-500", prompt("a keyboard")).status_code == 500
    assert chat(server, "fake-503", prompt("a keyboard")).status_code == 503
    assert chat(server, "fake-warp", prompt("a keyboard")).status_code == 404
    assert chat(server, "fake", "hello", messages=[]).status_code == 422


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_malformed_outputs(server: str) -> None:
    text = prompt("a keyboard on the ground")

    def content(model: str, **extra: object) -> str:
        r = chat(server, model, text, **extra)
        assert r.status_code == 200
        return str(r.json()["choices"][0]["message"]["content"])

    assert final_answers(content("fake-garbage-noanswer")) == []
    assert len(set(final_answers(content("fake-garbage-two")))) == 2
    (bad,) = final_answers(content("fake-garbage-badindex"))
    assert int(bad.split(":")[1]) not in (0, 1, 2)
    as_json = json.loads(content("fake", response_format={"type": "json_object"}))
    assert as_json["answer"] == 0 and "FINAL ANSWER: 0" in as_json["reasoning"]
    with pytest.raises(json.JSONDecodeError):
        json.loads(content("fake-garbage-nonjson", response_format={"type": "json_object"}))
    assert "FINAL ANSWER" not in content("fake", messages=[
        {"role": "user", "content": "Tell me a joke."}])


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_stalled_requests_are_released_when_the_client_leaves(server: str) -> None:
    with pytest.raises(httpx.TimeoutException):
        httpx.post(f"{server}/v1/chat/completions", timeout=0.5,
                   json={"model": "fake-stall", "messages": [{"role": "user", "content": "x"}]})
    body = {"model": "fake-stall", "stream": True, "messages": [{"role": "user", "content": "x"}]}
    with pytest.raises(httpx.TimeoutException), httpx.stream(
            "POST", f"{server}/v1/chat/completions", json=body, timeout=0.5) as r:
        r.read()
    deadline = time.monotonic() + 30
    while (stats := httpx.get(f"{server}/_fake/stats").json())["active"] != 0:
        assert time.monotonic() < deadline, stats
        time.sleep(0.05)
    assert stats["outcomes"].get("disconnected", 0) >= 2
    metrics = httpx.get(f"{server}/metrics").text
    assert 'aesop_fake_llm_requests_total{outcome="ok"}' in metrics


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_time_scale_applies_to_every_delay(server: str) -> None:
    # the server runs with --time-scale 0.1; this also overrides it per request
    r = chat(server, "fake-fixed-0.2", prompt("a keyboard"))
    assert r.status_code == 200
    r = chat(server, "fake-bimodal-scale-0.01", prompt("a keyboard"))
    assert r.json()["choices"][0]["message"]["content"].endswith("FINAL ANSWER: 0")
