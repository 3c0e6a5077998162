"""A named cache of nominal experiences D_e = {e_i} (paper §IV-A) and its threshold tau.

Every mutation is planned first (validated, turned into an ``Op``), made durable by
the store, then applied by ``Cache.apply``, the single mutation path. Planning never
changes state, so a rejected request leaves the cache exactly as it was. A cache is
its ``Header`` (config, version, calibration...) plus its experiences and their index.
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from shared.messages import Neighbor

from .calibration import Calibration
from .embedders import normalize
from .errors import Conflict, InvalidInput, NotFound
from .index import IndexKind, VectorIndex
from .scoring import MahalanobisModel, loo_topk_scores, topk_score

ScoreKind = Literal["topk", "mahalanobis"]


@dataclass(frozen=True)
class CacheConfig:
    """What a cache pins at creation: embedder ``model`` (None: raw vectors only) and ``dim``."""

    name: str
    model: str | None
    dim: int
    k: int = 5
    score: ScoreKind = "topk"
    index: IndexKind = "flat"
    shrinkage: float = 0.1  # Mahalanobis covariance shrinkage lambda


@dataclass(frozen=True)
class Experience:
    id: str
    text: str | None
    metadata: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Labelled:
    """A labelled text of a calibration or test set, with its detections if any."""

    text: str
    is_anomaly: bool
    detections: tuple[str, ...] = ()


@dataclass(frozen=True)
class Scored:
    """s(e_t; D_e) for one query, with its nearest nominal experiences."""

    score: float
    neighbors: tuple[Neighbor, ...]


@dataclass(frozen=True, eq=False)
class Add:
    """New experiences under fresh ``labels``, with their (n, dim) unit float32 vectors."""

    labels: tuple[int, ...]
    experiences: tuple[Experience, ...]
    vectors: np.ndarray
    version: int


@dataclass(frozen=True)
class Delete:
    id: str
    label: int
    version: int


@dataclass(frozen=True)
class Calibrate:
    calibration: Calibration
    version: int


@dataclass(frozen=True)
class Configure:
    k: int
    score: ScoreKind
    version: int


Op = Add | Delete | Calibrate | Configure


@dataclass(frozen=True)
class Header:
    """A cache apart from its experiences: what the store keeps in the cache's row."""

    config: CacheConfig
    version: int = 0
    next_label: int = 0  # labels are never reused, even after a delete
    calibration: Calibration | None = None
    stale: bool = False  # the experiences or the score changed since the calibration

    def after(self, op: Op) -> Header:
        """The header once ``op`` is applied."""
        calibrated = self.calibration is not None
        if isinstance(op, Add):
            top = max(op.labels, default=self.next_label - 1) + 1
            return replace(self, version=op.version, next_label=max(self.next_label, top),
                           stale=calibrated)
        if isinstance(op, Delete):
            return replace(self, version=op.version, stale=calibrated)
        if isinstance(op, Calibrate):
            return replace(self, version=op.version, calibration=op.calibration, stale=False)
        config = replace(self.config, k=op.k, score=op.score)
        return replace(self, version=op.version, config=config, stale=calibrated)


def unit_vectors(rows: np.ndarray) -> np.ndarray:
    """Finite rows scaled to unit length as float32 (``embedders.normalize``: in float64,
    so neither huge nor tiny numbers overflow or vanish); a zero row is InvalidInput
    naming it."""
    x = np.asarray(rows, dtype=np.float64)
    zero = ~x.any(axis=1)
    if zero.any():
        raise InvalidInput("a zero vector has no direction",
                           field=f"vectors[{int(np.argmax(zero))}]")
    return normalize(x)


