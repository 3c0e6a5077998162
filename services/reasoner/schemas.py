"""What the slow-reasoner service's routes take and answer (``/openapi.json``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from shared.messages import (
    MAX_DETECTIONS,
    DetectionMatch,
    Float,
    Int,
    Observation,
    Option,
    PairMatch,
)


class ReasonBody(BaseModel):
    model_config = ConfigDict(extra="forbid")

    request_id: str | None = Field(default=None, min_length=1, max_length=128)
    observation: Observation
    options: list[Option] = Field(min_length=1)
    deadline_s: Float = Field(gt=0.0)
    unusual: list[DetectionMatch] = Field(default_factory=list, max_length=MAX_DETECTIONS)
    unusual_pair: PairMatch | None = None

    @field_validator("options")
    @classmethod
    def _unique_indices(cls, options: list[Option]) -> list[Option]:
        indices = [o.index for o in options]
        if len(set(indices)) != len(indices):
            raise ValueError("option indices must be unique")
        return options


class CalibrateBody(BaseModel):
    model_config = ConfigDict(extra="forbid")

    n: Int = Field(default=100, ge=1, le=10_000)
    warmup: Int = Field(default=3, ge=0, le=100)
    quantile: Float = Field(default=0.95, gt=0.0, lt=1.0)
    confidence: Float = Field(default=0.95, gt=0.0, lt=1.0)
    timeout_s: Float = Field(default=30.0, gt=0.0, le=600.0)
    backend: Literal["primary", "hedge"] = "primary"
    observation: Observation | None = None  # default: the quadrotor red-box scene
    options: list[Option] | None = None


class BackendInfo(BaseModel):
    name: str  # primary or hedge
    base_url: str
    model: str
    stream: bool
    json_schema: bool
    response_format: str  # the shape of JSON mode's request: json_schema or json_object


class Backends(BaseModel):
    """``GET /v1/backends``: the configured LLM backends and the decision policy."""

    backends: list[BackendInfo]
    hedge_after_s: Float | None
    domain: str
    variant: Literal["cot", "single"]
    fallback: Literal["first_recovery", "rank"]
