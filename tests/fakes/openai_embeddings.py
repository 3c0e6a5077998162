"""A fake OpenAI-compatible embeddings server, run as a real HTTP server process.

    python -m tests.fakes.openai_embeddings --port 8100 --dim 16 [--api-key KEY]

``POST /v1/embeddings`` takes ``{"model": str, "input": str | [str]}`` and
answers like OpenAI: ``{"object": "list", "data": [{"object": "embedding",
"index": i, "embedding": [...]}], "model", "usage"}``. An embedding is a
standard-normal draw from a RNG seeded by sha256(text): deterministic, and
deliberately *not* unit-norm, so clients must normalise. With an API key set,
requests without ``Authorization: Bearer <key>`` get 401.

The model name injects behaviour (anything else is a normal model):

    fail-500     HTTP 500 with an OpenAI-style error body
    bad-json     HTTP 200 with a truncated JSON body
    no-data      HTTP 200, valid JSON without "data"
    wrong-count  one embedding fewer than inputs
    ragged       the last embedding one number short
    nan          NaN in the first embedding
    zero         an all-zero first embedding
    reversed     "data" in reverse order (each item keeps its right "index")
    slow         answers after 1 s
    echo-auth    HTTP 400 whose body echoes the Authorization header
    dim-<n>      n-dimensional embeddings

``GET /healthz`` answers 200 once serving; ``GET /_fake/requests`` lists what
was received (model, number of inputs, whether an Authorization header came;
never the header itself).

Tests use ``start_fake_embeddings_server()``, which starts the process on a
free port, polls until it answers, and always kills it.
"""

from __future__ import annotations

import argparse
import asyncio
import hashlib
import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import httpx
import numpy as np
from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse, Response

MODULE = "tests.fakes.openai_embeddings"
REPO_ROOT = Path(__file__).resolve().parents[2]
API_KEY_ENV = "FAKE_EMBEDDINGS_API_KEY"  # the key travels by environment, not argv
SLOW_S = 1.0


def fake_embedding(text: str, dim: int) -> np.ndarray:
    """The fake's vector for ``text``: deterministic, standard normal, not unit-norm."""
    seed = int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little")
    return np.random.default_rng(seed).standard_normal(dim)


def _error(status: int, message: str, code: str = "fake_error") -> JSONResponse:
    body = {"error": {"message": message, "type": "invalid_request_error", "code": code}}
    return JSONResponse(body, status_code=status)


def _inputs(body: Any) -> tuple[str, list[str]] | JSONResponse:
    if not isinstance(body, dict) or not isinstance(body.get("model"), str):
        return _error(400, "'model' (string) is required")
    raw = body.get("input")
    inputs = [raw] if isinstance(raw, str) else raw
    if not isinstance(inputs, list) or not inputs or not all(isinstance(t, str) for t in inputs):
        return _error(400, "'input' must be a string or a non-empty list of strings")
    return body["model"], inputs


def _vectors(model: str, inputs: list[str], dim: int) -> list[list[float]]:
    if model.startswith("dim-"):
        dim = int(model.removeprefix("dim-"))
    rows = [fake_embedding(text, dim).tolist() for text in inputs]
    if model == "nan":
        rows[0][0] = float("nan")
    elif model == "zero":
        rows[0] = [0.0] * dim
    elif model == "ragged":
        rows[-1] = rows[-1][:-1]
    return rows


def _answer(model: str, inputs: list[str], dim: int) -> Response:
    if model == "fail-500":
        return _error(500, "The server had an error while processing your request.", "server")
    if model == "bad-json":
        return Response('{"object": "list", "data": [{"index": 0, "embed', 200,
                        media_type="application/json")
    if model == "no-data":
        return JSONResponse({"object": "list", "model": model})
    data = [
        {"object": "embedding", "index": i, "embedding": row}
        for i, row in enumerate(_vectors(model, inputs, dim))
    ]
    if model == "wrong-count":
        data = data[:-1]
    if model == "reversed":
        data.reverse()
    tokens = sum(len(t.split()) for t in inputs)
    body = {"object": "list", "data": data, "model": model,
            "usage": {"prompt_tokens": tokens, "total_tokens": tokens}}
    # json.dumps, not JSONResponse: it writes NaN as Python's json does (the "nan" model)
    return Response(json.dumps(body), 200, media_type="application/json")


