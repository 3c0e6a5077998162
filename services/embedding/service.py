"""The vector-cache service: named caches on disk, embedders, jobs, micro-batched scoring.

Concurrency: per cache, writers are serialised by an asyncio lock and the
database commit happens before the in-memory apply; readers (scoring,
leave-one-out) run in worker threads under the shared side of a
readers-writer lock, so they see a cache either before or after a write.
Embedding happens outside every lock.

Model inference and query searches all run on ONE dedicated compute thread.
torch and FAISS share libgomp, which keeps a team of OpenMP threads per calling
thread for as long as that thread lives; with more than one such thread alive,
embedding one observation took twice as long here. So the rare heavy admin work
that also uses OpenMP (leave-one-out, loading a model) runs on a short-lived
thread of its own, which takes its team with it when it ends, and never on
asyncio's long-lived executor threads.
"""

from __future__ import annotations

import asyncio
import logging
import re
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import numpy as np

from shared.jobs import Job, Jobs
from shared.messages import Detection, Observation

from .batching import NORMAL, URGENT, ComputeThread, MicroBatcher
from .cache import (
    Add,
    Cache,
    CacheConfig,
    CalibrationScores,
    Delete,
    Detections,
    Labelled,
    Op,
    Scored,
    ScoreKind,
    unit_vectors,
)
from .calibration import (
    Calibration,
    CalibrationError,
    Method,
    auroc,
    conformal,
    loo_quantile,
    roc_curve,
    tpr_target,
)
from .detections import floats
from .embedders import Embedder, ModelNotFound
from .errors import Busy, Conflict, InvalidInput, NotFound
from .index import IndexKind
from .legacy import legacy_caches, read_legacy
from .loading import EmbedderPool
from .proposals import Policy, Proposal, State, scene_id
from .schemas import Added, CacheInfo, Calibrated, Deleted, Experience, Roc
from .settings import EmbeddingSettings
from .store import StorageError, Store

log = logging.getLogger(__name__)

CACHE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}")
T = TypeVar("T")


class RWLock:
    """Many readers or one writer; a waiting writer blocks new readers."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._readers = 0
        self._writer = False
        self._waiting = 0

    @contextmanager
    def read(self) -> Iterator[None]:
        with self._cond:
            self._cond.wait_for(lambda: not self._writer and not self._waiting)
            self._readers += 1
        try:
            yield
        finally:
            with self._cond:
                self._readers -= 1
                self._cond.notify_all()

    @contextmanager
    def write(self) -> Iterator[None]:
        with self._cond:
            self._waiting += 1
            self._cond.wait_for(lambda: not self._writer and not self._readers)
            self._waiting -= 1
            self._writer = True
        try:
            yield
        finally:
            with self._cond:
                self._writer = False
                self._cond.notify_all()


@dataclass
class Entry:
    cache: Cache
    saved: tuple[int, bool] | None = None  # the index file's (version, has HNSW graph)
    changed: int = 0  # experiences added or deleted since the index file was saved
    writer: asyncio.Lock = field(default_factory=asyncio.Lock)
    rw: RWLock = field(default_factory=RWLock)
    batchers: dict[tuple[int, bool], MicroBatcher[Query, Scored]] = field(default_factory=dict)
    proposals: dict[str, Proposal] = field(default_factory=dict)  # by id, oldest first

    def index_outdated(self) -> bool:
        """The saved index file is missing, older than the cache, or lacks a built graph."""
        return (self.saved is None or self.saved[0] != self.cache.version
                or (self.cache.index.graph_ready and not self.saved[1]))


@dataclass(frozen=True)
class Item:
    """An experience to add: text (embedded by the cache's model) or a raw vector."""

    text: str | None = None
    vector: Sequence[float] | None = None
    id: str | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)
    detections: tuple[Detection, ...] = ()


@dataclass(frozen=True)
class Query:
    """A text to score, with its detection phrases (distinct, in order)."""

    text: str
    phrases: tuple[str, ...] = ()

    @classmethod
    def of(cls, text: str, detections: Sequence[Detection] = ()) -> Query:
        return cls(text, tuple(dict.fromkeys(d.phrase for d in detections)))


