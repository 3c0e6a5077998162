"""The slow reasoner against a real OpenAI-compatible server that is not ours (issue 13):
llama-cpp-python's server (``make llama`` builds it into ``.venv-llama``) serving a tiny
GGUF model with random weights that the test writes itself (:mod:`tests.fakes.tiny_gguf`).

Random weights write noise; the server's grammar for the JSON Schema of the answer (one
of the offered options, a bounded reasoning) is what makes the reply parseable, so a
decision comes back from the model itself. The server is run with
``--interrupt_requests False`` so that it ends a stream only when its client leaves, and
says so on its output: that is how the tests see a cancelled request stop on the server.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

from services.reasoner.backends import BackendConfig, BackendError, OpenAIChatBackend
from services.reasoner.deciding import Decider, DeciderConfig
from shared.messages import Observation, Option, ReasonerRequest
from shared.process import free_port
from tests.fakes.tiny_gguf import write_tiny_llama

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

ROOT = Path(__file__).resolve().parents[2]
SERVER_PYTHON = Path(os.environ.get("AESOP_TEST_LLAMA_PYTHON",
                                    ROOT / ".venv-llama" / "bin" / "python"))
OPTIONS = (
    Option(index=0, label="continue", description="proceed with landing on the red box"),
    Option(index=1, label="alternative landing site", description="land on the blue box instead"),
    Option(index=2, label="holding zone", description="hover in the designated holding zone"),
)
DISCONNECTED = "Disconnected from client"


@dataclass
class LlamaServer:
    url: str  # ends in /v1
    log: Path
    proc: subprocess.Popen[bytes]

    def said(self, text: str) -> int:
        return self.log.read_text(errors="replace").count(text)

    def wait_said(self, text: str, times: int, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while self.said(text) < times:
            assert self.proc.poll() is None, self.log.read_text()[-2000:]
            assert time.monotonic() < deadline, self.log.read_text()[-2000:]
            time.sleep(0.05)


@pytest.fixture(scope="module")
def llama(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LlamaServer]:
    if not SERVER_PYTHON.is_file():
        pytest.fail(f"no llama.cpp server at {SERVER_PYTHON}: run `make llama` (make test does)")
    folder = tmp_path_factory.mktemp("llama")
    model = write_tiny_llama(folder / "tiny.gguf")
    port = free_port()
    log = folder / "server.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [str(SERVER_PYTHON), "-m", "llama_cpp.server", "--model", str(model),
             "--model_alias", "tiny", "--host", "127.0.0.1", "--port", str(port),
             "--n_ctx", "4096", "--verbose", "False", "--interrupt_requests", "False"],
            stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    server = LlamaServer(f"http://127.0.0.1:{port}/v1", log, proc)
    try:
        deadline = time.monotonic() + 60
        while True:
            assert proc.poll() is None, log.read_text()[-2000:]
            try:
                if httpx.get(f"{server.url}/models", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, log.read_text()[-2000:]
            time.sleep(0.1)
        yield server
    finally:
        proc.send_signal(signal.SIGTERM)  # it waits for a running generation: then SIGKILL
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def request(deadline_s: float) -> ReasonerRequest:
    observation = Observation(seq=1, task="land on the red box",
                              text="another quadrotor is parked on the red box\n"
                                   "a blue box on the ground")
    return ReasonerRequest(request_id="r1", observation=observation, options=OPTIONS,
                           deadline_s=deadline_s)


def backend(server: LlamaServer, **config: Any) -> OpenAIChatBackend:
    return OpenAIChatBackend(BackendConfig(name="llama", base_url=server.url, model="tiny",
                                           **config))


JSON_MODE = {"json_schema": True, "response_format": "json_object",
             "max_reasoning_chars": 200, "max_tokens": 600}


@pytest.mark.parametrize("stream", [True, False])
async def test_a_decision_comes_back_from_the_model(llama: LlamaServer, stream: bool) -> None:
    chat = backend(llama, stream=stream, **JSON_MODE)
    decider = Decider([chat], DeciderConfig())
    try:
        decision = await decider.decide(request(deadline_s=60.0))
    finally:
        await decider.aclose()
    assert decision.source == "llm", decision.rationale
    assert decision.choice in {0, 1, 2} and decision.model == "tiny"


async def test_usage_tokens_are_counted(llama: LlamaServer) -> None:
    chat = backend(llama, stream=False, **JSON_MODE)
    try:
        completion = await chat.complete([{"role": "user", "content": "land or hover?"}],
                                         answers=[0, 1, 2])
    finally:
        await chat.aclose()
    assert completion.prompt_tokens and completion.prompt_tokens > 10
    assert completion.completion_tokens and completion.completion_tokens > 5
    assert completion.text.rstrip().splitlines()[-1] in {f"FINAL ANSWER: {i}" for i in range(3)}


async def test_openais_shape_is_refused_naming_the_setting(llama: LlamaServer) -> None:
    chat = backend(llama, stream=False, **(JSON_MODE | {"response_format": "json_schema"}))
    try:
        with pytest.raises(BackendError) as refused:
            await chat.complete([{"role": "user", "content": "hi"}], answers=[0, 1])
    finally:
        await chat.aclose()
    assert refused.value.kind == "http"
    assert "AESOP_REASONER_REQUEST__RESPONSE_FORMAT=json_object" in str(refused.value)


async def test_streaming_early_exit_stops_the_generation(llama: LlamaServer) -> None:
    before = llama.said(DISCONNECTED)
    chat = backend(llama, stream=True, max_tokens=3000)  # runs to max_tokens on its own
    try:
        completion = await chat.complete([{"role": "user", "content": "say something"}],
                                         stop_when=lambda text: len(text) >= 20)
    finally:
        await chat.aclose()
    assert completion.stopped_early and 20 <= len(completion.text) < 60
    llama.wait_said(DISCONNECTED, before + 1)  # the server stopped generating for it


async def test_a_request_past_its_deadline_is_cancelled_on_the_server(
        llama: LlamaServer) -> None:
    before = llama.said(DISCONNECTED)
    chat = backend(llama, stream=True, max_tokens=2000)  # seconds of noise, no answer line
    decider = Decider([chat], DeciderConfig())
    try:
        decision = await decider.decide(request(deadline_s=1.5))
    finally:
        await decider.aclose()
    assert decision.source == "timeout"  # the fallback at the deadline
    llama.wait_said(DISCONNECTED, before + 1)
    # and the server is free again: the next question is answered by the model
    chat = backend(llama, stream=True, **JSON_MODE)
    decider = Decider([chat], DeciderConfig())
    try:
        assert (await decider.decide(request(deadline_s=60.0))).source == "llm"
    finally:
        await decider.aclose()
