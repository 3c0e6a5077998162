"""Settings of the slow-reasoner service (``AESOP_REASONER_*``, and the shared ``AESOP_*``)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit

from pydantic import AliasChoices, Field, SecretStr, field_validator, model_validator
from pydantic_settings import SettingsConfigDict

from shared.settings import Group, ServiceSettings

from .backends import BackendConfig, TokenField

OPENAI_REASONING = re.compile(r"(?:openai/)?(?:o\d|gpt-5)", re.IGNORECASE)


class LLMRequest(Group):
    """How the backends are asked (``AESOP_REASONER_REQUEST``), for servers that differ."""

    stream: bool = Field(default=True, description="SSE, cut off once the answer line parses")
    json_schema: bool = Field(
        default=False,
        description='ask for `{"reasoning", "answer"}`, the answer an `enum` of the offered '
                    "option indices, where servers support it")
    response_format: Literal["json_schema", "json_object"] = Field(
        default="json_schema",
        description="the shape of that request: `json_schema` for OpenAI, vLLM, Ollama, "
                    "llama.cpp's `llama-server`; `json_object` with a schema for "
                    "llama-cpp-python's server, which answers the other with a 500 that "
                    "names this knob")
    max_reasoning_chars: int | None = Field(
        default=None, ge=1,
        description="JSON mode: the reasoning's `maxLength`, so a small local model's "
                    "grammar closes it before `max_tokens` cuts the JSON off; OpenAI's "
                    "strict mode may refuse it")
    answer_first: bool = Field(
        default=False,
        description="JSON mode: the schema asks for the answer before the reasoning, and a "
                    'stream ends once `{"answer": n` is complete: a slow model\'s decision in '
                    "a few tokens, its text `FINAL ANSWER: n`, without reasoning")
    max_tokens: int = Field(default=512, ge=1, description="the completion's token limit")
    token_field: Literal["auto", "max_tokens", "max_completion_tokens"] = Field(
        default="auto",
        description="the name the limit is sent under; `auto`: `max_completion_tokens` for "
                    "`api.openai.com`, whose reasoning models refuse `max_tokens`; else "
                    "`max_tokens`")
    temperature: float | Literal["auto", "omit"] = Field(
        default="auto",
        description="`auto`: 0, left out for OpenAI's reasoning models `o1`, `o3`, `o4`, "
                    "`gpt-5` ..., which refuse any but their default; a number in [0, 2]; or "
                    "`omit`: not sent")

    @field_validator("temperature")
    @classmethod
    def _temperature_range(cls, v: float | str) -> float | str:
        if isinstance(v, float) and not 0.0 <= v <= 2.0:
            raise ValueError("a temperature is in [0, 2] (or auto, or omit)")
        return v


class Hedge(Group):
    """An optional second backend (``AESOP_REASONER_HEDGE``), enabled by its model, asked
    when the first has not answered after ``after_s`` (none: only when the first fails)."""

    model: str | None = Field(default=None,
                              description="the second backend's model; none: no hedge")
    base_url: str | None = Field(default=None, description="its server; none: the primary's")
    after_s: float | None = Field(default=None, gt=0.0,
                                  description="the hedging delay, s; none: failover only")

    @field_validator("model", "base_url", mode="before")
    @classmethod
    def _empty_is_none(cls, v: object) -> object:
        return None if v == "" else v


class ReasonerLimits(Group):
    """What a request may carry (``AESOP_REASONER_LIMITS``): past a limit, 422 over HTTP;
    dropped and counted on the bus."""

    max_observation_chars: int = Field(default=4000, ge=1,
                                       description="characters of the observation")
    max_options: int = Field(default=16, ge=1, description="options offered")
    max_deadline_s: float = Field(default=120.0, gt=0.0, description="the deadline, s")
    max_calibration_jobs: int = Field(
        default=1, ge=1,
        description="latency calibrations at once, each of their queries an LLM call; 429")


class ReasonerSettings(ServiceSettings):
    model_config = SettingsConfigDict(env_prefix="AESOP_REASONER_", extra="ignore",
                                      validate_by_name=True)

    port: int = Field(default=8002, ge=0, le=65535, description="HTTP port")
    llm_base_url: str = Field(
        default="http://127.0.0.1:8010/v1",
        description="the primary backend: any OpenAI-compatible server (the default: "
                    "`aesop serve fake-llm`)")
    llm_model: str = Field(default="fake", description="the primary backend's model")
    llm_api_key: SecretStr | None = Field(
        default=None,
        validation_alias=AliasChoices("AESOP_REASONER_LLM_API_KEY", "OPENAI_API_KEY"),
        description="key, also used by the hedge backend")
    llm_api_key_file: Path | None = Field(
        default=None,
        description="unless a key is set, the key's first line from a file (a compose "
                    "secret: not in `docker inspect`)")
    request: LLMRequest = Field(
        default=LLMRequest(),
        description="how the backends are asked, for servers that differ; a server's 400 "
                    "for a refused parameter names the knob to change")
    hedge: Hedge = Field(
        default=Hedge(),
        description="a second backend, enabled by its `model`, asked when the first has not "
                    "answered after `after_s` (none: only when the first fails)")
    domain: str = Field(default="quadrotor",
                        description="the prompt template: `quadrotor`, `vtol`, `warehouse`, "
                                    "`vehicle`")
    variant: Literal["cot", "single"] = Field(default="cot",
                                              description="its form: `cot` or `single`")
    fallback: Literal["first_recovery", "rank"] = Field(
        default="first_recovery", description="fallback policy: `first_recovery` or `rank`")
    fallback_ranks: dict[str, int] = Field(
        default_factory=dict,
        description="the `rank` policy's ranks: JSON option label -> rank, lower = more "
                    "conservative")
    limits: ReasonerLimits = Field(
        default=ReasonerLimits(),
        description="what a request may carry: past a limit, 422 on `POST /v1/reason`; on "
                    "the bus dropped, counted in `aesop_reasoner_bus_rejected_total{field}`")

    @model_validator(mode="after")
    def _key_from_file(self) -> ReasonerSettings:
        if self.llm_api_key_file is not None and self.llm_api_key is None:
            try:
                key = self.llm_api_key_file.read_text().strip()
            except OSError as exc:
                raise ValueError(f"AESOP_REASONER_LLM_API_KEY_FILE: cannot read "
                                 f"{self.llm_api_key_file}: {exc.strerror}") from None
            if not key:
                raise ValueError(f"AESOP_REASONER_LLM_API_KEY_FILE: {self.llm_api_key_file} "
                                 "is empty")
            self.llm_api_key = SecretStr(key)
        return self

    def token_field(self, base_url: str) -> TokenField:
        if self.request.token_field != "auto":
            return self.request.token_field
        host = (urlsplit(base_url).hostname or "").lower()
        return "max_completion_tokens" if host.endswith("openai.com") else "max_tokens"

    def temperature(self, model: str) -> float | None:
        if self.request.temperature == "omit":
            return None
        if self.request.temperature == "auto":
            return None if OPENAI_REASONING.match(model) else 0.0
        return self.request.temperature

    def backends(self) -> list[BackendConfig]:
        """The configured LLM backends: the primary, then the hedge if there is one."""
        targets = [("primary", self.llm_base_url, self.llm_model)]
        if self.hedge.model:
            targets.append(("hedge", self.hedge.base_url or self.llm_base_url, self.hedge.model))
        key = self.llm_api_key.get_secret_value() if self.llm_api_key else None
        ask = self.request
        return [BackendConfig(
            name=name, base_url=base_url, model=model, api_key=key, max_tokens=ask.max_tokens,
            temperature=self.temperature(model), stream=ask.stream, json_schema=ask.json_schema,
            token_field=self.token_field(base_url), response_format=ask.response_format,
            max_reasoning_chars=ask.max_reasoning_chars, answer_first=ask.answer_first)
            for name, base_url, model in targets]