class PhraseMemo:
    """The vectors of detection phrases no cache holds, the most recent ``size`` of them
    by (model, phrase): a camera reports an odd object ten times a second, and embedding
    it beside every observation's text made the bus's verdicts ~6 ms slower (p50)."""

    def __init__(self, size: int = 4096) -> None:
        self.size = size
        self._kept: OrderedDict[tuple[str, str], np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    def recall(self, model: str, phrases: Sequence[str]) -> dict[str, np.ndarray]:
        with self._lock:
            found = {p: self._kept[model, p] for p in phrases if (model, p) in self._kept}
            for p in found:
                self._kept.move_to_end((model, p))
        return found

    def keep(self, model: str, vectors: Mapping[str, np.ndarray]) -> None:
        with self._lock:
            for phrase, vector in vectors.items():
                self._kept[model, phrase] = vector
                self._kept.move_to_end((model, phrase))
            while len(self._kept) > self.size:
                self._kept.popitem(last=False)


class Components(NamedTuple):
    """Nominal scores of each component, one per calibration example or member, NaN
    where it has none (raw: ``CalibrationScores.of`` sorts them and drops the NaN)."""

    observation: np.ndarray
    detection: np.ndarray
    pair: np.ndarray | None  # None: pairs not asked for


@dataclass(frozen=True)
class ScoreBatch:
    results: list[Scored]
    threshold: float | None
    stale: bool
    version: int
    k: int
    model: str | None


async def on_fresh_thread(fn: Callable[..., T], *args: Any) -> T:
    """Run ``fn`` on a new thread that ends with it (see the module docstring)."""
    loop = asyncio.get_running_loop()
    future: asyncio.Future[T] = loop.create_future()

    def settle(result: Any, error: BaseException | None) -> None:
        if future.done():
            return
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(result)

    def run() -> None:
        try:
            result = fn(*args)
        except BaseException as exc:  # handed to the awaiting coroutine
            loop.call_soon_threadsafe(settle, None, exc)
        else:
            loop.call_soon_threadsafe(settle, result, None)

    threading.Thread(target=run, name="aesop-oneoff", daemon=True).start()
    return await future


def check_dims(config: CacheConfig, rows: Sequence[Sequence[float]],
               where: Sequence[int] | None = None) -> None:
    """Every row has the cache's pinned dimension (else Conflict naming the row)."""
    for n, row in enumerate(rows):
        if len(row) != config.dim:
            i = n if where is None else where[n]
            raise Conflict(f"vector has dimension {len(row)}; cache {config.name!r} is pinned "
                           f"to dimension {config.dim}", field=f"vectors[{i}]")


def roc_points(scores: np.ndarray, labels: np.ndarray, most: int = 201) -> dict[str, list[Any]]:
    """The ROC curve as JSON: fpr, tpr and the thresholds (None for the +-inf ends)."""
    fpr, tpr, thresholds = roc_curve(scores, labels)
    keep = np.unique(np.linspace(0, len(fpr) - 1, min(most, len(fpr))).round().astype(int))
    return {"fpr": fpr[keep].tolist(), "tpr": tpr[keep].tolist(),
            "thresholds": [float(t) if np.isfinite(t) else None for t in thresholds[keep]]}


class CacheService:
    def __init__(
        self,
        settings: EmbeddingSettings,
        embedders: EmbedderPool | None = None,
        on_batch: Callable[[int], None] | None = None,
    ) -> None:
        self.settings = settings
        self.embedders = embedders or EmbedderPool(
            openai_base_url=settings.openai_base_url,
            openai_api_key=(settings.openai_api_key.get_secret_value()
                            if settings.openai_api_key else None),
            model_dir=settings.model_dir or settings.data_dir / "models",
            max_loaded=settings.max_models, export_dir=Path(settings.data_dir) / "onnx",
            threads=settings.onnx_threads)
        self.jobs = Jobs(max_running=settings.max_jobs, setting="AESOP_EMBEDDING_MAX_JOBS")
        self._entries: dict[str, Entry] = {}
        self._create_lock = asyncio.Lock()
        self._on_batch = on_batch
        self._thread = ComputeThread()
        self._compute = self._thread.lane(NORMAL)
        self._urgent = self._thread.lane(URGENT)
        self._rest_pending = 0  # REST texts being scored or waiting (max_pending_texts)
        self._phrases = PhraseMemo()
        self._store: Store | None = None
        # called with each proposal made, counted, accepted or rejected (the worker
        # publishes them as events)
        self.proposal_listeners: list[Callable[[str, Proposal], None]] = []

    @property
    def store(self) -> Store:
        if self._store is None:
            raise RuntimeError("the cache service is not started")
        return self._store

    # -- lifecycle --------------------------------------------------------------

    async def start(self) -> None:
        """Open the database, import a legacy data directory once, load every cache
        (raises StorageCorrupt naming a file)."""
        self._store = await asyncio.to_thread(
            partial(Store, Path(self.settings.data_dir), fsync=self.settings.fsync,
                    max_bytes=self.settings.max_db_bytes))
        await asyncio.to_thread(self._import_legacy)
        for name in self.store.names():
            cache = await asyncio.to_thread(self.store.load, name)
            self._entries[name] = Entry(cache, saved=self.store.saved_index(name), proposals={
                p.id: p for p in await asyncio.to_thread(self.store.proposals, name)})
            log.info("cache %s: %d experiences, version %d", name, cache.size, cache.version)

    def _import_legacy(self) -> None:
        for directory in legacy_caches(Path(self.settings.data_dir)):
            source = str(directory.relative_to(self.settings.data_dir))
            if self.store.imported(source):
                continue
            cache = read_legacy(directory)
            if cache.name in self.store.names():
                log.warning("not importing %s: a cache named %r exists", directory, cache.name)
                continue
            self.store.import_cache(source, cache)
            log.info("imported cache %s (%d experiences, version %d) from %s; the old files "
                     "stay where they are", cache.name, cache.size, cache.version, directory)

    async def close(self) -> None:
        for entry in self._entries.values():
            for batcher in entry.batchers.values():
                await batcher.close()
            async with entry.writer:
                if entry.index_outdated():
                    await asyncio.to_thread(self._save_index, entry)
        self._entries.clear()
        if self._store is not None:
            self._store.close()
        self._thread.shutdown(wait=True)
        self.embedders.close()

    def _save_index(self, entry: Entry) -> None:
        """Save the index file (under the cache's writer lock); a failure is logged: the
        database holds everything, the next start catches up from an older file."""
        with entry.rw.read():
            try:
                path = self.store.save_index(entry.cache)
            except StorageError as exc:
                log.warning("%s", exc)
                return
            entry.saved = (entry.cache.version, entry.cache.index.graph_ready)
        entry.changed = 0
        log.info("cache %s: index saved to %s", entry.cache.name, path)

    # -- queries --------------------------------------------------------------

    def names(self) -> list[str]:
        return sorted(self._entries)

    def entry(self, name: str) -> Entry:
        try:
            return self._entries[name]
        except KeyError:
            raise NotFound(f"no cache named {name!r}", field="name") from None

    def describe(self, name: str) -> CacheInfo:
        entry = self.entry(name)
        with entry.rw.read():
            return CacheInfo.of(entry.cache)

    def experience(self, name: str, ident: str) -> Experience:
        entry = self.entry(name)
        with entry.rw.read():
            label = entry.cache.labels_by_id.get(ident)
            if label is None:
                raise NotFound(f"no experience {ident!r} in cache {name!r}", field="id")
            exp = entry.cache.experiences[label]
            return Experience(id=exp.id, text=exp.text, metadata=dict(exp.metadata),
                              detections=list(exp.detections))

    # -- mutations --------------------------------------------------------------

    async def create(
        self,
        name: str,
        *,
        model: str | None,
        dim: int | None = None,
        k: int | None = None,
        score: ScoreKind = "topk",
        index: IndexKind = "flat",
        proposals: Policy | None = None,
    ) -> tuple[CacheInfo, bool]:
        """Create cache ``name`` or reconcile an existing one; returns (description, created)."""
        if not CACHE_NAME.fullmatch(name):
            raise InvalidInput("cache names are 1-64 letters, digits, '_', '.', '-'", field="name")
        k = k or self.settings.default_k
        async with self._create_lock:
            if name in self._entries:
                return await self._reconcile(name, model=model, k=k, score=score,
                                             proposals=proposals), False
            if model is not None:
                embedder = await self._embedder(model)
                model, dim = embedder.name, embedder.dim
            elif dim is None:
                raise InvalidInput("a cache without a model needs 'dim'", field="dim")
            config = CacheConfig(name, model, int(dim), k, score, index,
                                 proposals=proposals or "review")
            entry = await asyncio.to_thread(self._create_entry, config)
            self._entries[name] = entry
            return CacheInfo.of(entry.cache), True

    def _create_entry(self, config: CacheConfig) -> Entry:
        self.store.create(config)
        return Entry(Cache(config))

    async def _reconcile(self, name: str, *, model: str | None, k: int, score: ScoreKind,
                         proposals: Policy | None = None) -> CacheInfo:
        entry = self._entries[name]
        pinned = entry.cache.config.model
        if model is not None and pinned is not None:
            resolved = (await self._embedder(model)).name
            if resolved != pinned:
                raise Conflict(f"cache {name!r} is pinned to model {pinned!r}; create another "
                               f"cache for {resolved!r}", field="model")
        async with entry.writer:
            op = entry.cache.plan_configure(k=k, score=score, proposals=proposals)
            if op is not None:
                await self._commit(entry, op)
        return self.describe(name)

    async def add(self, name: str, items: Sequence[Item], job: Job | None = None
                  ) -> Added:
        """Embed and add experiences; durable (fsync'd) when this returns."""
        entry = self.entry(name)
        config = entry.cache.config
        vectors = await self._vectors_for(config, items, job)
        found = await self._new_phrases(entry, [d for it in items for d in it.detections])
        async with entry.writer:
            op = entry.cache.plan_add(
                vectors, ids=[it.id for it in items], texts=[it.text for it in items],
                metadata=[it.metadata for it in items],
                detections=[it.detections for it in items], detection_vectors=found)
            await self._commit(entry, op)
            result = Added(ids=[e.id for e in op.experiences],
                           size=entry.cache.size, version=entry.cache.version,
                           job=None if job is None else job.id)
        if job is not None:
            job.progress(len(items), len(items))
        return result

    async def _vectors_for(self, config: CacheConfig, items: Sequence[Item], job: Job | None
                           ) -> np.ndarray:
        texts = [(i, it.text) for i, it in enumerate(items) if it.vector is None]
        # float64 until plan_add scales each row to unit length, once
        vectors = np.zeros((len(items), config.dim), dtype=np.float64)
        given = [(i, it.vector) for i, it in enumerate(items) if it.vector is not None]
        if given:
            check_dims(config, [v for _, v in given], [i for i, _ in given])
            vectors[[i for i, _ in given]] = [v for _, v in given]
        if texts:
            if config.model is None:
                raise Conflict(f"cache {config.name!r} has no embedding model: send "
                               "vectors instead of texts", field="items")
            embedder = await self._embedder(config.model)
            progress = job.progress if job is not None else None
            embedded = await self._on_compute(
                embedder.embed, [t for _, t in texts], batch_size=self.settings.embed_batch_size,
                progress=progress, show_progress_bar=len(texts) >= 1000)
            vectors[[i for i, _ in texts]] = embedded
        return vectors

    # -- proposals (see .proposals) ----------------------------------------------------

    def proposals(self, name: str, state: State | None = None) -> list[Proposal]:
        entry = self.entry(name)
        return [p for p in entry.proposals.values() if state is None or p.state == state]

    async def propose(self, name: str, obs: Observation, *, request_id: str, model: str,
                      rationale: str, score: float, p_value: float | None,
                      now: float) -> Proposal | None:
        """The slow reasoner answered "continue" for ``obs``, which this detector flagged:
        propose the scene to cache ``name`` (counted if it was proposed before; accepted at
        once under the policy ``auto``). None when the cache holds the scene already, or
        has ``max_pending_proposals`` pending and this one is new."""
        entry = self.entry(name)
        ident = scene_id(obs)
        async with entry.writer:
            if ident in entry.cache.labels_by_id:
                return None
            known = entry.proposals.get(ident)
            if known is not None and known.state == "accepted":
                known = None  # its experience was deleted since: propose it afresh
            if known is None:
                pending = sum(p.state == "pending" for p in entry.proposals.values())
                if pending >= self.settings.max_pending_proposals:
                    log.warning("cache %s: %d proposals pending "
                                "(AESOP_EMBEDDING_MAX_PENDING_PROPOSALS): %s not proposed",
                                name, pending, ident)
                    return None
            proposal = known.again(now) if known is not None else Proposal.first(
                obs, request_id=request_id, model=model, rationale=rationale, score=score,
                p_value=p_value, now=now)
            await asyncio.to_thread(self.store.save_proposal, name, proposal)
            entry.proposals[ident] = proposal
        self._tell("proposed", proposal)
        if proposal.state == "pending" and entry.cache.config.proposals == "auto":
            return await self.accept(name, ident, now=now)
        return proposal

    async def accept(self, name: str, ident: str, *, now: float) -> Proposal:
        """Add a pending proposal's scene as a nominal experience (id = the scene's): one
        transaction with the proposal's new state; the calibration goes stale."""
        entry = self.entry(name)
        proposal = self._pending(entry, ident)
        config = entry.cache.config
        item = Item(text=proposal.text, id=ident, detections=proposal.detections, metadata={
            "proposal": {"robot": proposal.robot, "seq": proposal.seq, "count": proposal.count,
                         "request_id": proposal.request_id, "model": proposal.model}})
        vectors = await self._vectors_for(config, [item], None)
        found = await self._new_phrases(entry, item.detections)
        async with entry.writer:
            proposal = self._pending(entry, ident).decided("accepted", now)
            op = entry.cache.plan_add(vectors, ids=[ident], texts=[item.text],
                                      metadata=[item.metadata], detections=[item.detections],
                                      detection_vectors=found)
            await self._commit(entry, op, proposal)
            entry.proposals[ident] = proposal
        self._tell("accepted", proposal)
        return proposal

    async def reject(self, name: str, ident: str, *, now: float) -> Proposal:
        entry = self.entry(name)
        async with entry.writer:
            proposal = self._pending(entry, ident).decided("rejected", now)
            await asyncio.to_thread(self.store.save_proposal, name, proposal)
            entry.proposals[ident] = proposal
        self._tell("rejected", proposal)
        return proposal

    def _pending(self, entry: Entry, ident: str) -> Proposal:
        proposal = entry.proposals.get(ident)
        if proposal is None:
            raise NotFound(f"no proposal {ident!r} on cache {entry.cache.name!r}", field="id")
        if proposal.state != "pending":
            raise Conflict(f"proposal {ident!r} is already {proposal.state}", field="id")
        return proposal

    def _tell(self, what: str, proposal: Proposal) -> None:
        for listener in self.proposal_listeners:
            try:
                listener(what, proposal)
            except Exception:
                log.exception("a proposal listener failed")

    async def _new_phrases(self, entry: Entry, detections: Sequence[Detection]
                           ) -> dict[str, np.ndarray]:
        """Unit vectors, by the cache's model, of the detections' phrases the cache has
        no vector for yet (``Cache.plan_add`` takes them)."""
        config = entry.cache.config
        phrases = list(dict.fromkeys(d.phrase for d in detections))
        with entry.rw.read():
            phrases = [p for p in phrases if p not in entry.cache.detection_vectors]
        if not phrases:
            return {}
        if config.model is None:
            raise Conflict(f"cache {config.name!r} has no embedding model to embed "
                           "detections with", field="items")
        embedder = await self._embedder(config.model)
        rows = await self._on_compute(embedder.embed, list(phrases),
                                      batch_size=self.settings.embed_batch_size)
        return dict(zip(phrases, unit_vectors(rows), strict=True))

    async def delete(self, name: str, ident: str) -> Deleted:
        entry = self.entry(name)
        async with entry.writer:
            await self._commit(entry, entry.cache.plan_delete(ident))
            return Deleted(id=ident, size=entry.cache.size, version=entry.cache.version)

    async def calibrate(
        self,
        name: str,
        method: Method,
        *,
        alpha: float | None = None,
        tpr: float | None = None,
        calibration: Sequence[Labelled] = (),
        pairs: bool = False,
    ) -> Calibrated:
        """Compute tau and store it with the cache. The answer adds, for a labelled
        calibration set with both classes, its ROC curve (at most 201 points).
        ``pairs``: keep pair scores too (:mod:`.detections`)."""
        entry = self.entry(name)
        if pairs and method == "tpr-target":
            raise InvalidInput("pairs are calibrated by loo-quantile or conformal, not "
                               "tpr-target", field="pairs")
        async with entry.writer:
            if pairs and not entry.cache.pair_counts:
                raise Conflict(f"cache {name!r} has no experience with two or more "
                               "detections: it has no pair to score against", field="pairs")
            scores = labels = components = None
            if calibration:
                scored = await self._score_labelled(entry, calibration, pairs=pairs)
                scores = np.array([r.score for r in scored])
                labels = np.array([x.is_anomaly for x in calibration], dtype=bool)
                components = Components(scores, floats(r.detection_score for r in scored),
                                        floats(r.pair_score for r in scored) if pairs
                                        else None)
            loo = (await on_fresh_thread(self._loo_all, entry, pairs)
                   if method == "loo-quantile" else None)
            cal = await self._calibration(entry, method, alpha, tpr, scores, labels,
                                          None if loo is None else loo.observation)
            cal = replace(cal, pairs=pairs)
            kept = self._calibration_scores(cal, loo, components, labels)
            await self._commit(entry, entry.cache.plan_calibration(cal, kept))
            version = entry.cache.version
        roc = None
        if scores is not None and labels is not None and labels.any() and (~labels).any():
            roc = Roc(**roc_points(scores, labels))
        return Calibrated(**cal.to_dict(), cache=name, version=version, roc=roc)

    async def _calibration(self, entry: Entry, method: Method, alpha: float | None,
                           tpr: float | None, scores: np.ndarray | None,
                           labels: np.ndarray | None, loo: np.ndarray | None) -> Calibration:
        """``loo``: the members' leave-one-out scores (loo-quantile)."""
        try:
            if method == "loo-quantile":
                assert loo is not None
                cal = loo_quantile(loo, 0.95 if alpha is None else alpha)
                if scores is not None and labels is not None and labels.any() \
                        and (~labels).any():
                    cal = replace(cal, auroc=auroc(scores, labels))
                return cal
            if method == "conformal":
                if scores is None or labels is None or (~labels).sum() == 0:
                    raise InvalidInput("conformal calibration needs held-out nominal examples",
                                       field="calibration")
                cal = conformal(scores[~labels], 0.95 if alpha is None else alpha)
                if labels.any():
                    cal = replace(cal, auroc=auroc(scores, labels))
                return cal
            if scores is None or labels is None:
                raise InvalidInput("tpr-target calibration needs a labelled calibration set",
                                   field="calibration")
            return tpr_target(scores, labels, 0.9 if tpr is None else tpr)
        except CalibrationError as exc:
            raise InvalidInput(str(exc), field=exc.field) from None

    async def _score_labelled(self, entry: Entry, items: Sequence[Labelled], *,
                              pairs: bool = False) -> list[Scored]:
        """Score a labelled set, each with its detection phrases (and pair scores)."""
        config = entry.cache.config
        if config.model is None:
            raise Conflict(f"cache {config.name!r} has no embedding model",
                           field="calibration")
        await self._embedder(config.model)  # loaded off the compute thread
        queries = [Query(x.text, tuple(dict.fromkeys(x.detections))) for x in items]
        return await self._on_compute(self._embed_and_score, entry, entry.cache.config.k,
                                      queries, pairs)

    @staticmethod
    def _calibration_scores(cal: Calibration, loo: Components | None,
                            components: Components | None,
                            labels: np.ndarray | None) -> CalibrationScores | None:
        """The nominal scores behind ``cal``'s p-values: the leave-one-out scores of
        the components (loo-quantile) or the calibration set's nominal ones (conformal);
        None for tpr-target. Refused when the combined p-value could never flag."""
        if cal.method == "loo-quantile":
            assert loo is not None
            kept = CalibrationScores.of(*loo)
        elif cal.method == "conformal" and components is not None and labels is not None:
            nominal = ~labels
            kept = CalibrationScores.of(
                components.observation[nominal], components.detection[nominal],
                None if components.pair is None else components.pair[nominal])
        else:
            return None
        if cal.alpha is not None:
            kept.check_power(cal.alpha)
        return kept

    def _loo_all(self, entry: Entry, pairs: bool) -> Components:
        """Each member's leave-one-out scores: the whole observation's, its worst
        detection's (NaN without detections; none for a cache without any) and, if asked,
        its worst pair's (NaN with fewer than two detections)."""
        with entry.rw.read():
            cache = entry.cache
            return Components(
                cache.loo_scores(),
                cache.loo_detection_scores() if cache.has_detections else np.zeros(0),
                cache.loo_pair_scores() if pairs else None)

    async def _commit(self, entry: Entry, op: Op, proposal: Proposal | None = None) -> None:
        """Commit ``op`` (with the ``proposal`` it accepts) to the database, then apply
        it: a 2xx after this is durable."""
        cache = entry.cache
        await asyncio.to_thread(self.store.commit, cache.name, op, cache.header.after(op),
                                proposal)
        with entry.rw.write():
            cache.apply(op)
        if isinstance(op, Add | Delete):
            entry.changed += len(op.labels) if isinstance(op, Add) else 1
        limit = self.settings.index_save_changes
        if limit and entry.changed >= limit:
            await asyncio.to_thread(self._save_index, entry)

    # -- scoring ------------------------------------------------------------------

    async def score_texts(self, name: str, texts: Sequence[str], k: int | None = None, *,
                          urgent: bool = False,
                          detections: Sequence[Sequence[Detection]] = ()) -> ScoreBatch:
        """Score ``texts``, each with its ``detections`` if given (one list per text).
        ``urgent`` (the bus's verdicts) goes before all other work on
        the compute thread and is never refused; other work runs as chunks of
        ``score_chunk`` texts and is refused with :class:`Busy` past
        ``max_pending_texts``. Cancelling the call drops the chunks not yet started."""
        queries = [Query.of(t, d) for t, d in
                   zip(texts, detections or [()] * len(texts), strict=True)]
        entry = self.entry(name)
        cache = entry.cache
        k = k or cache.config.k
        with entry.rw.read():
            cache.check_k(k)
        if cache.config.model is None:
            raise Conflict(f"cache {name!r} has no embedding model: score vectors",
                           field="texts")
        if urgent:
            return self._batch(entry, await self._score_on(entry, k, queries, True), k)
        limit = self.settings.max_pending_texts
        if self._rest_pending + len(texts) > limit:
            raise Busy(f"{self._rest_pending} texts are already waiting to be scored; with "
                       f"these {len(texts)} that is past the limit of {limit} "
                       "(AESOP_EMBEDDING_MAX_PENDING_TEXTS): retry later", field="texts")
        self._rest_pending += len(texts)
        try:
            results: list[Scored] = []
            step = self.settings.score_chunk
            for start in range(0, len(texts), step):
                results += await self._score_on(entry, k, queries[start:start + step], False)
        finally:
            self._rest_pending -= len(texts)
        return self._batch(entry, results, k)

    async def _score_on(self, entry: Entry, k: int, queries: list[Query], urgent: bool
                        ) -> list[Scored]:
        if self.settings.microbatch:
            return await self._batcher(entry, k, urgent).submit(queries)
        return await asyncio.get_running_loop().run_in_executor(
            self._urgent if urgent else self._compute,
            partial(self._embed_and_score, entry, k, queries))

    async def score_vectors(self, name: str, rows: Sequence[Sequence[float]],
                            k: int | None = None) -> ScoreBatch:
        entry = self.entry(name)
        check_dims(entry.cache.config, rows)
        k = k or entry.cache.config.k
        results = await self._score_vectors(entry, unit_vectors(np.array(rows)), k)
        return self._batch(entry, results, k)

    def _batch(self, entry: Entry, results: list[Scored], k: int) -> ScoreBatch:
        c = entry.cache
        return ScoreBatch(results, c.threshold, c.stale, c.version, k, c.config.model)

    def _batcher(self, entry: Entry, k: int, urgent: bool) -> MicroBatcher[Query, Scored]:
        """One batcher per (k, lane): the bus's observations are batched together and
        apart from REST chunks, which are batched up to one chunk's size."""
        if (k, urgent) not in entry.batchers:
            entry.batchers[k, urgent] = MicroBatcher(
                lambda queries: self._embed_and_score(entry, k, queries),
                max_items=self.settings.microbatch_max if urgent else self.settings.score_chunk,
                window_s=self.settings.microbatch_window_ms / 1000,
                on_batch=self._on_batch, executor=self._urgent if urgent else self._compute)
        return entry.batchers[k, urgent]

    def _embed_and_score(self, entry: Entry, k: int, queries: list[Query],
                         pairs: bool = False) -> list[Scored]:
        """Embed the texts, and the detection phrases the cache has no vector for, in one
        call; then score."""
        config = entry.cache.config
        assert config.model is not None
        phrases = list(dict.fromkeys(p for q in queries for p in q.phrases))
        with entry.rw.read():
            known = {p: entry.cache.detection_vectors[p] for p in phrases
                     if p in entry.cache.detection_vectors}
        known |= self._phrases.recall(config.model, [p for p in phrases if p not in known])
        unknown = [p for p in phrases if p not in known]
        rows = self.embedders.get(config.model).embed(
            [q.text for q in queries] + unknown, batch_size=self.settings.embed_batch_size)
        vectors = rows[:len(queries)]
        if unknown:
            new = dict(zip(unknown, unit_vectors(rows[len(queries):]), strict=True))
            self._phrases.keep(config.model, new)
            known |= new
        found = [Detections(q.phrases, np.stack([known[p] for p in q.phrases]))
                 if q.phrases else None for q in queries]
        with entry.rw.read():
            return entry.cache.score(vectors, k, self.settings.verdict_neighbors, found,
                                     pairs=pairs)

    async def _score_vectors(self, entry: Entry, vectors: np.ndarray, k: int | None = None
                             ) -> list[Scored]:
        def run() -> list[Scored]:
            with entry.rw.read():
                return entry.cache.score(vectors, k, self.settings.verdict_neighbors)

        return await self._on_compute(run)

    async def _on_compute(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Run ``fn`` on the compute thread (see the module docstring)."""
        return await asyncio.get_running_loop().run_in_executor(
            self._compute, partial(fn, *args, **kwargs))

    async def _embedder(self, model: str) -> Embedder:
        try:
            return await on_fresh_thread(self.embedders.get, model)
        except ModelNotFound as exc:
            raise InvalidInput(str(exc), field="model") from None
