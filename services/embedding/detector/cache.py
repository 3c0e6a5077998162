"""A named cache of nominal experiences D_e = {e_i} (paper §IV-A) and its threshold tau.

Every mutation is planned first (validated, turned into an ``Op``), made durable by
the store, then applied by ``Cache.apply``, the single mutation path. Planning never
changes state, so a rejected request leaves the cache exactly as it was. A cache is
its ``Header`` (config, version, calibration...) plus its experiences and their index.

Experiences may carry detections (``shared.messages.Detection``). Beside the experience
index a cache keeps the vector of every distinct detection phrase it has seen and how
many experiences hold it; those held by at least one are its *nominal detections*,
against which an observation's detections are scored (:mod:`.detections`). A cache
calibrated by ``loo-quantile`` or ``conformal`` keeps the nominal calibration scores of
both components (three, when the calibration asked for pairs: it also counts how many
experiences hold each pair of phrases), and judges an observation with detections by
their combined p-value.
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from shared.messages import Detection, DetectionMatch, Neighbor, PairMatch

from ..models.base import normalize
from . import detections as det
from .calibration import Calibration
from .errors import Conflict, InvalidInput, NotFound
from .index import IndexKind, VectorIndex
from .proposals import Policy
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
    proposals: Policy = "review"  # what a proposal from the slow reasoner becomes


MAX_MATCHES = 3  # detections a verdict names


@dataclass(frozen=True)
class CachedExperience:
    id: str
    text: str | None
    metadata: Mapping[str, Any] = field(default_factory=dict)
    detections: tuple[Detection, ...] = ()

    @property
    def phrases(self) -> tuple[str, ...]:
        """Its distinct detection phrases, in order."""
        return tuple(dict.fromkeys(d.phrase for d in self.detections))


@dataclass(frozen=True)
class Labelled:
    """A labelled text of a calibration or test set, with its detection phrases if any."""

    text: str
    is_anomaly: bool
    detections: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class Detections:
    """A query's detection phrases (distinct) and their unit vectors, one row each."""

    phrases: tuple[str, ...]
    vectors: np.ndarray


@dataclass(frozen=True, eq=False)
class CalibrationScores:
    """The nominal calibration scores behind a calibration's p-values, sorted: the
    observation scores, the detection scores (empty: the cache had no detections), and
    the pair scores (None: the calibration did not ask for pairs)."""

    observation: np.ndarray
    detection: np.ndarray
    pair: np.ndarray | None = None

    @classmethod
    def of(cls, observation: np.ndarray, detection: np.ndarray,
           pair: np.ndarray | None = None) -> CalibrationScores:
        """From raw scores; NaN (an observation without detections, or a pair) left out."""
        def clean(x: np.ndarray) -> np.ndarray:
            x = np.asarray(x, dtype=np.float64)
            return np.sort(x[~np.isnan(x)])
        return cls(clean(observation), clean(detection), None if pair is None else clean(pair))

    @property
    def tests(self) -> int:
        """How many p-values a verdict with detections combines (Bonferroni's factor)."""
        return 2 if self.pair is None else 3

    def least(self) -> int:
        """The fewest scores behind one of the components a verdict combines."""
        return min(len(self.observation), len(self.detection),
                   len(self.detection) if self.pair is None else len(self.pair))

    def check_power(self, alpha: float, tests: int | None = None) -> None:
        """InvalidInput unless the combined p-value can go below ``1 - alpha``: its least
        is ``tests/(n+1)`` (Bonferroni over ``tests`` components, default
        :attr:`tests`; n the fewest scores of one). Nothing to check without
        detection scores (text-only verdicts keep ``score > tau``)."""
        if self.pair is not None and len(self.pair) == 0:
            raise InvalidInput("no nominal calibration example has two or more detections: "
                               "there is no pair score to calibrate", field="pairs")
        n, tests = self.least(), tests or self.tests
        if n and tests / (n + 1) >= 1 - alpha:
            raise InvalidInput(
                f"{n} nominal calibration scores with detections cannot flag anything at "
                f"alpha {alpha}: the smallest combined p-value is {tests}/(n+1) and needs "
                f"to be below 1 - alpha (at least {math.ceil(tests / (1 - alpha))} nominal "
                "examples with detections, or a lower alpha)", field="alpha")


@dataclass(frozen=True)
class Scored:
    """s(e_t; D_e) for one query, with its nearest nominal experiences; for a query with
    detections, its worst detection's score, its least nominal detections and, when the
    cache's calibration has detection scores, the combined p-value; with pair scores too,
    its worst pair's score and the pair, when it is not a nominal pair as it is.
    ``is_anomaly``: None while the cache has no tau."""

    score: float
    neighbors: tuple[Neighbor, ...]
    is_anomaly: bool | None = None
    detection_score: float | None = None
    p_value: float | None = None
    matches: tuple[DetectionMatch, ...] = ()
    pair_score: float | None = None
    pair: PairMatch | None = None


