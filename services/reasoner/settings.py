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

    stream: bool = True
    json_schema: bool = False  # ask for {"reasoning", "answer"} where servers support it
    # the shape of that request: OpenAI's json_schema (vLLM, Ollama, llama.cpp's server),
    # or json_object with a schema (llama-cpp-python's server)
    response_format: Literal["json_schema", "json_object"] = "json_schema"
    # JSON mode: the reasoning's maxLength, so that a small local model's grammar closes
    # the string before max_tokens cuts the JSON off (OpenAI's strict mode may refuse it)
    max_reasoning_chars: int | None = Field(default=None, ge=1)
    # JSON mode: the answer before the reasoning, and the stream ended once the answer is
    # out (a slow model's decision in a few tokens; its reasoning is not waited for)
    answer_first: bool = False
    max_tokens: int = Field(default=512, ge=1)
    # the name the limit is sent under; auto: max_completion_tokens for api.openai.com
    # (its reasoning models refuse max_tokens), max_tokens for every other server
    token_field: Literal["auto", "max_tokens", "max_completion_tokens"] = "auto"
    # a number in [0, 2], or "omit" (not sent); auto: 0, left out for OpenAI's reasoning
    # models (o1, o3, o4, gpt-5 ...), which refuse any but their default
    temperature: float | Literal["auto", "omit"] = "auto"

    @field_validator("temperature")
    @classmethod
    def _temperature_range(cls, v: float | str) -> float | str:
        if isinstance(v, float) and not 0.0 <= v <= 2.0:
            raise ValueError("a temperature is in [0, 2] (or auto, or omit)")
        return v


class Hedge(Group):
    """An optional second backend (``AESOP_REASONER_HEDGE``), enabled by its model, asked
    when the first has not answered after ``after_s`` (none: only when the first fails)."""

    model: str | None = None
    base_url: str | None = None  # none: the primary's
    after_s: float | None = Field(default=None, gt=0.0)

    @field_validator("model", "base_url", mode="before")
    @classmethod
    def _empty_is_none(cls, v: object) -> object:
        return None if v == "" else v


class ReasonerLimits(Group):
    """What a request may carry (``AESOP_REASONER_LIMITS``): past a limit, 422 over HTTP;
    dropped and counted on the bus."""

    max_observation_chars: int = Field(default=4000, ge=1)
    max_options: int = Field(default=16, ge=1)
    max_deadline_s: float = Field(default=120.0, gt=0.0)
    # latency calibrations running at once: each of their queries is an LLM call
    max_calibration_jobs: int = Field(default=1, ge=1)


class ReasonerSettings(ServiceSettings):
    model_config = SettingsConfigDict(env_prefix="AESOP_REASONER_", extra="ignore",
                                      validate_by_name=True)

    port: int = Field(default=8002, ge=0, le=65535)
    # the primary backend: any OpenAI-compatible server (default: `aesop serve fake-llm`)
    llm_base_url: str = "http://127.0.0.1:8010/v1"
    llm_model: str = "fake"
    llm_api_key: SecretStr | None = Field(default=None, validation_alias=AliasChoices(
        "AESOP_REASONER_LLM_API_KEY", "OPENAI_API_KEY"))
    # or, unless that is set, the key's first line from a file (a compose secret: not in
    # `docker inspect`)
    llm_api_key_file: Path | None = None
    request: LLMRequest = LLMRequest()
    hedge: Hedge = Hedge()
    domain: str = "quadrotor"  # prompt template: quadrotor, vtol, warehouse, vehicle
    variant: Literal["cot", "single"] = "cot"
    fallback: Literal["first_recovery", "rank"] = "first_recovery"
    # rank policy: option label -> rank, lower is more conservative; JSON in the environment
    fallback_ranks: dict[str, int] = Field(default_factory=dict)
    limits: ReasonerLimits = ReasonerLimits()

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
