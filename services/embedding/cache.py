"""A named cache of nominal experiences D_e = {e_i} (paper §IV-A) and its threshold tau.

Every mutation is planned first (validated, turned into a WAL ``Record``) and
then applied by ``Cache.apply``, the single mutation path used both live and
when replaying the log on start. Planning never changes state, so a rejected
request leaves the cache exactly as it was.
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np

from shared.messages import Neighbor

from .calibration import Calibration
from .errors import Conflict, InvalidInput, NotFound
from .index import IndexKind, VectorIndex
from .scoring import MahalanobisModel, loo_topk_scores, topk_score
from .storage import Record, Snapshot

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
    """A labelled text of a calibration or test set."""

    text: str
    is_anomaly: bool


@dataclass(frozen=True)
class Scored:
    """s(e_t; D_e) for one query, with its nearest nominal experiences."""

    score: float
    neighbors: tuple[Neighbor, ...]


class Cache:
    def __init__(self, config: CacheConfig) -> None:
        self.config = config
        self.index = VectorIndex(config.dim, config.index)
        self.experiences: dict[int, Experience] = {}
        self.labels_by_id: dict[str, int] = {}
        self.next_label = 0
        self.version = 0
        self.calibration: Calibration | None = None
        self.stale = False
        self._mahalanobis: tuple[int, MahalanobisModel] | None = None

    # -- queries ---------------------------------------------------------------

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
            raise InvalidInput(
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
                raise InvalidInput("Mahalanobis scoring needs at least 3 experiences", field="k")
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
                raise InvalidInput("Mahalanobis scoring needs at least 3 experiences", field="k")
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
    ) -> Record:
        n = len(vectors)
        if vectors.ndim != 2 or vectors.shape[1] != self.config.dim:
            got = vectors.shape[1] if vectors.ndim == 2 else vectors.shape
            raise InvalidInput(
                f"vectors must have dimension {self.config.dim} (cache {self.name!r}), got {got}",
                field="vectors",
            )
        if not np.isfinite(vectors).all():
            row = int(np.argwhere(~np.isfinite(vectors))[0][0])
            raise InvalidInput("vectors must be finite (no NaN or inf)", field=f"vectors[{row}]")
        norms = np.linalg.norm(vectors, axis=1)
        if (norms < 1e-12).any():
            row = int(np.argmax(norms < 1e-12))
            raise InvalidInput("a zero vector has no direction", field=f"vectors[{row}]")
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
        labels = list(range(self.next_label, self.next_label + n))
        items = [
            {"id": ident, "label": label, "text": text, "metadata": dict(meta)}
            for ident, label, text, meta in zip(resolved, labels, texts, metadata, strict=True)
        ]
        unit = (vectors / norms[:, None]).astype(np.float32)
        return Record({"op": "add", "items": items, "version": self.version + 1}, {"vectors": unit})

    def plan_delete(self, ident: str) -> Record:
        if ident not in self.labels_by_id:
            raise NotFound(f"no experience {ident!r} in cache {self.name!r}", field="id")
        return Record({"op": "delete", "id": ident, "version": self.version + 1})

    def plan_calibration(self, calibration: Calibration) -> Record:
        if not math.isfinite(calibration.threshold):
            raise InvalidInput("calibration gave a non-finite threshold", field="calibration")
        return Record({"op": "calibrate", "calibration": calibration.to_dict(),
                       "version": self.version + 1})

    def plan_configure(self, *, k: int, score: ScoreKind) -> Record | None:
        if (k, score) == (self.config.k, self.config.score):
            return None
        return Record({"op": "configure", "k": k, "score": score, "version": self.version + 1})

    # -- the one mutation path -------------------------------------------------

    def apply(self, record: Record) -> None:
        op = record.op
        kind = op["op"]
        if kind == "add":
            items = op["items"]
            labels = np.array([it["label"] for it in items], dtype=np.int64)
            self.index.add(record.arrays["vectors"], labels)
            for it in items:
                self.experiences[it["label"]] = Experience(it["id"], it["text"], it["metadata"])
                self.labels_by_id[it["id"]] = it["label"]
            if items:
                self.next_label = max(self.next_label, int(labels.max()) + 1)
            self.stale = self.calibration is not None
        elif kind == "delete":
            label = self.labels_by_id.pop(op["id"])
            del self.experiences[label]
            self.index.remove(np.array([label], dtype=np.int64))
            self.stale = self.calibration is not None
        elif kind == "calibrate":
            self.calibration = Calibration(**op["calibration"])
            self.stale = False
        elif kind == "configure":
            self.config = CacheConfig(**{**asdict(self.config), "k": op["k"], "score": op["score"]})
            self.stale = self.calibration is not None
        else:
            raise ValueError(f"unknown operation {kind!r}")
        self.version = int(op["version"])

    # -- snapshots ---------------------------------------------------------------

    def to_snapshot(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        labels = self.index.labels()
        records = [
            {"id": e.id, "text": e.text, "metadata": dict(e.metadata)}
            for e in (self.experiences[int(label)] for label in labels)
        ]
        meta = {
            "config": asdict(self.config),
            "experiences": records,
            "next_label": self.next_label,
            "version": self.version,
            "calibration": None if self.calibration is None else self.calibration.to_dict(),
            "stale": self.stale,
        }
        return meta, {"labels": labels.copy(), "vectors": np.array(self.index.vectors())}

    @classmethod
    def from_snapshot(cls, snapshot: Snapshot) -> Cache:
        meta = snapshot.meta
        cache = cls(CacheConfig(**meta["config"]))
        labels = snapshot.arrays["labels"]
        if len(labels):
            cache.index.add(snapshot.arrays["vectors"], labels)
        for label, rec in zip(labels.tolist(), meta["experiences"], strict=True):
            cache.experiences[label] = Experience(rec["id"], rec["text"], rec["metadata"])
            cache.labels_by_id[rec["id"]] = label
        cache.next_label = int(meta["next_label"])
        cache.version = int(meta["version"])
        cal = meta["calibration"]
        cache.calibration = None if cal is None else Calibration(**cal)
        cache.stale = bool(meta["stale"])
        return cache