class Cache:
    def __init__(self, config: CacheConfig, index: VectorIndex | None = None) -> None:
        self.config = config
        self.version = 0
        self.next_label = 0  # labels are never reused, even after a delete
        self.calibration: Calibration | None = None
        self.stale = False  # the experiences or the score changed since the calibration
        self.index = index if index is not None else VectorIndex(config.dim, config.index)
        self.experiences: dict[int, Experience] = {}
        self.labels_by_id: dict[str, int] = {}
        self._mahalanobis: tuple[int, MahalanobisModel] | None = None

    @classmethod
    def restored(cls, header: Header, experiences: Mapping[int, Experience],
                 index: VectorIndex) -> Cache:
        """A cache as stored: ``index`` holds exactly the labels of ``experiences``."""
        cache = cls(header.config, index)
        cache.header = header
        cache.experiences = dict(experiences)
        cache.labels_by_id = {e.id: label for label, e in experiences.items()}
        return cache

    # -- queries ---------------------------------------------------------------

    @property
    def header(self) -> Header:
        """What the store keeps of this cache apart from its experiences."""
        return Header(self.config, self.version, self.next_label, self.calibration, self.stale)

    @header.setter
    def header(self, header: Header) -> None:
        self.config, self.version, self.next_label = header.config, header.version, \
            header.next_label
        self.calibration, self.stale = header.calibration, header.stale

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def size(self) -> int:
        return len(self.index)

    @property
    def threshold(self) -> float | None:
        return None if self.calibration is None else self.calibration.threshold

    def check_k(self, k: int, *, leave_one_out: bool = False) -> int:
        need = k + 1 if leave_one_out else k
        if k < 1:
            raise InvalidInput("k must be at least 1", field="k")
        if need > self.size:
            what = "leave-one-out scoring needs k+1" if leave_one_out else "k"
            raise Conflict(
                f"{what} = {need} is larger than cache {self.name!r} ({self.size} experiences)",
                field="k",
            )
        return k

    def score(self, vectors: np.ndarray, k: int | None = None, neighbors: int = 3) -> list[Scored]:
        """Score unit query vectors (nq, dim): top-k mean cosine similarity negated, or
        the Mahalanobis distance, per the cache's score function."""
        k = self.check_k(k or self.config.k)
        sims, labels = self.index.search(vectors, max(k, neighbors))
        if self.config.score == "mahalanobis":
            scores = self._mahalanobis_model().score(vectors)
        else:
            scores = topk_score(sims, k)
        return [
            Scored(float(s), self._neighbors(row_sims[:neighbors], row_labels[:neighbors]))
            for s, row_sims, row_labels in zip(scores, sims, labels, strict=True)
        ]

    def loo_scores(self, k: int | None = None) -> np.ndarray:
        """s(e_i; D_e minus {e_i}) for every member: the scores behind eq. (2)."""
        if self.config.score == "mahalanobis":
            if self.size < 3:
                raise Conflict("Mahalanobis scoring needs at least 3 experiences", field="k")
            return self._mahalanobis_model().loo_scores(self.index.vectors())
        k = self.check_k(k or self.config.k, leave_one_out=True)
        sims, labels = self.index.self_search(k + 1)
        return loo_topk_scores(sims, labels, self.index.labels(), k)

    def _neighbors(self, sims: np.ndarray, labels: np.ndarray) -> tuple[Neighbor, ...]:
        out = []
        for sim, label in zip(sims, labels, strict=True):
            exp = self.experiences.get(int(label))
            if exp is not None:
                out.append(Neighbor(id=exp.id, text=exp.text, similarity=float(sim)))
        return tuple(out)

    def _mahalanobis_model(self) -> MahalanobisModel:
        if self._mahalanobis is None or self._mahalanobis[0] != self.version:
            if self.size < 3:
                raise Conflict("Mahalanobis scoring needs at least 3 experiences", field="k")
            model = MahalanobisModel.fit(self.index.vectors(), shrinkage=self.config.shrinkage)
            self._mahalanobis = (self.version, model)
        return self._mahalanobis[1]

    # -- planning (validation; no state change) --------------------------------

    def plan_add(
        self,
        vectors: np.ndarray,
        *,
        ids: Sequence[str | None],
        texts: Sequence[str | None],
        metadata: Sequence[Mapping[str, Any]],
        field_prefix: str = "items",
    ) -> Add:
        n = len(vectors)
        if vectors.ndim != 2 or vectors.shape[1] != self.config.dim:
            got = vectors.shape[1] if vectors.ndim == 2 else vectors.shape
            raise Conflict(
                f"vectors must have dimension {self.config.dim} (cache {self.name!r}), got {got}",
                field="vectors",
            )
        if not np.isfinite(vectors).all():
            row = int(np.argwhere(~np.isfinite(vectors))[0][0])
            raise InvalidInput("vectors must be finite (no NaN or inf)", field=f"vectors[{row}]")
        unit = unit_vectors(vectors)
        seen: set[str] = set()
        resolved: list[str] = []
        for i, given in enumerate(ids):
            ident = given if given is not None else uuid.uuid4().hex
            if ident in seen:
                raise InvalidInput(f"duplicate id {ident!r} in request",
                                   field=f"{field_prefix}[{i}].id")
            if ident in self.labels_by_id:
                raise Conflict(f"id {ident!r} already exists in cache {self.name!r}",
                               field=f"{field_prefix}[{i}].id")
            seen.add(ident)
            resolved.append(ident)
        first = self.next_label
        return Add(
            labels=tuple(range(first, first + n)),
            experiences=tuple(Experience(ident, text, dict(meta)) for ident, text, meta
                              in zip(resolved, texts, metadata, strict=True)),
            vectors=unit, version=self.version + 1)

    def plan_delete(self, ident: str) -> Delete:
        if ident not in self.labels_by_id:
            raise NotFound(f"no experience {ident!r} in cache {self.name!r}", field="id")
        return Delete(ident, self.labels_by_id[ident], self.version + 1)

    def plan_calibration(self, calibration: Calibration) -> Calibrate:
        if not math.isfinite(calibration.threshold):
            raise InvalidInput("calibration gave a non-finite threshold", field="calibration")
        return Calibrate(calibration, self.version + 1)

    def plan_configure(self, *, k: int, score: ScoreKind) -> Configure | None:
        if (k, score) == (self.config.k, self.config.score):
            return None
        return Configure(k, score, self.version + 1)

    # -- the one mutation path -------------------------------------------------

    def apply(self, op: Op) -> None:
        header = self.header.after(op)
        if isinstance(op, Add):
            self.index.add(op.vectors, np.array(op.labels, dtype=np.int64))
            for label, exp in zip(op.labels, op.experiences, strict=True):
                self.experiences[label] = exp
                self.labels_by_id[exp.id] = label
        elif isinstance(op, Delete):
            del self.labels_by_id[op.id]
            del self.experiences[op.label]
            self.index.remove(np.array([op.label], dtype=np.int64))
        self.header = header
