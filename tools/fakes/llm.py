"""A fake OpenAI-compatible LLM server for tests and demos of the slow reasoner.

It speaks ``POST /v1/chat/completions`` (plain and SSE streaming) and ``GET /v1/models``,
answers the AESOP prompts with a rule-based "model" (:func:`decide`), and waits a latency
drawn from a configurable profile (:func:`sample_latency`) before answering. Ops routes:
``/healthz``, ``/readyz``, ``/metrics`` and ``GET /_fake/stats`` (active/total requests).

Latency profiles (seconds, every delay multiplied by ``time_scale``):

- ``fixed``: always ``fixed_s``;
- ``normal``: ``N(mean_s, std_s)`` truncated at 0;
- ``bimodal``: the paper's GPT-3.5-turbo latencies (appendix "Choosing K": N = 500
  queries, bimodal, mean 3.1 s, std 0.85 s, 95 % quantile 4.3 s = K). Mixture
  :data:`BIMODAL`: 53 % ``N(2.4, 0.35)``, 44 % ``N(3.8, 0.30)``, 3 % outliers
  ``U(4.5, 6.0)``; analytically mean 3.10 s, std 0.85 s, 95 % quantile ~4.3 s;
- ``stall``: never answers; the request waits until the client disconnects.

Model-name grammar (per-request overrides, so one server serves many behaviours)::

    model   := "fake" ("-" segment)*            anything else: the server's defaults
    segment := "fixed-" SECONDS                 latency profile fixed
             | "normal-" MEAN "-" STD           latency profile normal
             | "bimodal" | "stall"              latency profile bimodal / stall
             | "scale-" FACTOR                  time_scale for this request
             | "429" | "5" DIGIT DIGIT          answer that HTTP error at once
             | "garbage" ["-" KIND]             malformed output; KIND is one of
                                                noanswer | two | badindex | nonjson
                                                (random when omitted)
             | "reasoning"                      as OpenAI's reasoning models: 400 for
                                                max_tokens or a temperature other than 1
                                                (they want max_completion_tokens), and
                                                reasoning_content deltas before the answer

e.g. ``fake-fixed-0.2``, ``fake-normal-1.0-0.2-scale-0.1``, ``fake-stall``, ``fake-500``,
``fake-429``, ``fake-garbage-two``, ``fake-bimodal``. An unknown segment -> 404
``model_not_found``. Without a failure segment, failures are injected at the configured
rates (``rate_429``, ``rate_5xx``, ``rate_garbage``) from a seeded RNG.

A stream ends with a usage chunk when ``stream_options.include_usage`` is true (as
OpenAI's API does). When ``response_format`` asks for JSON (``json_object`` /
``json_schema``) the content is ``{"reasoning": str, "answer": int}``, its keys in the
order of the schema's properties, as a grammar-bound server writes them.

With a key (the service's admin token, ``AESOP_ADMIN_TOKEN`` or ``_FILE``: the one the
reasoner holds as its ``AESOP_REASONER_LLM_API_KEY``), every route but the ops ones wants
``Authorization: Bearer <key>``, as OpenAI's API does (401 ``invalid_api_key`` otherwise):
no other local process holds the server.

Run: ``python -m tools.fakes.llm --port 8010 [--profile bimodal]``; every
flag also from ``AESOP_FAKE_LLM_*`` (``AESOP_FAKE_LLM_HOST``, ``AESOP_FAKE_LLM_PORT`` too).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import random
import re
import sys
import time
import uuid
from collections import Counter as Tally
from collections.abc import AsyncIterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal, cast

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse, Response, StreamingResponse
from prometheus_client import CollectorRegistry, Counter, Gauge
from pydantic import BaseModel, Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict
from starlette.middleware.base import BaseHTTPMiddleware, RequestResponseEndpoint

from shared.http import OPS_PATHS, error_response, install_error_handlers, ops_router, same_token
from shared.settings import ServiceSettings

Profile = Literal["fixed", "normal", "bimodal", "stall"]
GarbageKind = Literal["noanswer", "two", "badindex", "nonjson"]
GARBAGE_KINDS: tuple[GarbageKind, ...] = ("noanswer", "two", "badindex", "nonjson")
DEFAULT_PORT = 8010
POLL_S = 0.05  # how often a waiting request checks whether its client is gone


# --------------------------------------------------------------------------- latency


@dataclass(frozen=True)
class Component:
    """One mixture component: ``normal`` (mean, std) or ``uniform`` [low, high], in s."""

    weight: float
    kind: Literal["normal", "uniform"]
    a: float  # mean or low, s
    b: float  # std or high, s


# Fitted to the paper's appendix: mean 3.1 s, std 0.85 s, 95 % quantile 4.3 s (= K), and a
# small fraction of outliers up to 6 s.
BIMODAL: tuple[Component, ...] = (
    Component(0.53, "normal", 2.4, 0.35),
    Component(0.44, "normal", 3.8, 0.30),
    Component(0.03, "uniform", 4.5, 6.0),
)


@dataclass(frozen=True)
class FakeLLMConfig:
    """How the fake model behaves; every delay is multiplied by ``time_scale``."""

    profile: Profile = "fixed"
    fixed_s: float = 0.0  # s
    mean_s: float = 3.1  # s, profile normal
    std_s: float = 0.85  # s, profile normal
    time_scale: float = 1.0
    seed: int = 0
    rate_429: float = 0.0  # fraction of requests answered 429
    rate_5xx: float = 0.0  # fraction answered 500
    rate_garbage: float = 0.0  # fraction answered with malformed output
    retry_after_s: int = 1  # Retry-After header of a 429
    error_status: int = 0  # 0, or an HTTP status to answer every request with
    garbage: GarbageKind | Literal["random", ""] = ""  # "" = only at rate_garbage
    reasoning: bool = False  # behave as an OpenAI reasoning model (module docstring)

    def __post_init__(self) -> None:
        checks = [
            (self.fixed_s >= 0, "fixed_s must be >= 0"),
            (self.mean_s >= 0 and self.std_s >= 0, "mean_s and std_s must be >= 0"),
            (self.time_scale >= 0, "time_scale must be >= 0"),
            (all(0 <= r <= 1 for r in (self.rate_429, self.rate_5xx, self.rate_garbage)),
             "rates must be in [0, 1]"),
            (self.error_status == 0 or 400 <= self.error_status <= 599,
             "error_status must be 0 or a 4xx/5xx status"),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(message)


def sample_latency(config: FakeLLMConfig, rng: random.Random) -> float:
    """One latency in seconds (before ``time_scale``); ``inf`` for ``stall``. Pure given rng."""
    if config.profile == "fixed":
        return config.fixed_s
    if config.profile == "normal":
        return max(0.0, rng.gauss(config.mean_s, config.std_s))
    if config.profile == "stall":
        return math.inf
    return sample_mixture(BIMODAL, rng)


def sample_mixture(components: Sequence[Component], rng: random.Random) -> float:
    u, acc = rng.random(), 0.0
    chosen = components[-1]
    for comp in components:
        acc += comp.weight
        if u < acc:
            chosen = comp
            break
    if chosen.kind == "uniform":
        return rng.uniform(chosen.a, chosen.b)
    return max(0.0, rng.gauss(chosen.a, chosen.b))


# --------------------------------------------------------------------------- model names


class UnknownModel(ValueError):
    """A ``fake-...`` model name that does not follow the grammar."""


_NUMBER = re.compile(r"^\d+(\.\d+)?$")


def config_for_model(model: str, base: FakeLLMConfig) -> FakeLLMConfig:
    """Apply the model-name grammar (module docstring) on top of ``base``."""
    if model != "fake" and not model.startswith("fake-"):
        return base
    parts = model.split("-")[1:]
    changes: dict[str, Any] = {}
    i = 0

    def number() -> float:
        nonlocal i
        if i >= len(parts) or not _NUMBER.match(parts[i]):
            raise UnknownModel(f"model {model!r}: expected a number after {parts[i - 1]!r}")
        i += 1
        return float(parts[i - 1])

    while i < len(parts):
        seg = parts[i]
        i += 1
        if seg == "fixed":
            changes.update(profile="fixed", fixed_s=number())
        elif seg == "normal":
            changes.update(profile="normal", mean_s=number(), std_s=number())
        elif seg in ("bimodal", "stall"):
            changes["profile"] = seg
        elif seg == "scale":
            changes["time_scale"] = number()
        elif seg == "429" or re.fullmatch(r"5\d\d", seg):
            changes["error_status"] = int(seg)
        elif seg == "reasoning":
            changes["reasoning"] = True
        elif seg == "garbage":
            kind = "random"
            if i < len(parts) and parts[i] in GARBAGE_KINDS:
                kind, i = parts[i], i + 1
            changes["garbage"] = kind
        else:
            raise UnknownModel(f"model {model!r}: unknown segment {seg!r}")
    return replace(base, **changes)


# --------------------------------------------------------------------------- the "model"


@dataclass(frozen=True)
class Option:
    index: int
    label: str
    description: str = ""

    @property
    def text(self) -> str:
        return f"{self.label} {self.description}".lower()


@dataclass(frozen=True)
class ParsedPrompt:
    task: str = ""
    observations: tuple[str, ...] = ()
    options: tuple[Option, ...] = ()
    single_token: bool = False


_OPTION = re.compile(r"^\s*(\d+)\s*[:.)]\s*(.+?)\s*$")
_LABEL_SEP = re.compile(r"\s+(?:—|–|--)\s+")
_SINGLE = re.compile(
    r"single[- ]token|single word|no chain[- ]of[- ]thought|without (?:any )?"
    r"(?:explanation|reasoning)|do not (?:explain|reason)|no explanation", re.IGNORECASE)


def parse_prompt(prompt: str) -> ParsedPrompt:
    """Read ``Task:`` (a ``> `` line), ``Observation:`` (``> `` lines) and ``Options:``
    (``n: label — desc``)."""
    task, observations, options = "", [], []
    section = ""
    for raw in prompt.splitlines():
        line = raw.strip()
        low = line.lower()
        if low.startswith("task:"):  # the task on its line, or quoted on the next
            task, section = line[5:].strip(), "" if line[5:].strip() else "task"
        elif section == "task" and line.startswith(">"):
            task, section = line.lstrip("> ").strip(), ""
        elif re.match(r"observations?\s*:", low):
            section = "obs"
            rest = line.split(":", 1)[1].strip() if ":" in line else ""
            if rest:
                observations.append(rest.lstrip("> ").strip())
        elif low.startswith("options:"):
            section = "opt"
        elif low.startswith("unusual detections"):
            section = "unusual"  # the detector's finding: the observation says it all
        elif line.startswith(">"):
            if section not in ("opt", "unusual"):
                observations.append(line.lstrip("> ").strip())
        elif section == "opt" and (m := _OPTION.match(line)):
            label, description = _split_label(m.group(2))
            options.append(Option(int(m.group(1)), label, description))
        elif section == "opt" and line and options:
            section = ""  # instructions follow the options
    return ParsedPrompt(task, tuple(o for o in observations if o), tuple(options),
                        bool(_SINGLE.search(prompt)))


def _split_label(text: str) -> tuple[str, str]:
    """``"label — description"`` -> (label, description); the description is optional."""
    parts = _LABEL_SEP.split(text, maxsplit=1)
    return parts[0].strip(), (parts[1].strip() if len(parts) > 1 else "")


# "... is landing on the red box" states the task, not an obstruction: a bare "on" after a
# form of "land" does not count (the robot's own landing), "landed on" does (another's)
_ON = (r"(?<!landing )(?<!land )(?<!lands )"
       r"\b(?:on|onto|atop|on top of|landed on|sitting on|parked on)\s+(?:the\s+|a\s+)?")
_RED_OCCUPIED = re.compile(_ON + r"red\s+(?:box|landing)", re.IGNORECASE)
_BLUE_OCCUPIED = re.compile(_ON + r"blue\s+(?:box|landing)", re.IGNORECASE)
_DRONE = re.compile(r"\b(?:quadrotor|quadcopter|drone|uav)s?\b", re.IGNORECASE)

# hazard name -> (pattern in an observation, words that mark a better-matching option)
HAZARDS: dict[str, tuple[str, tuple[str, ...]]] = {
    "fire": (r"\bfire|flame", ("fire", "extinguish", "evacuat")),
    "smoke": (r"\bsmoke|smoking\b", ("smoke", "fire", "evacuat")),
    "leak": (r"\bleak|spill", ("leak", "spill", "clean")),
    "flood": (r"\bflood|standing water", ("flood", "water")),
    "ice": (r"\bic(?:e|y)\b", ("ice", "icy", "slow")),
    "collision": (r"\bcollision|collid|crash", ("collision", "stop")),
    "person lying": (r"\bperson\b.*\blying|lying.*\bperson\b|\bunconscious",
                     ("person", "medical", "emergency", "help")),
    "blocked": (r"\bblock(?:ed|ing|s)?\b|obstruct", ("reroute", "detour", "alternative route",
                                                      "blocked", "obstruct")),
    # the control loop asks this when the anomaly detector stops answering
    "unmonitored": (r"detector has gone silent|\bunmonitored\b", ("holding", "hover")),
}


def _find(options: Sequence[Option], words: Sequence[str], skip_zero: bool = True
          ) -> Option | None:
    for opt in options:
        if skip_zero and opt.index == 0:
            continue
        if any(w in opt.text for w in words):
            return opt
    return None


def _continue_option(options: Sequence[Option]) -> Option:
    return next((o for o in options if o.index == 0), options[0])


def _recovery_option(options: Sequence[Option]) -> Option:
    return next((o for o in options if o.index == 1),
                next((o for o in options if o.index != 0), options[0]))


def decide(prompt: str) -> tuple[int, str]:
    """The rule-based model: ``(choice, answer text)``; choice ``-1`` when the prompt offers
    no options (the text then has no FINAL ANSWER line, like a refusal)."""
    parsed = parse_prompt(prompt)
    if not parsed.options:
        return -1, ("I'm sorry, but I can't determine a course of action: the request lists "
                    "no options to choose from.")
    opts = parsed.options
    red = any(_RED_OCCUPIED.search(o) for o in parsed.observations)
    blue = any(_BLUE_OCCUPIED.search(o) for o in parsed.observations)
    notes, hazards = [], []
    for obs in parsed.observations:
        found = [name for name, (pat, _) in HAZARDS.items() if re.search(pat, obs, re.I)]
        hazards += found
        if _RED_OCCUPIED.search(obs):
            what = "another quadrotor" if _DRONE.search(obs) else "an object"
            notes.append(f"- {obs}: {what} occupies the red box, the nominal landing site.")
        elif _BLUE_OCCUPIED.search(obs):
            notes.append(f"- {obs}: the blue box, the alternative landing site, is occupied.")
        elif found:
            notes.append(f"- {obs}: a hazard ({', '.join(found)}) for the task.")
        else:
            notes.append(f"- {obs}: harmless, it does not affect the task.")

    choice: Option | None = None
    if red and blue:
        choice = _find(opts, ("holding zone", "hover", "holding"))
        why = "both landing boxes are occupied, so hold in the holding zone"
    elif red:
        choice = _find(opts, ("alternative landing", "blue box", "alternate landing"))
        why = "the red box is occupied and the blue box is free, so land at the alternative site"
    if choice is None and (hazards or red):
        words = tuple(w for h in hazards for w in HAZARDS[h][1])
        choice = _find(opts, words) or _recovery_option(opts)
        why = f"the observation shows a hazard ({', '.join(hazards) or 'occupied landing site'})"
    if choice is None:
        choice = _continue_option(opts)
        why = "nothing in the observation endangers the task, so continue"

    final = f"FINAL ANSWER: {choice.index}"
    if parsed.single_token:
        return choice.index, final
    lines = ["Let me check each observed object against the task"
             + (f" ({parsed.task})." if parsed.task else "."), *notes,
             f"Conclusion: {why}; option {choice.index} ({choice.label}).", final]
    return choice.index, "\n".join(lines)


def garble(kind: GarbageKind, text: str, choice: int, n_options: int) -> str:
    """Malformed output of the given kind, built from a well-formed answer."""
    body = "\n".join(line for line in text.splitlines() if not line.startswith("FINAL ANSWER"))
    if kind == "noanswer":
        return body or "Hmm, hard to say."
    if kind == "two":
        other = 1 if choice == 0 else 0
        return f"{body}\nFINAL ANSWER: {choice}\nFINAL ANSWER: {other}".lstrip()
    if kind == "badindex":
        return f"{body}\nFINAL ANSWER: {max(n_options, 0) + 7}".lstrip()
    return f"Sure! Here is my analysis, not in JSON: {body[:80]} ... the answer is {choice}"


# --------------------------------------------------------------------------- HTTP API


class ChatMessage(BaseModel):
    role: str
    content: str | list[dict[str, Any]] | None = None

    def text(self) -> str:
        if isinstance(self.content, list):  # content parts: keep the text ones
            return "".join(str(p.get("text", "")) for p in self.content)
        return self.content or ""


class ChatRequest(BaseModel):
    model: str = "fake"
    messages: list[ChatMessage] = Field(min_length=1)
    max_tokens: int | None = Field(default=None, ge=1)
    max_completion_tokens: int | None = Field(default=None, ge=1)
    temperature: float | None = Field(default=None, ge=0, le=2)
    stream: bool = False
    stream_options: dict[str, Any] | None = None
    response_format: dict[str, Any] | None = None

    def wants_usage(self) -> bool:
        return bool((self.stream_options or {}).get("include_usage"))

    def prompt(self) -> str:
        """The last user message if it carries options, else all messages concatenated."""
        users = [m.text() for m in self.messages if m.role == "user"]
        if users and re.search(r"^\s*options:", users[-1], re.I | re.M):
            return users[-1]
        return "\n".join(m.text() for m in self.messages)

    def wants_json(self) -> bool:
        kind = (self.response_format or {}).get("type", "text")
        return kind in ("json_object", "json_schema")

    def answer_first(self) -> bool:
        """The schema asks for the answer before the reasoning (a grammar-bound server
        writes the keys in the schema's order)."""
        fmt = self.response_format or {}
        schema = fmt.get("schema") or (fmt.get("json_schema") or {}).get("schema") or {}
        keys = list((schema.get("properties") or {}) if isinstance(schema, dict) else {})
        return keys[:1] == ["answer"]


@dataclass
class Stats:
    """Live request accounting, exposed at ``/_fake/stats`` and in ``/metrics``."""

    registry: CollectorRegistry
    active: int = 0
    total: int = 0
    outcomes: Tally[str] = field(default_factory=Tally)

    def __post_init__(self) -> None:
        self.requests = Counter("aesop_fake_llm_requests", "fake LLM requests by outcome",
                                ["outcome"], registry=self.registry)
        self.gauge = Gauge("aesop_fake_llm_active_requests", "requests being answered",
                           registry=self.registry)

    def outcome(self, name: str) -> None:
        self.outcomes[name] += 1
        self.requests.labels(name).inc()

    def enter(self) -> None:
        self.active += 1
        self.total += 1
        self.gauge.set(self.active)

    def leave(self) -> None:
        self.active -= 1
        self.gauge.set(self.active)


async def wait_or_disconnect(request: Request, seconds: float) -> bool:
    """Sleep ``seconds`` (may be inf); False as soon as the client has disconnected."""
    deadline = time.monotonic() + seconds
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return True
        await asyncio.sleep(min(POLL_S, left))
        if await request.is_disconnected():
            return False


def _tokens(text: str) -> int:
    return max(1, math.ceil(len(text) / 4))


def _chunks(text: str, n: int = 8) -> list[str]:
    pieces = re.findall(r"\S+\s*|\s+", text) or [""]
    size = max(1, math.ceil(len(pieces) / n))
    return ["".join(pieces[i:i + size]) for i in range(0, len(pieces), size)]


class KeyGuard(BaseHTTPMiddleware):
    """Every route but the ops ones wants ``Authorization: Bearer <key>``."""

    def __init__(self, app: Any, key: SecretStr) -> None:
        super().__init__(app)
        self.key = key

    async def dispatch(self, request: Request, call_next: RequestResponseEndpoint
                       ) -> Response:
        if request.url.path not in OPS_PATHS:
            scheme, _, given = request.headers.get("authorization", "").partition(" ")
            if scheme.lower() != "bearer" or not same_token(given.strip(), self.key):
                return error_response(401, "invalid_api_key",
                                      "a valid 'Authorization: Bearer <key>' is missing")
        return await call_next(request)


def create_app(config: FakeLLMConfig, api_key: SecretStr | None = None) -> FastAPI:
    """The fake server; all state (RNG, counters, registry) lives in this app. With
    ``api_key``, every route but the ops ones wants it as its bearer key."""
    app = FastAPI(title="aesop fake LLM", version="1")
    install_error_handlers(app)
    if api_key is not None:
        app.add_middleware(KeyGuard, key=api_key)
    registry = CollectorRegistry()
    stats = Stats(registry)
    rng = random.Random(config.seed)
    app.state.stats, app.state.config = stats, config
    app.include_router(ops_router(registry, ready=lambda: None))

    @app.get("/_fake/stats")
    async def fake_stats() -> dict[str, Any]:
        return {"active": stats.active, "total": stats.total, "outcomes": dict(stats.outcomes)}

    @app.get("/v1/models")
    async def models() -> dict[str, Any]:
        names = ["fake", "fake-fixed-0.2", "fake-normal-3.1-0.85", "fake-bimodal", "fake-stall",
                 "fake-429", "fake-500", "fake-garbage"]
        return {"object": "list", "data": [
            {"id": n, "object": "model", "created": 0, "owned_by": "aesop"} for n in names]}

    @app.post("/v1/chat/completions")
    async def chat(body: ChatRequest, request: Request) -> Response:
        try:
            cfg = config_for_model(body.model, config)
        except UnknownModel as exc:
            stats.outcome("unknown_model")
            return error_response(404, "model_not_found", str(exc), "model")
        refused = _refused(body, cfg)
        if refused is not None:
            stats.outcome("400")
            return refused
        draw = rng.random()
        if cfg.error_status == 429 or (not cfg.error_status and draw < cfg.rate_429):
            stats.outcome("429")
            return error_response(429, "rate_limit_exceeded", "fake rate limit", None,
                                  {"Retry-After": str(cfg.retry_after_s)})
        if cfg.error_status or draw < cfg.rate_429 + cfg.rate_5xx:
            status = cfg.error_status or 500
            stats.outcome(str(status))
            return error_response(status, "server_error", f"fake server error {status}")
        latency = sample_latency(cfg, rng) * cfg.time_scale
        content = _content(body, cfg, rng)
        if body.stream:
            usage = _usage(body, content) if body.wants_usage() else None
            thought = "Let me look at the options first." if cfg.reasoning else ""
            return StreamingResponse(_stream(body.model, content, latency, request, stats,
                                             usage=usage, thought=thought),
                                     media_type="text/event-stream")
        stats.enter()
        try:
            if not await wait_or_disconnect(request, latency):
                stats.outcome("disconnected")
                return Response(status_code=499)
        finally:
            stats.leave()
        stats.outcome("ok")
        message = {"role": "assistant", "content": content}
        if cfg.reasoning:
            message["reasoning_content"] = "Let me look at the options first."
        return JSONResponse({
            "id": f"chatcmpl-{uuid.uuid4().hex[:24]}", "object": "chat.completion",
            "created": int(time.time()), "model": body.model,
            "choices": [{"index": 0, "message": message, "finish_reason": "stop"}],
            "usage": _usage(body, content)})

    return app


def _usage(body: ChatRequest, content: str) -> dict[str, int]:
    prompt_tokens, completion_tokens = _tokens(body.prompt()), _tokens(content)
    return {"prompt_tokens": prompt_tokens, "completion_tokens": completion_tokens,
            "total_tokens": prompt_tokens + completion_tokens}


def _refused(body: ChatRequest, cfg: FakeLLMConfig) -> JSONResponse | None:
    """What OpenAI's reasoning models answer to the older parameters (their wording)."""
    if not cfg.reasoning:
        return None
    if body.max_tokens is not None:
        message = ("Unsupported parameter: 'max_tokens' is not supported with this model. "
                   "Use 'max_completion_tokens' instead.")
        return JSONResponse({"error": {"message": message, "type": "invalid_request_error",
                                       "param": "max_tokens", "code": "unsupported_parameter"}},
                            status_code=400)
    if body.temperature is not None and body.temperature != 1:
        message = (f"Unsupported value: 'temperature' does not support {body.temperature} with "
                   "this model. Only the default (1) value is supported.")
        return JSONResponse({"error": {"message": message, "type": "invalid_request_error",
                                       "param": "temperature", "code": "unsupported_value"}},
                            status_code=400)
    return None


def _content(body: ChatRequest, cfg: FakeLLMConfig, rng: random.Random) -> str:
    prompt = body.prompt()
    choice, text = decide(prompt)
    kind: str = cfg.garbage
    if kind == "" and rng.random() < cfg.rate_garbage:
        kind = "random"
    if kind == "random":
        kind = rng.choice(GARBAGE_KINDS)
    n_options = len(parse_prompt(prompt).options)
    if kind == "nonjson":
        return garble("nonjson", text, choice, n_options)
    if kind:
        text = garble(cast(GarbageKind, kind), text, choice, n_options)
    if body.wants_json():
        if body.answer_first():
            return json.dumps({"answer": choice, "reasoning": text})
        return json.dumps({"reasoning": text, "answer": choice})
    return text


async def _stream(model: str, content: str, latency: float, request: Request,
                  stats: Stats, *, usage: dict[str, int] | None = None, thought: str = ""
                  ) -> AsyncIterator[str]:
    """SSE chunks: half the latency before the first token, the rest spread between chunks;
    ``thought`` first as ``reasoning_content`` deltas, ``usage`` in a last chunk."""
    cid, created = f"chatcmpl-{uuid.uuid4().hex[:24]}", int(time.time())

    def chunk(delta: dict[str, str], finish: str | None = None) -> str:
        return "data: " + json.dumps({
            "id": cid, "object": "chat.completion.chunk", "created": created, "model": model,
            "choices": [{"index": 0, "delta": delta, "finish_reason": finish}]}) + "\n\n"

    stats.enter()
    outcome = "disconnected"
    try:
        if not await wait_or_disconnect(request, latency / 2):
            return
        pieces = _chunks(content)
        gap = latency / 2 / max(1, len(pieces))
        yield chunk({"role": "assistant", "content": ""})
        for piece in _chunks(thought) if thought else []:
            yield chunk({"reasoning_content": piece})
        for piece in pieces:
            if not await wait_or_disconnect(request, gap):
                return
            yield chunk({"content": piece})
        yield chunk({}, "stop")
        if usage is not None:
            yield "data: " + json.dumps({
                "id": cid, "object": "chat.completion.chunk", "created": created,
                "model": model, "choices": [], "usage": usage}) + "\n\n"
        yield "data: [DONE]\n\n"
        outcome = "ok"
    finally:
        stats.leave()
        stats.outcome(outcome)


# --------------------------------------------------------------------------- running it


class FakeLLMSettings(BaseSettings):
    """``AESOP_FAKE_LLM_*`` environment variables -> :class:`FakeLLMConfig`."""

    model_config = SettingsConfigDict(env_prefix="AESOP_FAKE_LLM_", extra="ignore")

    profile: Profile = Field(
        default="fixed",
        description="the latency profile: `fixed`, `normal`, `bimodal` (the paper's "
                    "GPT-3.5-turbo latencies) or `stall` (never answers)")
    fixed_s: float = Field(default=0.0, ge=0, description="the latency of profile `fixed` (s)")
    mean_s: float = Field(default=3.1, ge=0, description="the mean of profile `normal` (s)")
    std_s: float = Field(default=0.85, ge=0,
                         description="the standard deviation of profile `normal` (s)")
    time_scale: float = Field(default=1.0, ge=0, description="multiplies every delay")
    seed: int = Field(default=0, description="seeds the latencies and the failures injected")
    rate_429: float = Field(default=0.0, ge=0, le=1, description="the fraction answered 429")
    rate_5xx: float = Field(default=0.0, ge=0, le=1, description="the fraction answered 500")
    rate_garbage: float = Field(default=0.0, ge=0, le=1,
                                description="the fraction answered with malformed output")
    retry_after_s: int = Field(default=1, ge=0,
                               description="the `Retry-After` header of a 429 (s)")

    def to_config(self) -> FakeLLMConfig:
        return FakeLLMConfig(**self.model_dump())


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="fake-llm", description=__doc__.splitlines()[0])
    p.add_argument("--host")
    p.add_argument("--port", type=int)
    p.add_argument("--profile", choices=["fixed", "normal", "bimodal", "stall"])
    for flag, kind in (("fixed-s", float), ("mean-s", float), ("std-s", float),
                       ("time-scale", float), ("seed", int), ("rate-429", float),
                       ("rate-5xx", float), ("rate-garbage", float), ("retry-after-s", int)):
        p.add_argument(f"--{flag}", type=kind)
    p.add_argument("--log-level", choices=["debug", "info", "warning", "error"])
    return p


