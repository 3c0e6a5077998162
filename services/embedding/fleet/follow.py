"""A replica following the others' writes to the shared store
(:mod:`services.embedding.storage.pgstore`).

A thread listens on PostgreSQL and hands each notice to the event loop, where the cache
service applies it (``CacheService.follow``, through :class:`Followed`): a cache's new
version is read from the change log and applied to this replica's copy and index, a
proposal is read again.
Every ``poll_s`` the stored versions are compared too (one query), and after the listener
was cut off everything is read again, so a lost notice costs at most ``poll_s`` of lag.
Its own notices (its ``origin``) are skipped.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from typing import Protocol

from ..detector.errors import StorageError
from ..storage.pgstore import Notice, PostgresStore

log = logging.getLogger(__name__)

POLL = "poll"


class Followed(Protocol):
    """What a follower needs of the cache service: the shared store, and the catch-ups
    it applies to this replica's copies."""

    def shared_store(self) -> PostgresStore: ...

    async def sync(self, *, proposals: bool) -> None: ...

    async def follow(self, name: str) -> None: ...

    async def follow_proposal(self, name: str, ident: str) -> None: ...


class Follower:
    def __init__(self, caches: Followed, poll_s: float = 5.0) -> None:
        self.caches = caches
        self.poll_s = poll_s
        self._stop = threading.Event()
        self._queue: asyncio.Queue[Notice | None] = asyncio.Queue()
        self._thread: threading.Thread | None = None
        self._task: asyncio.Task[None] | None = None
        self._failing = False

    def start(self) -> None:
        store = self.caches.shared_store()
        loop = asyncio.get_running_loop()

        def notice(n: Notice | None) -> None:
            if n is None or n.get("origin") != store.origin:
                loop.call_soon_threadsafe(self._queue.put_nowait, n)

        self._thread = threading.Thread(target=store.listen, args=(self._stop, notice),
                                        name="aesop-follow", daemon=True)
        self._thread.start()
        self._task = asyncio.create_task(self._run())

    async def stop(self) -> None:
        self._stop.set()
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, 5.0)

    async def _run(self) -> None:
        while True:
            try:
                notice = await asyncio.wait_for(self._queue.get(), self.poll_s)
            except TimeoutError:
                notice = {POLL: True}
            try:
                await self._apply(notice)
            except (StorageError, KeyError) as exc:
                if not self._failing:
                    log.warning("following the other replicas: %s (read again when the "
                                "store answers)", exc)
                self._failing = True
            else:
                self._failing = False

    async def _apply(self, notice: Notice | None) -> None:
        if notice is None or self._failing:
            await self.caches.sync(proposals=True)
        elif POLL in notice:
            await self.caches.sync(proposals=False)
        elif "version" in notice:
            await self.caches.follow(notice["cache"])
        elif "proposal" in notice:
            await self.caches.follow_proposal(notice["cache"], notice["proposal"])
