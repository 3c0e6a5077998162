"""What the vector-cache service's routes take and answer, as pydantic models.

The routes declare them (so ``/openapi.json`` documents every shape), the
domain code returns the answers, and :mod:`.client` parses them back: one
definition for the server, its clients and its tests.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal, TypeVar

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic.json_schema import SkipJsonSchema

from shared.messages import (
    MAX_DETECTIONS,
    Detection,
    DetectionMatch,
    Float,
    Int,
    Neighbor,
    NotBool,
    PairMatch,
)

from .detector.cache import Cache, ScoreKind
from .detector.calibration import Method
from .detector.index import IndexKind
from .detector.policy import NEEDS_LABELLED, needs_labelled
from .detector.proposals import Policy, Proposal, State

# any finite number: vectors are scaled to unit length in float64 before they are
# stored as float32, so neither 1e300 nor 1e-300 overflows or vanishes
Number = Annotated[Float, Field(allow_inf_nan=False)]
# a vector has a direction: at least one number is not zero
Vector = Annotated[list[Number], Field(min_length=1, json_schema_extra={
    "contains": {"not": {"const": 0}}})]
Id = Annotated[str, Field(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.:\-]+$")]
Text = Annotated[str, Field(min_length=1, pattern=r"\S")]  # not only whitespace
T = TypeVar("T")
NonEmpty = Annotated[list[T], Field(min_length=1)]


def schema_extra(**extra: Any) -> Callable[[dict[str, Any]], None]:
    """``json_schema_extra`` adding ``extra`` and dropping the ``"default": null`` of
    properties that may be left out but are never null (see ``refuse_nulls``)."""
    def edit(schema: dict[str, Any]) -> None:
        for prop in schema.get("properties", {}).values():
            if prop.get("default", ...) is None and "anyOf" not in prop:
                del prop["default"]
        schema.update(extra)
    return edit


def exactly_one_of(*keys: str) -> dict[str, Any]:
    """JSON Schema for "exactly one of these keys" (the model validates the same)."""
    return {"oneOf": [{"required": [key]} for key in keys]}


def refuse_nulls(data: Any, *keys: str) -> Any:
    """Optional keys whose schema has no null: an explicit null is refused, as the schema says."""
    if isinstance(data, dict):
        for key in keys:
            if key in data and data[key] is None:
                raise ValueError(f"'{key}' may be left out but not null")
    return data


@dataclass(frozen=True)
class Item:
    """An experience to add as ``CacheService.add`` takes it (the routes make one of each
    :class:`ItemIn` or vector): text (embedded by the cache's model) or a raw vector."""

    text: str | None = None
    vector: Sequence[float] | None = None
    id: str | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)
    detections: tuple[Detection, ...] = ()


class Body(BaseModel):
    """A request body: unknown fields are refused (422 naming them)."""

    model_config = ConfigDict(extra="forbid")


class Answer(BaseModel):
    """A response body. Clients ignore fields they do not know (a newer server)."""

    model_config = ConfigDict(extra="ignore")


# --------------------------------------------------------------------------- requests


class CreateCache(Body):
    model: str | None = Field(default=None, min_length=1, max_length=512)
    dim: Annotated[int, Field(ge=1, le=16384), NotBool] | None = None
    k: Annotated[int, Field(ge=1, le=1000), NotBool] | None = None
    score: ScoreKind = "topk"
    index: IndexKind = "flat"
    # what a scene the reasoner answered "continue" for becomes: a proposal to review, or
    # an experience at once; left out: "review" for a new cache, unchanged for another
    proposals: Policy | SkipJsonSchema[None] = None

    @model_validator(mode="before")
    @classmethod
    def _no_nulls(cls, data: Any) -> Any:
        return refuse_nulls(data, "proposals")


Detections = Annotated[list[Detection], Field(max_length=MAX_DETECTIONS)]


class ItemIn(Body):
    text: Text
    id: Id | None = None
    metadata: dict[str, Any] = Field(default_factory=dict)
    detections: Detections = Field(default_factory=list)  # as Observation.detections


