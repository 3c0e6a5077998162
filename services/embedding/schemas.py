"""What the vector-cache service's routes take and answer, as pydantic models.

The routes declare them (so ``/openapi.json`` documents every shape), the
domain code returns the answers, and :mod:`.client` parses them back: one
definition for the server, its clients and its tests.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from shared.messages import Neighbor

from .cache import Cache, ScoreKind
from .calibration import Method
from .index import IndexKind

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Id = Annotated[str, Field(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.:\-]+$")]


class Body(BaseModel):
    """A request body: unknown fields are refused (422 naming them)."""

    model_config = ConfigDict(extra="forbid")


class Answer(BaseModel):
    """A response body. Clients ignore fields they do not know (a newer server)."""

    model_config = ConfigDict(extra="ignore")


# --------------------------------------------------------------------------- requests


class CreateCache(Body):
    model: str | None = Field(default=None, min_length=1, max_length=512)
    dim: int | None = Field(default=None, ge=1, le=16384)
    k: int | None = Field(default=None, ge=1, le=1000)
    score: ScoreKind = "topk"
    index: IndexKind = "flat"


class ItemIn(Body):
    text: str = Field(min_length=1)
    id: Id | None = None
    metadata: dict[str, Any] = Field(default_factory=dict)


class AddExperiences(Body):
    items: list[ItemIn] | None = None
    vectors: list[list[FiniteFloat]] | None = None
    ids: list[Id] | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> AddExperiences:
        if (self.items is None) == (self.vectors is None):
            raise ValueError("send either 'items' (texts) or 'vectors'")
        if self.ids is not None and (self.vectors is None or len(self.ids) != len(self.vectors)):
            raise ValueError("'ids' must accompany 'vectors', one id per vector")
        return self


class LabelledIn(Body):
    text: str = Field(min_length=1)
    label: Literal["nominal", "anomaly"]


class Calibrate(Body):
    method: Method
    alpha: float | None = Field(default=None, gt=0.0, lt=1.0)
    tpr: float | None = Field(default=None, gt=0.0, le=1.0)
    calibration: list[LabelledIn] | None = None


class Score(Body):
    texts: list[str] | None = None
    vectors: list[list[FiniteFloat]] | None = None
    k: int | None = Field(default=None, ge=1, le=1000)

    @model_validator(mode="after")
    def _one_kind(self) -> Score:
        if (self.texts is None) == (self.vectors is None):
            raise ValueError("send either 'texts' or 'vectors'")
        return self


# --------------------------------------------------------------------------- answers


class CalibrationInfo(Answer):
    """tau and how it was obtained (``services.embedding.calibration.Calibration``)."""

    method: Method
    threshold: float  # tau: anomaly iff score > tau
    alpha: float | None
    n: int
    tpr: float | None = None
    fpr: float | None = None
    auroc: float | None = None
    target_tpr: float | None = None


class CacheCalibration(CalibrationInfo):
    stale: bool  # experiences changed since tau was computed


class CacheInfo(Answer):
    """``GET /v1/caches/{name}``, and the answer of ``PUT``."""

    name: str
    size: int
    dim: int
    model: str | None
    k: int
    score: ScoreKind
    index: IndexKind
    threshold: float | None
    calibration: CacheCalibration | None
    version: int

    @classmethod
    def of(cls, cache: Cache) -> CacheInfo:
        cal = None
        if cache.calibration is not None:
            cal = CacheCalibration(**cache.calibration.to_dict(), stale=cache.stale)
        c = cache.config
        return cls(name=c.name, size=cache.size, dim=c.dim, model=c.model, k=c.k,
                   score=c.score, index=c.index, threshold=cache.threshold, calibration=cal,
                   version=cache.version)


class CacheList(Answer):
    caches: list[CacheInfo]


class Added(Answer):
    """Experiences added (durable when this is answered)."""

    ids: list[str]
    size: int
    version: int
    job: str | None = None  # the job that did it (``GET /v1/jobs/{id}``)


class Experience(Answer):
    id: str
    text: str | None
    metadata: dict[str, Any]


class Deleted(Answer):
    id: str
    size: int
    version: int


class Roc(Answer):
    fpr: list[float]
    tpr: list[float]
    thresholds: list[float | None]  # None for an infinite threshold


class Calibrated(CalibrationInfo):
    """``POST /v1/caches/{name}/calibrate``: tau, stored with the cache."""

    cache: str
    version: int
    roc: Roc | None = None  # for a labelled calibration set with both classes


class ScoreResult(Answer):
    score: float  # s(e_t; D_e): higher is more anomalous
    is_anomaly: bool | None  # None while the cache has no tau
    neighbors: list[Neighbor]


class Scores(Answer):
    """``POST /v1/caches/{name}/score``."""

    results: list[ScoreResult]
    threshold: float | None
    stale: bool
    k: int
    model: str | None
    version: int