def create_app(*, dim: int = 16, api_key: str | None = None) -> FastAPI:
    """The fake server as an ASGI app (see the module docstring)."""
    app = FastAPI(title="fake OpenAI embeddings")
    received: list[dict[str, Any]] = []

    @app.get("/healthz")
    async def healthz() -> dict[str, bool]:
        return {"ok": True}

    @app.get("/_fake/requests")
    async def requests() -> dict[str, list[dict[str, Any]]]:
        return {"requests": received}

    @app.post("/v1/embeddings")
    async def embeddings(request: Request) -> Response:
        auth = request.headers.get("authorization")
        try:
            parsed = _inputs(await request.json())
        except ValueError:
            return _error(400, "the body is not JSON")
        if isinstance(parsed, JSONResponse):
            return parsed
        model, inputs = parsed
        received.append({"model": model, "inputs": len(inputs), "auth": auth is not None})
        if api_key is not None and auth != f"Bearer {api_key}":
            return _error(401, "Incorrect API key provided.", "invalid_api_key")
        if model == "echo-auth":
            return _error(400, f"echo: Authorization: {auth}")
        if model == "slow":
            await asyncio.sleep(SLOW_S)
        return _answer(model, inputs, dim)

    return app


# --- the process ---------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog=f"python -m {MODULE}", description=__doc__.split("\n")[0])
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=0, help="0: any free port")
    parser.add_argument("--dim", type=int, default=16)
    parser.add_argument("--api-key", default=os.environ.get(API_KEY_ENV) or None,
                        help=f"require this bearer token (default: ${API_KEY_ENV})")
    parser.add_argument("--port-file", type=Path, help="write the bound port here")
    parser.add_argument("--exit-on-stdin-eof", action="store_true",
                        help="exit when standard input closes (the parent died)")
    args = parser.parse_args(argv)

    import uvicorn

    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((args.host, args.port))
    if args.port_file is not None:
        tmp = args.port_file.with_suffix(".tmp")
        tmp.write_text(str(sock.getsockname()[1]))
        tmp.replace(args.port_file)
    if args.exit_on_stdin_eof:
        threading.Thread(target=_exit_on_eof, daemon=True).start()
    app = create_app(dim=args.dim, api_key=args.api_key)
    uvicorn.Server(uvicorn.Config(app, log_level="warning")).run(sockets=[sock])


def _exit_on_eof() -> None:
    sys.stdin.buffer.read()
    os._exit(0)


@contextmanager
def start_fake_embeddings_server(
    *, port: int = 0, dim: int = 16, api_key: str | None = None, startup_timeout_s: float = 30.0
) -> Iterator[tuple[str, subprocess.Popen[bytes]]]:
    """Runs the fake in a subprocess; yields ``(base_url, process)``.

    ``base_url`` ends in ``/v1`` (give it to an OpenAI client). Returns once
    ``/healthz`` answers; the process is killed on exit, whatever happens.
    """
    env = {k: v for k, v in os.environ.items() if k != API_KEY_ENV}
    if api_key is not None:
        env[API_KEY_ENV] = api_key
    with TemporaryDirectory(prefix="fake-embeddings-") as tmp:
        port_file, log_path = Path(tmp) / "port", Path(tmp) / "server.log"
        cmd = [sys.executable, "-m", MODULE, "--port", str(port), "--dim", str(dim),
               "--port-file", str(port_file), "--exit-on-stdin-eof"]
        with log_path.open("wb") as log:
            process = subprocess.Popen(cmd, cwd=REPO_ROOT, env=env, stdin=subprocess.PIPE,
                                       stdout=log, stderr=subprocess.STDOUT)
        try:
            bound = _wait_ready(process, port_file, log_path, startup_timeout_s)
            yield f"http://127.0.0.1:{bound}/v1", process
        finally:
            _stop(process)


def _wait_ready(
    process: subprocess.Popen[bytes], port_file: Path, log_path: Path, timeout_s: float
) -> int:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"the fake embeddings server exited with {process.returncode}:\n"
                               f"{_tail(log_path)}")
        if port_file.exists():
            port = int(port_file.read_text())
            try:
                if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1.0).status_code == 200:
                    return port
            except httpx.HTTPError:
                pass
        time.sleep(0.05)
    raise RuntimeError(f"the fake embeddings server did not answer within {timeout_s:g} s:\n"
                       f"{_tail(log_path)}")


def _stop(process: subprocess.Popen[bytes]) -> None:
    if process.stdin is not None:
        process.stdin.close()
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _tail(path: Path, chars: int = 2000) -> str:
    return path.read_text(errors="replace")[-chars:] if path.exists() else "(no log)"


if __name__ == "__main__":
    main()
