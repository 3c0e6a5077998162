"""Settings of the slow-reasoner service (``AESOP_REASONER_*``, and the shared ``AESOP_*``)."""

from __future__ import annotations

import re
from typing import Literal
from urllib.parse import urlsplit

from pydantic import AliasChoices, Field, SecretStr, field_validator
from pydantic_settings import SettingsConfigDict

from shared.settings import ServiceSettings

from .backends import BackendConfig, TokenField

OPENAI_REASONING = re.compile(r"(?:openai/)?(?:o\d|gpt-5)", re.IGNORECASE)


class ReasonerSettings(ServiceSettings):
    model_config = SettingsConfigDict(env_prefix="AESOP_REASONER_", extra="ignore",
                                      validate_by_name=True)

    port: int = Field(default=8002, ge=0, le=65535)
    # the primary backend: any OpenAI-compatible server (default: `aesop serve fake-llm`)
    llm_base_url: str = "http://127.0.0.1:8010/v1"
    llm_model: str = "fake"
    llm_api_key: SecretStr | None = Field(default=None, validation_alias=AliasChoices(
        "AESOP_REASONER_LLM_API_KEY", "OPENAI_API_KEY"))
    llm_stream: bool = True
    llm_json_schema: bool = False  # ask for {"reasoning", "answer"} where servers support it
    # the shape of that request: OpenAI's json_schema (vLLM, Ollama, llama.cpp's server),
    # or json_object with a schema (llama-cpp-python's server)
    llm_response_format: Literal["json_schema", "json_object"] = "json_schema"
    # JSON mode: the reasoning's maxLength, so that a small local model's grammar closes
    # the string before max_tokens cuts the JSON off (OpenAI's strict mode may refuse it)
    llm_max_reasoning_chars: int | None = Field(default=None, ge=1)
    llm_max_tokens: int = Field(default=512, ge=1)
    # the name the limit is sent under; auto: max_completion_tokens for api.openai.com
    # (its reasoning models refuse max_tokens), max_tokens for every other server
    llm_token_field: Literal["auto", "max_tokens", "max_completion_tokens"] = "auto"
    # a number in [0, 2], or "omit" (not sent); auto: 0, left out for OpenAI's reasoning
    # models (o1, o3, o4, gpt-5 ...), which refuse any but their default
    llm_temperature: float | Literal["auto", "omit"] = "auto"
    # an optional second backend, asked when the first has not answered after hedge_after_s
    hedge_base_url: str | None = None
    hedge_model: str | None = None
    hedge_after_s: float | None = Field(default=None, gt=0.0)
    domain: str = "quadrotor"  # prompt template: quadrotor, vtol, warehouse, vehicle
    variant: Literal["cot", "single"] = "cot"
    fallback: Literal["first_recovery", "rank"] = "first_recovery"
    # rank policy: option label -> rank, lower is more conservative; JSON in the environment
    fallback_ranks: dict[str, int] = Field(default_factory=dict)
    max_observation_chars: int = Field(default=4000, ge=1)
    max_options: int = Field(default=16, ge=1)
    max_deadline_s: float = Field(default=120.0, gt=0.0)
    # latency calibrations running at once: each of their queries is an LLM call
    max_calibration_jobs: int = Field(default=1, ge=1)

    @field_validator("hedge_base_url", "hedge_model", mode="before")
    @classmethod
    def _empty_is_none(cls, v: object) -> object:
        return None if v == "" else v

    @field_validator("llm_temperature")
    @classmethod
    def _temperature_range(cls, v: float | str) -> float | str:
        if isinstance(v, float) and not 0.0 <= v <= 2.0:
            raise ValueError("a temperature is in [0, 2] (or auto, or omit)")
        return v

    def token_field(self, base_url: str) -> TokenField:
        if self.llm_token_field != "auto":
            return self.llm_token_field
        host = (urlsplit(base_url).hostname or "").lower()
        return "max_completion_tokens" if host.endswith("openai.com") else "max_tokens"

    def temperature(self, model: str) -> float | None:
        if self.llm_temperature == "omit":
            return None
        if self.llm_temperature == "auto":
            return None if OPENAI_REASONING.match(model) else 0.0
        return self.llm_temperature

    def backends(self) -> list[BackendConfig]:
        """The configured LLM backends: the primary, then the hedge if there is one."""
        key = self.llm_api_key.get_secret_value() if self.llm_api_key else None
        configs = [BackendConfig(
            name="primary", base_url=self.llm_base_url, model=self.llm_model, api_key=key,
            max_tokens=self.llm_max_tokens, temperature=self.temperature(self.llm_model),
            stream=self.llm_stream, json_schema=self.llm_json_schema,
            token_field=self.token_field(self.llm_base_url),
            response_format=self.llm_response_format,
            max_reasoning_chars=self.llm_max_reasoning_chars)]
        if self.hedge_model:
            base_url = self.hedge_base_url or self.llm_base_url
            configs.append(BackendConfig(
                name="hedge", base_url=base_url, model=self.hedge_model, api_key=key,
                max_tokens=self.llm_max_tokens, temperature=self.temperature(self.hedge_model),
                stream=self.llm_stream, json_schema=self.llm_json_schema,
                token_field=self.token_field(base_url),
                response_format=self.llm_response_format,
                max_reasoning_chars=self.llm_max_reasoning_chars))
        return configs
