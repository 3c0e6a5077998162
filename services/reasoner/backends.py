"""OpenAI-compatible chat-completions clients for the slow reasoner: streaming, no retries.

One adapter, :class:`OpenAIChatBackend`, speaks ``POST {base_url}/chat/completions`` to
cloud OpenAI, Ollama (``/v1``), vLLM, llama.cpp's server and the fake LLM
(:mod:`tools.fakes.llm`). It is deliberately thin:

- **No hidden retries** (transport ``retries=0``, no retry loop): a 429 or 5xx is one
  request and one :class:`BackendError`; the caller decides what to do by its deadline.
- **No own timeouts**: the caller owns the single deadline ``K`` and cancels the task;
  cancellation closes the response and its connection (the server sees a disconnect).
- **Streaming early exit**: with ``stream=True`` the SSE ``data:`` lines are read as
  they arrive, ``choices[0].delta.content`` is accumulated, and after every chunk
  ``stop_when(text_so_far)`` is asked; when it says True the stream is closed at once
  and the :class:`Completion` has ``stopped_early=True``.
- **JSON mode** (``json_schema=True``): the request carries a ``response_format``
  with the schema of ``{"reasoning": str, "answer": int}`` (the answer one of the
  offered options, the reasoning at most ``max_reasoning_chars`` where set, so that a
  small local model's grammar closes the string) in the shape the server takes
  (``response_format``: OpenAI's ``json_schema``, which vLLM, Ollama and llama.cpp's
  own server take too, or ``json_object`` with a ``schema``, which llama-cpp-python's
  server takes), and the reply is turned back
  into ``"<reasoning>\\nFINAL ANSWER: <answer>"`` so the one strict parser
  (:mod:`services.reasoner.parsing`) applies to both modes. A reasoning line that is
  exactly ``FINAL ANSWER: <answer>`` (same number) is dropped as a duplicate; any other
  marker in the reasoning stays, so the parser rejects the ambiguity. Reply content that
  is not such JSON is passed through unchanged (the parser then rejects it).
  ``stop_when`` is not consulted in JSON mode (partial JSON is not a final-answer line).
  With ``answer_first`` the schema puts the answer before the reasoning (a grammar-bound
  server writes the keys in the schema's order) and a streamed reply ends as soon as
  ``{"answer": n`` is complete: the text is then ``FINAL ANSWER: n``, without reasoning.
- **The API as it is now**: the completion limit goes by ``token_field``
  (``max_completion_tokens`` for OpenAI, whose reasoning models refuse ``max_tokens``),
  ``temperature`` is left out when None (those models refuse any but the default), a
  stream asks for ``stream_options.include_usage`` (the usage comes in a last chunk),
  and only ``content`` is read: ``reasoning_content`` / ``reasoning`` deltas are not the
  answer. A 400 for a refused parameter names the setting to change.

Errors (:class:`BackendError.kind`): ``http`` (status >= 400, ``status`` set), ``connect``
(cannot reach the server), ``timeout`` (an httpx timeout, only if the caller configured
one on its own client), ``protocol`` (anything else: bad JSON, missing fields, broken
stream). Messages never contain the API key (no header is ever formatted into them).
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol
from urllib.parse import urlsplit, urlunsplit

import httpx

ErrorKind = Literal["http", "timeout", "protocol", "connect"]
TokenField = Literal["max_tokens", "max_completion_tokens"]
ResponseFormat = Literal["json_schema", "json_object"]
StopWhen = Callable[[str], bool]
MAX_ERROR_BODY = 200  # characters of a server's error body kept in a BackendError


def answer_schema(answers: Sequence[int] | None = None,
                  max_reasoning_chars: int | None = None, answer_first: bool = False
                  ) -> dict[str, Any]:
    """The JSON Schema of a JSON-mode reply: the answer one of ``answers`` (any integer
    when None), the reasoning at most ``max_reasoning_chars`` long (unbounded when None);
    the reasoning first, or the answer with ``answer_first``."""
    reasoning: dict[str, Any] = {"type": "string"}
    if max_reasoning_chars is not None:
        reasoning["maxLength"] = max_reasoning_chars
    answer: dict[str, Any] = {"type": "integer"}
    if answers:
        answer["enum"] = sorted(set(answers))
    order = ("answer", "reasoning") if answer_first else ("reasoning", "answer")
    properties = {"reasoning": reasoning, "answer": answer}
    return {"type": "object", "properties": {k: properties[k] for k in order},
            "required": list(order), "additionalProperties": False}


_ANSWER_FIRST = re.compile(r'^\s*\{\s*"answer"\s*:\s*(\d+)\s*[,}]')


def answer_so_far(partial: str) -> int | None:
    """The answer of a streamed answer-first JSON reply, once it is complete."""
    match = _ANSWER_FIRST.match(partial)
    return None if match is None else int(match.group(1))


def response_format(shape: ResponseFormat, schema: dict[str, Any]) -> dict[str, Any]:
    """``response_format`` as a server of ``shape`` takes it."""
    if shape == "json_object":
        return {"type": "json_object", "schema": schema}
    return {"type": "json_schema",
            "json_schema": {"name": "aesop_decision", "strict": True, "schema": schema}}


class BackendError(Exception):
    """A request that produced no completion; ``kind`` says how, ``status`` the HTTP code."""

    def __init__(self, kind: ErrorKind, message: str, status: int | None = None) -> None:
        super().__init__(message)
        self.kind: ErrorKind = kind
        self.status = status


_SECRET_LIKE = re.compile(r"\b(?:sk|pk|rk|key|token)-[A-Za-z0-9_\-]{6,}|\bBearer\s+\S+",
                          re.IGNORECASE)


def redact_url(url: str) -> str:
    """'http://user:pw@host/v1?api-key=k' -> 'http://***@host/v1?***'."""
    parts = urlsplit(url)
    netloc = parts.netloc
    if "@" in netloc:
        netloc = "***@" + netloc.rsplit("@", 1)[1]
    return urlunsplit((parts.scheme, netloc, parts.path, "***" if parts.query else "", ""))


def error_snippet(body: str, secrets: tuple[str, ...] = ()) -> str:
    """The start of a server's error body, on one line, with the configured key and
    anything shaped like a key or a bearer token replaced by '***' (servers echo them)."""
    text = " ".join(body.split())[:MAX_ERROR_BODY]
    for secret in secrets:
        if secret:
            text = text.replace(secret, "***")
    return _SECRET_LIKE.sub("***", text)


@dataclass(frozen=True)
class BackendConfig:
    """Where and how to ask one model; ``base_url`` ends before ``/chat/completions``."""

    name: str
    base_url: str
    model: str
    api_key: str | None = None
    max_tokens: int = 512
    temperature: float | None = 0.0  # None: not sent (reasoning models refuse any but 1)
    stream: bool = True
    json_schema: bool = False
    # the name of the completion limit: OpenAI's current API (and its reasoning models,
    # which refuse max_tokens) wants max_completion_tokens; llama.cpp, vLLM, Ollama take
    # max_tokens
    token_field: TokenField = "max_tokens"
    response_format: ResponseFormat = "json_schema"  # the shape of JSON mode's request
    max_reasoning_chars: int | None = None  # JSON mode: the reasoning's maxLength
    answer_first: bool = False  # JSON mode: the answer first, the stream ended after it

    def __post_init__(self) -> None:
        if not self.name or not self.model:
            raise ValueError("name and model must be non-empty")
        if not self.base_url.startswith(("http://", "https://")):
            raise ValueError("base_url must start with http:// or https://")
        if self.max_tokens < 1 or not (self.temperature is None
                                       or 0.0 <= self.temperature <= 2.0):
            raise ValueError("max_tokens must be >= 1 and temperature in [0, 2] or None")
        if self.max_reasoning_chars is not None and self.max_reasoning_chars < 1:
            raise ValueError("max_reasoning_chars must be >= 1 or None")

    @property
    def public_url(self) -> str:
        """``base_url`` without what may be a secret in it (user info, the query)."""
        return redact_url(self.base_url)

    def __repr__(self) -> str:  # never show the key
        key = "set" if self.api_key else None
        return (f"BackendConfig(name={self.name!r}, base_url={self.public_url!r}, "
                f"model={self.model!r}, api_key={key!r}, stream={self.stream})")


@dataclass(frozen=True)
class Completion:
    """The model's text (so far, if ``stopped_early``) and token usage when reported."""

    text: str
    prompt_tokens: int | None
    completion_tokens: int | None
    stopped_early: bool


