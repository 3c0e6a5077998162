"""The vector-cache service: named caches on disk, their lifecycle and every change to them.

What it holds apart: scoring (:mod:`.scorer`: the compute thread, its lanes and batchers),
the proposal workflow (:mod:`.review`), the calibration policy (:mod:`.detector.policy`),
one cache's locks (:mod:`.entries`). A change is planned on the cache, committed to the
database (a 2xx after that is durable), then applied in memory; embedding happens outside
every lock.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import numpy as np

from shared.jobs import Job, Jobs
from shared.messages import Detection
from shared.threads import on_fresh_thread

from .batching import NORMAL, URGENT, ComputeThread
from .detector import policy
from .detector.cache import Add, Cache, CacheConfig, Delete, Labelled, Op, ScoreKind, unit_vectors
from .detector.calibration import Method, roc_curve
from .detector.detections import embedded_form
from .detector.errors import Behind, Conflict, InvalidInput, NotFound, StorageError
from .detector.index import IndexKind
from .detector.policy import Components, Evidence
from .detector.proposals import Policy, Proposal
from .entries import Entry
from .fleet.follow import Follower
from .models.loading import EmbedderPool
from .review import Review
from .schemas import Added, CacheInfo, Calibrated, Deleted, Experience, Item, Roc
from .scorer import Scorer, check_dims
from .settings import DEFAULT_K, EmbeddingSettings
from .storage.pgstore import PostgresStore
from .storage.store import Store

log = logging.getLogger(__name__)

CACHE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}")


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
        on_follow: Callable[[float], None] | None = None,
    ) -> None:
        """``on_batch``: each embedding batch's size; ``on_follow``: with a shared store,
        each change of another replica's as it is applied here, with its age (s)."""
        self.settings = settings
        self.embedders = embedders or EmbedderPool(
            openai_base_url=settings.openai_base_url,
            openai_api_key=(settings.openai_api_key.get_secret_value()
                            if settings.openai_api_key else None),
            model_dir=settings.model_dir or settings.data_dir / "models",
            max_loaded=settings.max_models, export_dir=Path(settings.data_dir) / "onnx",
            threads=settings.tuning.onnx_threads)
        self.jobs = Jobs(max_running=settings.limits.max_jobs,
                         setting="AESOP_EMBEDDING_LIMITS__MAX_JOBS")
        self._entries: dict[str, Entry] = {}
        self._create_lock = asyncio.Lock()
        self._thread = ComputeThread()
        # the bus's observations that need no model: scored beside the embeddings (scorer)
        self._search = ComputeThread("aesop-search")
        self._store: Store | PostgresStore | None = None
        self._on_follow = on_follow
        self._follower: Follower | None = None
        self.scorer = Scorer(settings, self.embedders, self.entry, self._thread.lane(NORMAL),
                             self._thread.lane(URGENT), on_batch,
                             known=self._search.lane(URGENT))
        self.review = Review(self)

    @property
    def store(self) -> Store | PostgresStore:
        if self._store is None:
            raise RuntimeError("the cache service is not started")
        return self._store

    # -- lifecycle --------------------------------------------------------------

    async def start(self) -> None:
        """Open the database and load every cache (raises StorageCorrupt naming a file)."""
        self._store = await asyncio.to_thread(open_store, self.settings)
        for name in await asyncio.to_thread(self.store.names):
            await self._load(name)
        if self.store.shared:
            self._follower = Follower(self, poll_s=self.settings.tuning.follow_poll_s)
            self._follower.start()

    async def _load(self, name: str) -> Entry:
        cache = await asyncio.to_thread(self.store.load, name)
        entry = self._entries[name] = Entry(
            cache, saved=self.store.saved_index(name),
            proposals={p.id: p for p in await asyncio.to_thread(self.store.proposals, name)})
        log.info("cache %s: %d experiences, version %d", name, cache.size, cache.version)
        return entry

    async def close(self) -> None:
        if self._follower is not None:
            await self._follower.stop()
        for entry in self._entries.values():
            await self.scorer.close(entry)
            async with entry.writer:
                if entry.index_outdated():
                    await asyncio.to_thread(self._save_index, entry)
        self._entries.clear()
        if self._store is not None:
            self._store.close()
        self._thread.shutdown(wait=True)
        self._search.shutdown(wait=True)
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
        score: ScoreKind | None = None,
        index: IndexKind | None = None,
        proposals: Policy | None = None,
        model_is_default: bool = False,
    ) -> tuple[CacheInfo, bool]:
        """Create cache ``name`` (what is None: the default) or change the existing one's
        settings that are not None, leaving the others as they are (a PUT that names one
        field changes that field); returns (description, created). ``model_is_default``:
        ``model`` was not asked for, only a new cache takes it."""
        if not CACHE_NAME.fullmatch(name):
            raise InvalidInput("cache names are 1-64 letters, digits, '_', '.', '-'", field="name")
        asked = None if model_is_default else model
        async with self._create_lock:
            if name in self._entries:
                return await self._reconcile(name, model=asked, k=k, score=score,
                                             proposals=proposals), False
            if model is not None:
                embedder = await self.scorer.embedder(model)
                model, dim = embedder.name, embedder.dim
            elif dim is None:
                raise InvalidInput("a cache without a model needs 'dim'", field="dim")
            config = CacheConfig(name, model, int(dim), k or DEFAULT_K, score or "topk",
                                 index or "flat", proposals=proposals or "review")
            try:
                entry = await asyncio.to_thread(self._create_entry, config)
            except Behind:  # another replica created it meanwhile
                await self._load(name)
                return await self._reconcile(name, model=asked, k=k, score=score,
                                             proposals=proposals), False
            self._entries[name] = entry
            return CacheInfo.of(entry.cache), True

    def _create_entry(self, config: CacheConfig) -> Entry:
        self.store.create(config)
        return Entry(Cache(config))

    async def _reconcile(self, name: str, *, model: str | None, k: int | None,
                         score: ScoreKind | None, proposals: Policy | None = None
                         ) -> CacheInfo:
        entry = self._entries[name]
        pinned = entry.cache.config.model
        if model is not None and pinned is not None:
            resolved = (await self.scorer.embedder(model)).name
            if resolved != pinned:
                raise Conflict(f"cache {name!r} is pinned to model {pinned!r}; create another "
                               f"cache for {resolved!r}", field="model")
        async with self.writing(entry):
            now = entry.cache.config  # what the request does not name stays as it is
            op = entry.cache.plan_configure(k=k or now.k, score=score or now.score,
                                            proposals=proposals)
            if op is not None:
                await self.commit(entry, op)
        return self.describe(name)

    async def add(self, name: str, items: Sequence[Item], job: Job | None = None
                  ) -> Added:
        """Embed and add experiences; durable (fsync'd) when this returns."""
        entry = self.entry(name)
        config = entry.cache.config
        vectors = await self.vectors_for(config, items, job)
        found = await self.new_phrases(entry, [d for it in items for d in it.detections])
        async with self.writing(entry):
            op = entry.cache.plan_add(
                vectors, ids=[it.id for it in items], texts=[it.text for it in items],
                metadata=[it.metadata for it in items],
                detections=[it.detections for it in items], detection_vectors=found)
            await self.commit(entry, op)
            result = Added(ids=[e.id for e in op.experiences],
                           size=entry.cache.size, version=entry.cache.version,
                           job=None if job is None else job.id)
        if job is not None:
            job.progress(len(items), len(items))
        return result

    async def vectors_for(self, config: CacheConfig, items: Sequence[Item], job: Job | None
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
            embedder = await self.scorer.embedder(config.model)
            progress = job.progress if job is not None else None
            embedded = await self.scorer.on_compute(
                embedder.embed, [t for _, t in texts],
                batch_size=self.settings.tuning.embed_batch_size,
                progress=progress, show_progress_bar=len(texts) >= 1000)
            vectors[[i for i, _ in texts]] = embedded
        return vectors

    async def new_phrases(self, entry: Entry, detections: Sequence[Detection]
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
        embedder = await self.scorer.embedder(config.model)
        rows = await self.scorer.on_compute(embedder.embed, [embedded_form(p) for p in phrases],
                                      batch_size=self.settings.tuning.embed_batch_size)
        return dict(zip(phrases, unit_vectors(rows), strict=True))

    async def delete(self, name: str, ident: str) -> Deleted:
        entry = self.entry(name)
        async with self.writing(entry):
            await self.commit(entry, entry.cache.plan_delete(ident))
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
        """Compute tau by the calibration policy (:mod:`.detector.policy`) and store it with
        the cache. The answer adds, for a labelled calibration set with both classes, its ROC
        curve (at most 201 points). ``pairs``: keep pair scores too
        (:mod:`.detector.detections`)."""
        entry = self.entry(name)
        policy.check(method, pairs)
        async with self.writing(entry):
            if pairs and not entry.cache.pair_counts:
                raise Conflict(f"cache {name!r} has no experience with two or more "
                               "detections: it has no pair to score against", field="pairs")
            labelled = labels = None
            if calibration:
                scored = await self.scorer.score_labelled(entry, calibration, pairs=pairs)
                labelled, labels = policy.labelled_components(scored, calibration, pairs=pairs)
            loo = (await on_fresh_thread(self._loo_all, entry, pairs)
                   if policy.needs_loo(method) else None)
            evidence = Evidence(loo, labelled, labels)
            cal, kept = policy.calibrate(method, evidence, alpha=alpha, tpr=tpr, pairs=pairs)
            await self.commit(entry, entry.cache.plan_calibration(cal, kept))
            version = entry.cache.version
        roc = None
        if evidence.both_classes:
            assert labelled is not None and labels is not None
            roc = Roc(**roc_points(labelled.observation, labels))
        return Calibrated(**cal.to_dict(), cache=name, version=version, roc=roc)

    def _loo_all(self, entry: Entry, pairs: bool) -> Components:
        """The cache's leave-one-out evidence, under its read lock."""
        with entry.rw.read():
            return policy.loo_components(entry.cache, pairs=pairs)

    @asynccontextmanager
    async def writing(self, entry: Entry) -> AsyncIterator[None]:
        """Hold the cache's writer lock; with a shared store, the cache is first caught up
        with the other replicas' writes, so what is planned here is planned on the newest."""
        async with entry.writer:
            if self.store.shared:
                await self._catch_up(entry)
            yield

    async def commit(self, entry: Entry, op: Op, proposal: Proposal | None = None) -> None:
        """Commit ``op`` (with the ``proposal`` it accepts) to the database, then apply
        it: a 2xx after this is durable. Under :meth:`writing`. ``Behind`` (another
        replica wrote first: nothing was written) after catching up with it."""
        cache = entry.cache
        try:
            await asyncio.to_thread(self.store.commit, cache.name, op, cache.header.after(op),
                                    proposal)
        except Behind:
            await self._catch_up(entry)
            raise
        with entry.rw.write():
            cache.apply(op)
        self._changed(entry, op)
        limit = self.settings.tuning.index_save_changes
        if limit and entry.changed >= limit:
            await asyncio.to_thread(self._save_index, entry)

    def _changed(self, entry: Entry, op: Op) -> None:
        if isinstance(op, Add | Delete):
            entry.changed += len(op.labels) if isinstance(op, Add) else 1

    # -- following the other replicas (a shared store) -----------------------------

    async def follow(self, name: str) -> None:
        """Bring cache ``name`` up to the shared store: load it if it is new here."""
        entry = self._entries.get(name)
        if entry is None:
            async with self._create_lock:
                if name not in self._entries:
                    await self._load(name)
            return
        async with entry.writer:
            await self._catch_up(entry)

    async def follow_proposal(self, name: str, ident: str) -> None:
        """Read proposal ``ident`` of cache ``name`` as another replica wrote it."""
        entry = self._entries.get(name)
        if entry is None:
            return
        proposal = await asyncio.to_thread(self.shared_store().proposal, name, ident)
        if proposal is not None:
            entry.proposals[ident] = proposal

    async def sync(self, *, proposals: bool) -> None:
        """Catch up every cache and load new ones; ``proposals``: read every proposal
        again too (after the replica was not listening)."""
        stored = await asyncio.to_thread(self.shared_store().versions)
        for name, version in stored.items():
            entry = self._entries.get(name)
            if entry is None or entry.cache.version != version:
                await self.follow(name)
            if proposals:
                self._entries[name].proposals = {
                    p.id: p for p in await asyncio.to_thread(self.store.proposals, name)}

    def shared_store(self) -> PostgresStore:
        if not isinstance(self.store, PostgresStore):
            raise RuntimeError("only a shared store has other replicas to follow")
        return self.store

    async def _catch_up(self, entry: Entry) -> None:
        """Apply the changes other replicas wrote since this copy's version (under the
        cache's writer lock)."""
        cache = entry.cache
        ops, header = await asyncio.to_thread(self.shared_store().changes_since, cache.name,
                                              cache.version)
        if not ops and header == cache.header:
            return
        with entry.rw.write():
            for op, _ in ops:
                # an experience added and deleted after this copy's version: never held
                if not (isinstance(op, Delete) and op.label not in cache.experiences):
                    cache.apply(op)
                    self._changed(entry, op)
            cache.header = header
        now = time.time()
        for _, at in ops:
            if self._on_follow is not None:
                self._on_follow(max(0.0, now - at))
        log.info("cache %s: caught up to version %d (%d changes of other replicas)",
                 cache.name, cache.version, len(ops))


def open_store(settings: EmbeddingSettings) -> Store | PostgresStore:
    """The store ``settings`` name: PostgreSQL (``AESOP_EMBEDDING_STORE``), shared by
    replicas, or the SQLite file in the data directory."""
    if settings.store is not None:
        return PostgresStore(settings.store.get_secret_value(), Path(settings.data_dir),
                             fsync=settings.fsync)
    return Store(Path(settings.data_dir), fsync=settings.fsync,
                 max_bytes=settings.max_db_bytes)