@dataclass(frozen=True, eq=False)
class Add:
    """New experiences under fresh ``labels``, with their (n, dim) unit float32 vectors,
    and the vectors of the detection phrases the cache has not seen before."""

    labels: tuple[int, ...]
    experiences: tuple[CachedExperience, ...]
    vectors: np.ndarray
    version: int
    detection_vectors: Mapping[str, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class Delete:
    id: str
    label: int
    version: int


@dataclass(frozen=True, eq=False)
class SetCalibration:
    calibration: Calibration
    version: int
    scores: CalibrationScores | None = None  # loo-quantile and conformal keep theirs


@dataclass(frozen=True)
class Configure:
    k: int
    score: ScoreKind
    version: int
    proposals: Policy = "review"


Op = Add | Delete | SetCalibration | Configure


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
        if isinstance(op, SetCalibration):
            return replace(self, version=op.version, calibration=op.calibration, stale=False)
        config = replace(self.config, k=op.k, score=op.score, proposals=op.proposals)
        scoring = (op.k, op.score) != (self.config.k, self.config.score)
        return replace(self, version=op.version, config=config,
                       stale=self.stale or (calibrated and scoring))


def unit_vectors(rows: np.ndarray) -> np.ndarray:
    """Finite rows scaled to unit length as float32 (``models.base.normalize``: in float64,
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
        self.experiences: dict[int, CachedExperience] = {}
        self.labels_by_id: dict[str, int] = {}
        self.detection_vectors: dict[str, np.ndarray] = {}  # every phrase seen: unit float32
        self.detection_counts: dict[str, int] = {}  # phrase: experiences holding it (> 0)
        # (phrase, phrase), in order: experiences holding both (> 0)
        self.pair_counts: dict[tuple[str, str], int] = {}
        self.calibration_scores: CalibrationScores | None = None
        self._mahalanobis: tuple[int, MahalanobisModel] | None = None
        self._nominal: tuple[int, det.NominalDetections] | None = None
        self._pairs: tuple[int, det.NominalPairs] | None = None

    @classmethod
    def restored(cls, header: Header, experiences: Mapping[int, CachedExperience],
                 index: VectorIndex, detection_vectors: Mapping[str, np.ndarray] | None = None,
                 calibration_scores: CalibrationScores | None = None) -> Cache:
        """A cache as stored: ``index`` holds exactly the labels of ``experiences``,
        ``detection_vectors`` every phrase they hold (and maybe more)."""
        cache = cls(header.config, index)
        cache.header = header
        cache.experiences = dict(experiences)
        cache.labels_by_id = {e.id: label for label, e in experiences.items()}
        cache.detection_vectors = dict(detection_vectors or {})
        for exp in experiences.values():
            cache._count(exp, +1)
        cache.calibration_scores = calibration_scores
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

    @property
    def has_detections(self) -> bool:
        return bool(self.detection_counts)

    def score(self, vectors: np.ndarray, k: int | None = None, neighbors: int = 3,
              detections: Sequence[Detections | None] = (), *, pairs: bool = False
              ) -> list[Scored]:
        """Score unit query vectors (nq, dim): top-k mean cosine similarity negated, or
        the Mahalanobis distance, per the cache's score function; and judge each (see
        :meth:`judge`), with its ``detections`` if given (one per query, or none).
        ``pairs``: give each one's pair score even if the calibration has none (to
        calibrate with pairs)."""
        k = self.check_k(k or self.config.k)
        sims, labels = self.index.search(vectors, max(k, neighbors))
        if self.config.score == "mahalanobis":
            scores = self._mahalanobis_model().score(vectors)
        else:
            scores = topk_score(sims, k)
        per_query = list(detections) or [None] * len(scores)
        return [
            self.judge(float(s), self._neighbors(row_sims[:neighbors], row_labels[:neighbors]),
                       found, pairs=pairs)
            for s, row_sims, row_labels, found in zip(scores, sims, labels, per_query,
                                                      strict=True)
        ]

    def judge(self, score: float, neighbors: tuple[Neighbor, ...],
              found: Detections | None, *, pairs: bool = False) -> Scored:
        """h(o_t). Without detections (or a cache without any): ``score > tau``, as
        always. With them, and a calibration that kept detection scores: the Bonferroni
        combination of the conformal p-values (two, or three with pairs), anomaly iff
        ``p < 1 - alpha``; otherwise ``score > tau`` still, the detections only named."""
        threshold = self.threshold
        plain = Scored(score, neighbors, None if threshold is None else score > threshold)
        if found is None or not found.phrases or not self.detection_counts:
            return plain
        nominal = self.nominal_detections()
        all_sims = det.similarities(nominal, found.vectors)
        index = np.argmax(all_sims, axis=1)
        sims = all_sims[np.arange(len(index)), index]
        worst = float(-sims.min())
        cal, scores = self.calibration, self.calibration_scores
        calibrated = (cal is not None and cal.alpha is not None and scores is not None
                      and scores.least() > 0)
        p_each: list[float | None] = [None] * len(sims)
        p_value = p_pair = None
        is_anomaly = plain.is_anomaly
        with_pairs = pairs or (scores is not None and scores.pair is not None)
        pair = det.worst_pair(self.nominal_pairs(), all_sims) if with_pairs else None
        if calibrated:
            assert cal is not None and cal.alpha is not None and scores is not None
            p_each = det.p_values_sorted(scores.detection, -sims).tolist()
            p_obs = det.p_values_sorted(scores.observation, np.array([score]),
                                         None if self.config.score == "mahalanobis" else 1.0)
            p_det = det.p_values_sorted(scores.detection, np.array([worst]))
            p_pairs = None
            if scores.pair is not None:
                p_pairs = det.p_values_sorted(scores.pair, np.array(
                    [np.nan if pair is None else pair.score]))
                p_pair = None if pair is None else float(p_pairs[0])
            p_value = float(det.combined_p(p_obs, p_det, p_pairs)[0])
            is_anomaly = p_value < 1.0 - cal.alpha
        order = [int(i) for i in np.argsort(sims, kind="stable") if sims[i] < 1.0]
        matches = tuple(
            DetectionMatch(detection=found.phrases[i], nearest=nominal.labels[int(index[i])],
                           similarity=float(sims[i]), p_value=p_each[i])
            for i in order[:MAX_MATCHES])
        named = None
        if pair is not None and pair.nearest >= 0 and pair.similarity < 1.0:
            nominal_pairs = self.nominal_pairs()
            a, b = pair.detections
            c = nominal.labels[int(nominal_pairs.first[pair.nearest])]
            d = nominal.labels[int(nominal_pairs.second[pair.nearest])]
            named = PairMatch(detections=(found.phrases[a], found.phrases[b]), nearest=(c, d),
                              similarity=pair.similarity, p_value=p_pair)
        return Scored(score, neighbors, is_anomaly, worst, p_value, matches,
                      None if pair is None else pair.score, named)

    def nominal_detections(self) -> det.NominalDetections:
        """The distinct detections of the experiences (in phrase order), built once per
        version."""
        if self._nominal is None or self._nominal[0] != self.version:
            phrases = tuple(sorted(self.detection_counts))
            vectors = (np.stack([self.detection_vectors[p] for p in phrases]) if phrases
                       else np.zeros((0, self.config.dim), dtype=np.float32))
            counts = np.array([self.detection_counts[p] for p in phrases], dtype=np.int64)
            self._nominal = (self.version, det.NominalDetections(phrases, vectors, counts))
        return self._nominal[1]

    def nominal_pairs(self) -> det.NominalPairs:
        """The distinct pairs of detections the experiences hold together, as indices into
        :meth:`nominal_detections`, built once per version."""
        if self._pairs is None or self._pairs[0] != self.version:
            where = {p: i for i, p in enumerate(self.nominal_detections().labels)}
            keys = list(self.pair_counts)
            self._pairs = (self.version, det.NominalPairs(
                np.array([where[a] for a, _ in keys], dtype=np.int64),
                np.array([where[b] for _, b in keys], dtype=np.int64),
                np.array([self.pair_counts[k] for k in keys], dtype=np.int64)))
        return self._pairs[1]

    def loo_pair_scores(self) -> np.ndarray:
        """Each experience's pair score with the pairs only it holds left out (NaN for one
        with fewer than two detections): the pair component's scores behind eq. (2)."""
        nominal = self.nominal_detections()
        where = {p: i for i, p in enumerate(nominal.labels)}
        held = [[where[p] for p in exp.phrases] for exp in self.experiences.values()]
        return det.loo_pair_scores(nominal, self.nominal_pairs(), held)

    def loo_detection_scores(self) -> np.ndarray:
        """Each experience's detection score with what only it holds left out (NaN for
        one without detections): the detection component's scores behind eq. (2)."""
        nominal = self.nominal_detections()
        where = {p: i for i, p in enumerate(nominal.labels)}
        held = [[where[p] for p in exp.phrases] for exp in self.experiences.values()]
        return det.loo_scores(nominal, held, nominal.vectors)

    def loo_members(self, labels: Sequence[int], *, pairs: bool = False
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The leave-one-out scores of the experiences ``labels`` alone (each scored
        against the cache without itself, as :meth:`loo_scores`,
        :meth:`loo_detection_scores` and :meth:`loo_pair_scores` score every member):
        whole observation, worst detection (NaN without one), worst pair (None unless
        ``pairs``; NaN with fewer than two detections)."""
        wanted = np.array(labels, dtype=np.int64)
        where = {int(label): i for i, label in enumerate(self.index.labels())}
        rows = [where[int(label)] for label in wanted]
        if self.config.score == "mahalanobis":
            observation = self.loo_scores()[rows]
        else:
            k = self.check_k(self.config.k, leave_one_out=True)
            sims, found = self.index.search(self.index.vectors()[rows], k + 1)
            observation = loo_topk_scores(sims, found, wanted, k)
        if not self.has_detections:
            return observation, np.full(len(rows), np.nan), None
        nominal = self.nominal_detections()
        index = {p: i for i, p in enumerate(nominal.labels)}
        held = [[index[p] for p in self.experiences[int(label)].phrases] for label in wanted]
        detection = det.loo_scores(nominal, held, nominal.vectors)
        pair = det.loo_pair_scores(nominal, self.nominal_pairs(), held) if pairs else None
        return observation, detection, pair

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
        detections: Sequence[Sequence[Detection]] = (),
        detection_vectors: Mapping[str, np.ndarray] | None = None,
        field_prefix: str = "items",
    ) -> Add:
        """``detections``: each experience's (or none), ``detection_vectors`` the vector
        of every phrase among them that the cache has not seen (any unit-length rows)."""
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
        held = [tuple(d) for d in detections] or [()] * n
        experiences = tuple(CachedExperience(ident, text, dict(meta), found) for ident, text, meta,
                            found in zip(resolved, texts, metadata, held, strict=True))
        new: dict[str, np.ndarray] = {}
        for exp in experiences:
            for phrase in exp.phrases:
                if phrase not in self.detection_vectors and phrase not in new:
                    if detection_vectors is None or phrase not in detection_vectors:
                        raise Conflict(f"no vector for detection {phrase!r}", field="detections")
                    new[phrase] = np.asarray(detection_vectors[phrase], dtype=np.float32)
        return Add(labels=tuple(range(first, first + n)), experiences=experiences,
                   vectors=unit, version=self.version + 1, detection_vectors=new)

    def plan_delete(self, ident: str) -> Delete:
        if ident not in self.labels_by_id:
            raise NotFound(f"no experience {ident!r} in cache {self.name!r}", field="id")
        return Delete(ident, self.labels_by_id[ident], self.version + 1)

    def plan_calibration(self, calibration: Calibration,
                         scores: CalibrationScores | None = None) -> SetCalibration:
        if not math.isfinite(calibration.threshold):
            raise InvalidInput("calibration gave a non-finite threshold", field="calibration")
        return SetCalibration(calibration, self.version + 1, scores)

    def plan_configure(self, *, k: int, score: ScoreKind, proposals: Policy | None = None
                       ) -> Configure | None:
        proposals = proposals or self.config.proposals
        if (k, score, proposals) == (self.config.k, self.config.score, self.config.proposals):
            return None
        return Configure(k, score, self.version + 1, proposals)

    # -- the one mutation path -------------------------------------------------

    def apply(self, op: Op) -> None:
        header = self.header.after(op)
        if isinstance(op, Add):
            self.index.add(op.vectors, np.array(op.labels, dtype=np.int64))
            self.detection_vectors.update(op.detection_vectors)
            for label, exp in zip(op.labels, op.experiences, strict=True):
                self.experiences[label] = exp
                self.labels_by_id[exp.id] = label
                self._count(exp, +1)
        elif isinstance(op, Delete):
            del self.labels_by_id[op.id]
            self._count(self.experiences.pop(op.label), -1)
            self.index.remove(np.array([op.label], dtype=np.int64))
        elif isinstance(op, SetCalibration):
            self.calibration_scores = op.scores
        self.header = header

    def _count(self, exp: CachedExperience, step: int) -> None:
        phrases = sorted(exp.phrases)
        for phrase in phrases:
            _step(self.detection_counts, phrase, step)
        for i, first in enumerate(phrases):
            for second in phrases[i + 1:]:
                _step(self.pair_counts, (first, second), step)


def _step(counts: dict[Any, int], key: Any, step: int) -> None:
    left = counts.get(key, 0) + step
    if left > 0:
        counts[key] = left
    else:
        counts.pop(key, None)