class ChatBackend(Protocol):
    """What the decider needs from a model; cancellation must abort the request."""

    name: str
    model: str

    async def complete(
        self, messages: list[dict[str, str]], *, stop_when: StopWhen | None = None,
        answers: Sequence[int] | None = None,
    ) -> Completion: ...

    async def aclose(self) -> None: ...


def make_client() -> httpx.AsyncClient:
    """An AsyncClient with no retries and no timeouts (the caller's deadline rules)."""
    return httpx.AsyncClient(transport=httpx.AsyncHTTPTransport(retries=0), timeout=None)


class OpenAIChatBackend:
    """:class:`ChatBackend` over the OpenAI chat-completions API (see module docstring)."""

    def __init__(self, config: BackendConfig, client: httpx.AsyncClient | None = None) -> None:
        self.config = config
        self.name = config.name
        self.model = config.model
        self._client = client or make_client()
        self._owns_client = client is None

    @property
    def url(self) -> str:
        return self.config.base_url.rstrip("/") + "/chat/completions"

    async def complete(
        self, messages: list[dict[str, str]], *, stop_when: StopWhen | None = None,
        answers: Sequence[int] | None = None,
    ) -> Completion:
        """The model's reply to ``messages``; ``answers``: the option indices offered
        (JSON mode asks for one of them)."""
        payload = self._payload(messages, answers)
        try:
            if self.config.stream:
                return await self._streamed(payload, stop_when)
            return await self._plain(payload)
        except httpx.TimeoutException as exc:
            raise BackendError("timeout", f"{self.name}: {type(exc).__name__}") from None
        except httpx.ConnectError as exc:
            raise BackendError("connect", f"{self.name}: cannot connect: {exc}") from None
        except httpx.HTTPError as exc:
            raise BackendError("protocol", f"{self.name}: {type(exc).__name__}: {exc}") from None

    async def aclose(self) -> None:
        if self._owns_client:
            await self._client.aclose()

    # ------------------------------------------------------------------ internals

    def _payload(self, messages: list[dict[str, str]], answers: Sequence[int] | None
                 ) -> dict[str, Any]:
        payload: dict[str, Any] = {
            "model": self.config.model, "messages": messages, "stream": self.config.stream,
            self.config.token_field: self.config.max_tokens,
        }
        if self.config.temperature is not None:
            payload["temperature"] = self.config.temperature
        if self.config.stream:  # the usage comes in a last chunk only when asked for
            payload["stream_options"] = {"include_usage": True}
        if self.config.json_schema:
            payload["response_format"] = response_format(
                self.config.response_format,
                answer_schema(answers, self.config.max_reasoning_chars,
                              self.config.answer_first))
        return payload

    def _headers(self) -> dict[str, str]:
        if self.config.api_key:
            return {"Authorization": f"Bearer {self.config.api_key}"}
        return {}

    async def _plain(self, payload: dict[str, Any]) -> Completion:
        response = await self._client.post(self.url, json=payload, headers=self._headers())
        self._check(response.status_code, response.text)
        try:
            body = response.json()
            text = body["choices"][0]["message"]["content"] or ""
        except (ValueError, KeyError, IndexError, TypeError) as exc:
            raise BackendError("protocol", f"{self.name}: bad completion body ({exc!r})") from None
        usage = body.get("usage") or {}
        return self._finish(str(text), usage, stopped_early=False)

    async def _streamed(self, payload: dict[str, Any], stop_when: StopWhen | None
                        ) -> Completion:
        check = None if self.config.json_schema else stop_when
        first = self.config.json_schema and self.config.answer_first
        parts: list[str] = []
        usage: dict[str, Any] = {}
        async with self._client.stream("POST", self.url, json=payload,
                                       headers=self._headers()) as response:
            if response.status_code >= 400:
                await response.aread()
                self._check(response.status_code, response.text)
            async for line in response.aiter_lines():
                chunk = self._sse_chunk(line)
                if chunk is None:
                    break
                usage = chunk.get("usage") or usage
                delta = _delta_text(chunk)
                if not delta:
                    continue
                parts.append(delta)
                if first and (answer := answer_so_far("".join(parts))) is not None:
                    return self._finish(f"FINAL ANSWER: {answer}", usage, stopped_early=True)
                if check is not None and check("".join(parts)):
                    return self._finish("".join(parts), usage, stopped_early=True)
            # leaving the block closes the response; an early return closes it unread
        return self._finish("".join(parts), usage, stopped_early=False)

    def _sse_chunk(self, line: str) -> dict[str, Any] | None:
        """One ``data:`` line as JSON; ``{}`` for other lines; None at ``[DONE]``."""
        if not line.startswith("data:"):
            return {}
        data = line[5:].strip()
        if data == "[DONE]":
            return None
        try:
            chunk = json.loads(data)
        except ValueError:
            raise BackendError("protocol", f"{self.name}: bad SSE data line") from None
        if not isinstance(chunk, dict):
            raise BackendError("protocol", f"{self.name}: SSE chunk is not an object")
        return chunk

    def _check(self, status: int, body: str) -> None:
        if status >= 400:
            snippet = error_snippet(body, (self.config.api_key or "",))
            raise BackendError("http", f"{self.name}: HTTP {status}: {snippet}{_hint(body)}",
                               status=status)

    def _finish(self, text: str, usage: dict[str, Any], *, stopped_early: bool) -> Completion:
        if self.config.json_schema and not stopped_early:
            text = json_to_text(text)
        return Completion(text=text, prompt_tokens=_int_or_none(usage.get("prompt_tokens")),
                          completion_tokens=_int_or_none(usage.get("completion_tokens")),
                          stopped_early=stopped_early)


