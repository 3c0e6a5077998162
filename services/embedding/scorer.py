"""Scoring against a cache: micro-batched, on the compute thread, in two lanes.

Model inference and query searches all run on ONE dedicated compute thread (torch and FAISS
share libgomp, which keeps a team of OpenMP threads per calling thread; with more than one
such thread alive, embedding one observation took twice as long). The bus's observations go
in the urgent lane, before REST scoring and admin work; REST requests run as chunks of
``score_chunk`` texts and are refused past ``max_pending_texts``.

One exception: a bus observation whose vectors are all known already (its text in the
memo, its detection phrases in the cache or the memo: a camera describing the scene it
described before) needs no model, only a search (one query, on one OpenMP thread), and is
scored at once on a search thread of its own (``known``), beside whatever the compute
thread is embedding. Embedding is not preemptible: without it such an observation waited
for the batch being embedded, and a robot flooding distinct texts kept one of its own in
nearly every batch (issue 43, finding 10: the other robot's verdicts waited up to a whole
embedding of the flood's, 60 ms on a busy 2-core machine, for a search of 1 ms).
"""

from __future__ import annotations

import asyncio
import threading
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass
from functools import partial
from typing import Any, TypeVar

import numpy as np

from shared.messages import Detection
from shared.threads import on_fresh_thread

from .batching import MicroBatcher
from .detector.cache import CacheConfig, Detections, Labelled, Scored, unit_vectors
from .detector.detections import embedded_form
from .detector.errors import Busy, Conflict, InvalidInput
from .entries import Entry, Query
from .models.base import Embedder, ModelNotFound
from .models.loading import EmbedderPool
from .settings import VERDICT_NEIGHBORS, EmbeddingSettings

T = TypeVar("T")


class VectorMemo:
    """The most recent ``size`` vectors by (model, text). For detection phrases no cache
    holds: a camera reports an odd object ten times a second, and embedding it beside every
    observation's text made the bus's verdicts ~6 ms slower (p50). For whole observations:
    a robot's camera describes the same scene frame after frame, and a fleet's robots see
    the same places; a model gives one text one vector, so a text seen again is not
    embedded again (``aesop bench fleet``: what a core buys with and without it)."""

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


@dataclass(frozen=True)
class ScoreBatch:
    results: list[Scored]
    threshold: float | None
    stale: bool
    version: int
    k: int
    model: str | None
    alpha: float | None = None  # the calibration's (1 - alpha: the false-positive promise)


def check_dims(config: CacheConfig, rows: Sequence[Sequence[float]],
               where: Sequence[int] | None = None) -> None:
    """Every row has the cache's pinned dimension (else Conflict naming the row)."""
    for n, row in enumerate(rows):
        if len(row) != config.dim:
            i = n if where is None else where[n]
            raise Conflict(f"vector has dimension {len(row)}; cache {config.name!r} is pinned "
                           f"to dimension {config.dim}", field=f"vectors[{i}]")


