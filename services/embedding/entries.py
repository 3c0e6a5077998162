"""One cache as the service holds it, the locks and threads its work runs under, an
experience to add and a text to score.

Per cache, writers are serialised by an asyncio lock and the database commit happens
before the in-memory apply; readers (scoring, leave-one-out) run in worker threads under
the shared side of a readers-writer lock, so they see a cache either before or after a
write.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from shared.messages import Detection

from .detector.cache import Cache
from .detector.proposals import Proposal

if TYPE_CHECKING:
    from .batching import MicroBatcher
    from .detector.cache import Scored

@dataclass(frozen=True)
class Query:
    """A text to score, with its detection phrases (distinct, in order)."""

    text: str
    phrases: tuple[str, ...] = ()

    @classmethod
    def of(cls, text: str, detections: Sequence[Detection] = ()) -> Query:
        return cls(text, tuple(dict.fromkeys(d.phrase for d in detections)))


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