def _hint(body: str) -> str:
    """The setting to change when a server refuses a parameter we sent."""
    if "should be 'text' or 'json_object'" in body:  # llama-cpp-python, on json_schema
        return " (set AESOP_REASONER_REQUEST__RESPONSE_FORMAT=json_object)"
    refused = re.search(r"unsupported (?:parameter|value): '(\w+)'", body, re.IGNORECASE)
    if refused is None:
        return ""
    if refused.group(1) == "max_tokens":
        return " (set AESOP_REASONER_REQUEST__TOKEN_FIELD=max_completion_tokens)"
    if refused.group(1) == "max_completion_tokens":
        return " (set AESOP_REASONER_REQUEST__TOKEN_FIELD=max_tokens)"
    if refused.group(1) == "temperature":
        return " (set AESOP_REASONER_REQUEST__TEMPERATURE=omit)"
    return ""


def _delta_text(chunk: dict[str, Any]) -> str:
    try:
        content = chunk["choices"][0]["delta"].get("content")
    except (KeyError, IndexError, TypeError, AttributeError):
        return ""
    return content if isinstance(content, str) else ""


def _int_or_none(value: object) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


_MARKER_LINE = re.compile(r"^\s*final\s*answer\s*:\s*(\d+)\s*\.?\s*$", re.IGNORECASE)


def json_to_text(content: str) -> str:
    """``{"reasoning": str, "answer": int}`` -> ``"reasoning\\nFINAL ANSWER: n"``.

    Pure. Content that is not that JSON is returned unchanged, for the strict parser to
    reject. Reasoning lines that merely repeat ``FINAL ANSWER: <answer>`` are dropped.
    """
    try:  # not strict: a grammar-bound server may leave control characters in strings
        data = json.loads(content, strict=False)
    except ValueError:
        return content
    if not isinstance(data, dict):
        return content
    answer, reasoning = data.get("answer"), data.get("reasoning", "")
    if isinstance(answer, bool) or not isinstance(answer, int) or not isinstance(reasoning, str):
        return content
    kept = [line for line in reasoning.splitlines() if not _repeats(line, answer)]
    return "\n".join([*kept, f"FINAL ANSWER: {answer}"]).strip()


def _repeats(line: str, answer: int) -> bool:
    match = _MARKER_LINE.match(line)
    return match is not None and int(match.group(1)) == answer