class Scorer:
    """Scores texts (with their detections) and vectors against the caches ``entry``
    looks up, on the compute thread's ``normal`` and ``urgent`` lanes."""

    def __init__(self, settings: EmbeddingSettings, embedders: EmbedderPool,
                 entry: Callable[[str], Entry], normal: Executor, urgent: Executor,
                 on_batch: Callable[[int], None] | None = None,
                 known: Executor | None = None) -> None:
        """``known``: where a bus observation whose vectors are all known is scored (not
        behind the compute thread's embeddings); None: in the urgent lane's batches."""
        self.settings = settings
        self.embedders = embedders
        self.entry = entry
        self._compute = normal
        self._urgent = urgent
        self._known = known
        self._on_batch = on_batch
        self._rest_pending = 0  # REST texts being scored or waiting (max_pending_texts)
        self._phrases = VectorMemo()
        self._texts = VectorMemo(settings.tuning.text_memo)

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
            return self._batch(entry, await self._score_urgent(entry, k, queries), k)
        limit = self.settings.limits.max_pending_texts
        if self._rest_pending + len(texts) > limit:
            raise Busy(f"{self._rest_pending} texts are already waiting to be scored; with "
                       f"these {len(texts)} that is past the limit of {limit} "
                       "(AESOP_EMBEDDING_LIMITS__MAX_PENDING_TEXTS): retry later", field="texts")
        self._rest_pending += len(texts)
        try:
            results: list[Scored] = []
            step = self.settings.tuning.score_chunk
            for start in range(0, len(texts), step):
                results += await self._score_on(entry, k, queries[start:start + step], False)
        finally:
            self._rest_pending -= len(texts)
        return self._batch(entry, results, k)

    async def _score_urgent(self, entry: Entry, k: int, queries: list[Query]) -> list[Scored]:
        """The bus's: on the search thread if no vector is to embed, else in the urgent
        lane's batches."""
        if self._known is not None and self._texts.size:
            scored = await asyncio.get_running_loop().run_in_executor(
                self._known, partial(self._score_known, entry, k, queries))
            if scored is not None:
                return scored
        return await self._score_on(entry, k, queries, True)

    async def _score_on(self, entry: Entry, k: int, queries: list[Query], urgent: bool
                        ) -> list[Scored]:
        if self.settings.tuning.microbatch:
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
        alpha = None if c.calibration is None else c.calibration.alpha
        return ScoreBatch(results, c.threshold, c.stale, c.version, k, c.config.model, alpha)

    def _batcher(self, entry: Entry, k: int, urgent: bool) -> MicroBatcher[Query, Scored]:
        """One batcher per (k, lane): the bus's observations are batched together and
        apart from REST chunks, which are batched up to one chunk's size."""
        tuning = self.settings.tuning
        if (k, urgent) not in entry.batchers:
            entry.batchers[k, urgent] = MicroBatcher(
                lambda queries: self._embed_and_score(entry, k, queries),
                max_items=tuning.microbatch_max if urgent else tuning.score_chunk,
                window_s=tuning.microbatch_window_ms / 1000,
                on_batch=self._on_batch, executor=self._urgent if urgent else self._compute)
        return entry.batchers[k, urgent]

    def _recall(self, entry: Entry, model: str, queries: list[Query]) -> tuple[
            dict[str, np.ndarray], dict[str, np.ndarray], list[str], list[str]]:
        """The vectors known without the model: of the texts (the memo) and of the
        detection phrases (the cache's, the memo's); and the texts and phrases to embed."""
        phrases = list(dict.fromkeys(p for q in queries for p in q.phrases))
        with entry.rw.read():
            known = {p: entry.cache.detection_vectors[p] for p in phrases
                     if p in entry.cache.detection_vectors}
        known |= self._phrases.recall(model, [p for p in phrases if p not in known])
        unknown = [p for p in phrases if p not in known]
        texts = list(dict.fromkeys(q.text for q in queries))
        seen = self._texts.recall(model, texts) if self._texts.size else {}
        fresh = [t for t in texts if t not in seen]
        return seen, known, fresh, unknown

    def _score_known(self, entry: Entry, k: int, queries: list[Query]) -> list[Scored] | None:
        """Score ``queries`` if every vector they need is known (None if one is to
        embed): a search, no model."""
        model = entry.cache.config.model
        assert model is not None
        seen, known, fresh, unknown = self._recall(entry, model, queries)
        if fresh or unknown:
            return None
        return self._score(entry, k, queries, seen, known)

    def _score(self, entry: Entry, k: int, queries: list[Query], texts: dict[str, np.ndarray],
               phrases: dict[str, np.ndarray], pairs: bool = False) -> list[Scored]:
        vectors = np.stack([texts[q.text] for q in queries])
        found = [Detections(q.phrases, np.stack([phrases[p] for p in q.phrases]))
                 if q.phrases else None for q in queries]
        with entry.rw.read():
            return entry.cache.score(vectors, k, VERDICT_NEIGHBORS, found, pairs=pairs)

    def _embed_and_score(self, entry: Entry, k: int, queries: list[Query],
                         pairs: bool = False) -> list[Scored]:
        """Embed the texts, and the detection phrases the cache has no vector for, in one
        call; then score."""
        config = entry.cache.config
        assert config.model is not None
        seen, known, fresh, unknown = self._recall(entry, config.model, queries)
        rows = self.embedders.get(config.model).embed(
            fresh + [embedded_form(p) for p in unknown],
            batch_size=self.settings.tuning.embed_batch_size) if fresh or unknown else None
        if fresh:
            assert rows is not None
            embedded = dict(zip(fresh, rows[:len(fresh)], strict=True))
            if self._texts.size:
                self._texts.keep(config.model, embedded)
            seen |= embedded
        if unknown:
            assert rows is not None
            new = dict(zip(unknown, unit_vectors(rows[len(fresh):]), strict=True))
            self._phrases.keep(config.model, new)
            known |= new
        return self._score(entry, k, queries, seen, known, pairs)

    async def _score_vectors(self, entry: Entry, vectors: np.ndarray, k: int | None = None
                             ) -> list[Scored]:
        def run() -> list[Scored]:
            with entry.rw.read():
                return entry.cache.score(vectors, k, VERDICT_NEIGHBORS)

        return await self.on_compute(run)

    async def score_labelled(self, entry: Entry, items: Sequence[Labelled], *,
                              pairs: bool = False) -> list[Scored]:
        """Score a labelled set, each with its detection phrases (and pair scores)."""
        config = entry.cache.config
        if config.model is None:
            raise Conflict(f"cache {config.name!r} has no embedding model",
                           field="calibration")
        await self.embedder(config.model)  # loaded off the compute thread
        queries = [Query(x.text, tuple(dict.fromkeys(x.detections))) for x in items]
        return await self.on_compute(self._embed_and_score, entry, entry.cache.config.k,
                                      queries, pairs)

    async def on_compute(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Run ``fn`` on the compute thread's normal lane."""
        return await asyncio.get_running_loop().run_in_executor(
            self._compute, partial(fn, *args, **kwargs))

    async def embedder(self, model: str) -> Embedder:
        """The model, loaded on a thread of its own (not the compute thread: see
        :func:`shared.threads.on_fresh_thread`); a model there is none of is an InvalidInput."""
        try:
            return await on_fresh_thread(self.embedders.get, model)
        except ModelNotFound as exc:
            raise InvalidInput(str(exc), field="model") from None

    @staticmethod
    async def close(entry: Entry) -> None:
        for batcher in entry.batchers.values():
            await batcher.close()
