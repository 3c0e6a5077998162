"""Fan-out of stream items to every connected page without a slow page holding up the rest.

Each client has its own bounded queue; when it is full the oldest item is
dropped (and counted), so publishing never waits. Everything runs on the one
asyncio loop of the service.
"""

from __future__ import annotations

import asyncio
from collections import deque


class ClientQueue:
    """Items for one page, newest kept: ``put`` never blocks, ``get`` waits."""

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError("maxsize must be >= 1")
        self._items: deque[str] = deque(maxlen=maxsize)
        self._ready = asyncio.Event()
        self.closed = False
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._items)

    def put(self, item: str) -> None:
        if self.closed:
            return
        if len(self._items) == self._items.maxlen:
            self.dropped += 1
        self._items.append(item)
        self._ready.set()

    async def get(self) -> str | None:
        """The oldest item; None once closed."""
        while not self._items:
            if self.closed:
                return None
            self._ready.clear()
            await self._ready.wait()
        return self._items.popleft()

    def close(self) -> None:
        self.closed = True
        self._items.clear()
        self._ready.set()


class Hub:
    """The set of connected clients; ``publish`` puts one serialized item in every queue."""

    def __init__(self, maxsize: int) -> None:
        self.maxsize = maxsize
        self.clients: set[ClientQueue] = set()
        self._dropped_by_gone = 0

    def connect(self) -> ClientQueue:
        client = ClientQueue(self.maxsize)
        self.clients.add(client)
        return client

    def disconnect(self, client: ClientQueue) -> None:
        if client in self.clients:
            self.clients.discard(client)
            self._dropped_by_gone += client.dropped
        client.close()

    def publish(self, item: str) -> None:
        for client in self.clients:
            client.put(item)

    @property
    def dropped(self) -> int:
        """Items dropped for slow clients so far, connected or gone."""
        return self._dropped_by_gone + sum(c.dropped for c in self.clients)

    def close(self) -> None:
        for client in list(self.clients):
            self.disconnect(client)