class FakeLLMServiceSettings(ServiceSettings):
    """Host and port (``AESOP_FAKE_LLM_HOST``, ``_PORT``; 8010 by default), log level; the
    admin token is the key every request wants."""

    model_config = SettingsConfigDict(env_prefix="AESOP_FAKE_LLM_", extra="ignore",
                                      validate_by_name=True)

    port: int = Field(default=DEFAULT_PORT, ge=0, le=65535, description="HTTP port")


def main(argv: list[str] | None = None) -> int:
    """Serve until SIGINT/SIGTERM. Flags override ``AESOP_FAKE_LLM_*`` / ``AESOP_*`` env."""
    import uvicorn

    args = {k: v for k, v in vars(build_parser().parse_args(argv)).items() if v is not None}
    service = {k: args.pop(k) for k in ("host", "port", "log_level") if k in args}
    config = FakeLLMSettings(**args).to_config()
    settings = FakeLLMServiceSettings(**service)
    try:
        settings.check_exposure()
    except ValueError as exc:
        print(f"fake-llm: {exc}", file=sys.stderr)
        return 2
    # Not shared.http.serve: a stalled request must not hold shutdown for long.
    uvicorn.run(create_app(config, settings.admin_token), host=settings.host, port=settings.port,
                log_level=settings.log_level, access_log=False, timeout_graceful_shutdown=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