class AddExperiences(Body):
    """Either ``items`` (texts, embedded by the cache's model) or ``vectors`` with
    optional ``ids`` (one per vector, no repeats)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=schema_extra(oneOf=[
        {"required": ["items"], "not": {"required": ["ids"]}}, {"required": ["vectors"]}]))

    items: NonEmpty[ItemIn] | SkipJsonSchema[None] = None
    vectors: NonEmpty[Vector] | SkipJsonSchema[None] = None
    ids: Annotated[list[Id], Field(min_length=1, json_schema_extra={"uniqueItems": True})] \
        | SkipJsonSchema[None] = None

    @model_validator(mode="before")
    @classmethod
    def _no_nulls(cls, data: Any) -> Any:
        return refuse_nulls(data, "items", "vectors", "ids")

    @model_validator(mode="after")
    def _one_kind(self) -> AddExperiences:
        if (self.items is None) == (self.vectors is None):
            raise ValueError("send either 'items' (texts) or 'vectors'")
        if self.ids is not None and (self.vectors is None or len(self.ids) != len(self.vectors)):
            raise ValueError("'ids' must accompany 'vectors', one id per vector")
        return self


class LabelledIn(Body):
    text: Text
    label: Literal["nominal", "anomaly"]
    detections: Detections = Field(default_factory=list)


class Calibrate(Body):
    """``loo-quantile`` (eq. 2) needs nothing but the cache; ``conformal`` and
    ``tpr-target`` need a labelled ``calibration`` set."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"if": {
        "properties": {"method": {"enum": list(NEEDS_LABELLED)}}},
        "then": {"required": ["calibration"], "properties": {
            "calibration": {"type": "array", "minItems": 1}}}})

    method: Method
    alpha: Annotated[float, Field(gt=0.0, lt=1.0), NotBool] | None = None
    tpr: Annotated[float, Field(gt=0.0, le=1.0), NotBool] | None = None
    calibration: list[LabelledIn] | None = Field(default=None, validate_default=True)
    # score pairs of detections too (loo-quantile, conformal): two nominal objects that no
    # nominal experience shows together; a third p-value in the Bonferroni combination
    pairs: StrictBool = False

    @field_validator("calibration")
    @classmethod
    def _labelled_set(cls, value: list[LabelledIn] | None, info: ValidationInfo
                      ) -> list[LabelledIn] | None:
        method = info.data.get("method")
        if method is not None and needs_labelled(method) and not value:
            raise ValueError(f"{method} calibration needs a labelled calibration set")
        return value


class QueryIn(Body):
    text: Text
    detections: Detections = Field(default_factory=list)  # as Observation.detections


class Score(Body):
    """One of ``texts``, ``queries`` (texts with their detections) or ``vectors``; ``k``
    defaults to the cache's."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=schema_extra(
        **exactly_one_of("texts", "queries", "vectors")))

    texts: NonEmpty[Text] | SkipJsonSchema[None] = None
    queries: NonEmpty[QueryIn] | SkipJsonSchema[None] = None
    vectors: NonEmpty[Vector] | SkipJsonSchema[None] = None
    k: Annotated[int, Field(ge=1, le=1000), NotBool] | None = None

    @model_validator(mode="before")
    @classmethod
    def _no_nulls(cls, data: Any) -> Any:
        return refuse_nulls(data, "texts", "queries", "vectors")

    @model_validator(mode="after")
    def _one_kind(self) -> Score:
        if sum(x is not None for x in (self.texts, self.queries, self.vectors)) != 1:
            raise ValueError("send one of 'texts', 'queries' or 'vectors'")
        return self


# --------------------------------------------------------------------------- answers


class CalibrationInfo(Answer):
    """tau and how it was obtained (``services.embedding.detector.calibration.Calibration``)."""

    method: Method
    threshold: Float  # tau: anomaly iff score > tau
    alpha: Float | None
    n: Int
    tpr: Float | None = None
    fpr: Float | None = None
    auroc: Float | None = None
    target_tpr: Float | None = None
    pairs: bool = False  # verdicts with detections combine three p-values (pairs too)


class CacheCalibration(CalibrationInfo):
    stale: bool  # experiences changed since tau was computed


class CacheInfo(Answer):
    """``GET /v1/caches/{name}``, and the answer of ``PUT``."""

    name: str
    size: Int
    dim: Int
    model: str | None
    k: Int
    score: ScoreKind
    index: IndexKind
    threshold: Float | None
    calibration: CacheCalibration | None
    version: Int
    detections: Int = 0  # distinct detections of the experiences (the nominal ones)
    proposals: Policy = "review"

    @classmethod
    def of(cls, cache: Cache) -> CacheInfo:
        cal = None
        if cache.calibration is not None:
            cal = CacheCalibration(**cache.calibration.to_dict(), stale=cache.stale)
        c = cache.config
        return cls(name=c.name, size=cache.size, dim=c.dim, model=c.model, k=c.k,
                   score=c.score, index=c.index, threshold=cache.threshold, calibration=cal,
                   version=cache.version, detections=len(cache.detection_counts),
                   proposals=c.proposals)


class CacheList(Answer):
    caches: list[CacheInfo]


class Added(Answer):
    """Experiences added (durable when this is answered)."""

    ids: list[str]
    size: Int
    version: Int
    job: str | None = None  # the job that did it (``GET /v1/jobs/{id}``)


class Experience(Answer):
    id: str
    text: str | None
    metadata: dict[str, Any]
    detections: list[Detection] = Field(default_factory=list)


class Deleted(Answer):
    id: str
    size: Int
    version: Int


class Roc(Answer):
    fpr: list[Float]
    tpr: list[Float]
    thresholds: list[Float | None]  # None for an infinite threshold


class Calibrated(CalibrationInfo):
    """``POST /v1/caches/{name}/calibrate``: tau, stored with the cache."""

    cache: str
    version: Int
    roc: Roc | None = None  # for a labelled calibration set with both classes


class ScoreResult(Answer):
    score: Float  # s(e_t; D_e): higher is more anomalous
    is_anomaly: bool | None  # None while the cache has no tau
    neighbors: list[Neighbor]
    detection_score: Float | None = None  # the worst detection's (with detections)
    p_value: Float | None = None  # combined; anomaly iff below 1 - alpha
    detections: list[DetectionMatch] = Field(default_factory=list)  # least nominal first
    pair_score: Float | None = None  # the worst pair's (pairs calibrated, 2+ detections)
    pair: PairMatch | None = None  # that pair, unless a nominal experience holds it as is


class ProposalInfo(Answer):
    """A scene the slow reasoner answered "continue" for, proposed as nominal."""

    id: str  # the scene's id: the experience's once accepted
    state: State
    count: Int  # times proposed
    text: str
    detections: list[Detection]
    task: str
    robot: str
    seq: Int  # the flagged observation's, the first time
    request_id: str
    model: str  # the LLM that answered "continue"
    rationale: str
    score: Float  # the detector's, the first time
    p_value: Float | None
    first_at: Float
    last_at: Float
    decided_at: Float | None
    # why only a person may accept it (its text or detections trip, or nearly trip, the
    # injection tripwire); None: nothing suspicious
    flag: str | None = None

    @classmethod
    def of(cls, p: Proposal) -> ProposalInfo:
        return cls(id=p.id, state=p.state, count=p.count, text=p.text,
                   detections=list(p.detections), task=p.task, robot=p.robot, seq=p.seq,
                   request_id=p.request_id, model=p.model, rationale=p.rationale,
                   score=p.score, p_value=p.p_value, first_at=p.first_at, last_at=p.last_at,
                   decided_at=p.decided_at, flag=p.flag)


class ProposalList(Answer):
    """``GET /v1/caches/{name}/proposals``."""

    cache: str
    policy: Policy
    proposals: list[ProposalInfo]


class ReviewMany(Body):
    """``POST /v1/caches/{name}/proposals/accept|reject``: a batch review, in this order."""

    ids: list[str] = Field(min_length=1, max_length=1000)


class Reviewed(Answer):
    """The proposals a batch review decided, and the cache after it (its calibration
    recomputed from the accepted scenes under the policy ``window``)."""

    proposals: list[ProposalInfo]
    cache: CacheInfo


class Scores(Answer):
    """``POST /v1/caches/{name}/score``."""

    results: list[ScoreResult]
    threshold: Float | None
    stale: bool
    k: Int
    model: str | None
    version: Int
