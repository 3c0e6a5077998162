"""The bridge's queues: bounded drop-oldest lanes, taken by priority or in turn by one worker.

Named lanes, each a bounded drop-oldest FIFO (at most so many items
and so many bytes), behind one condition, from which one worker takes either by priority
(the first lane with something in it: the set-points before the rest) or in turn (each
lane one item at a time: a flood on one ROS topic waits behind the others' samples, not
in front of them).

A lane holds what it is given by reference; ``size`` is what the caller says the item
costs (a sample's bytes; 0 for an item bounded by count alone), so the bytes a lane holds
never pass its ``max_bytes`` (an item larger than that is refused, never queued).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Limit:
    items: int
    bytes: int | None = None  # None: bounded by count alone (the items cost 0)


@dataclass
class _Lane:
    limit: Limit
    queue: deque[tuple[Any, int]] = field(default_factory=deque)
    bytes: int = 0
    peak_bytes: int = 0
    dropped: int = 0


class Lanes:
    def __init__(self, limits: Mapping[str, Limit], *, in_turn: bool) -> None:
        if not limits or any(lim.items < 1 or (lim.bytes is not None and lim.bytes < 1)
                             for lim in limits.values()):
            raise ValueError(f"lanes need at least one item and one byte each: {limits}")
        self._lanes = {name: _Lane(limit) for name, limit in limits.items()}
        self._order = list(limits)
        self._in_turn = in_turn
        self._next = 0  # in turn: the lane to look at first
        self._ready = threading.Condition()
        self._closed = False

    def put(self, name: str, item: Any, size: int = 0) -> list[Any]:
        """Queue ``item`` (``size`` bytes) on lane ``name``; returns what was dropped to
        make room, oldest first (``item`` itself when it is larger than the lane)."""
        dropped: list[Any] = []
        with self._ready:
            lane = self._lanes[name]
            limit = lane.limit.bytes
            if limit is not None and size > limit:
                lane.dropped += 1
                return [item]
            while lane.queue and (len(lane.queue) >= lane.limit.items or
                                  (limit is not None and lane.bytes + size > limit)):
                old, old_size = lane.queue.popleft()
                lane.bytes -= old_size
                lane.dropped += 1
                dropped.append(old)
            lane.queue.append((item, size))
            lane.bytes += size
            lane.peak_bytes = max(lane.peak_bytes, lane.bytes)
            self._ready.notify()
        return dropped

    def take(self, timeout: float) -> tuple[str, Any] | None:
        """The next ``(lane, item)``, waiting at most ``timeout`` s for one; None when none
        came or the lanes are closed."""
        with self._ready:
            while not self._closed:
                for i in range(len(self._order)):
                    at = (self._next + i) % len(self._order) if self._in_turn else i
                    lane = self._lanes[self._order[at]]
                    if lane.queue:
                        item, size = lane.queue.popleft()
                        lane.bytes -= size
                        if self._in_turn:
                            self._next = (at + 1) % len(self._order)
                        return self._order[at], item
                if not self._ready.wait(timeout):
                    return None
            return None

    def close(self) -> None:
        """Wake the worker for good: :meth:`take` answers None from now on."""
        with self._ready:
            self._closed = True
            self._ready.notify_all()

    def bytes(self) -> int:
        """The bytes all lanes hold now."""
        with self._ready:
            return sum(lane.bytes for lane in self._lanes.values())

    def status(self) -> dict[str, dict[str, Any]]:
        """Per lane: items and bytes held now, their limits, the most bytes it has held
        and how many items it dropped."""
        with self._ready:
            return {name: {"items": len(lane.queue), "max_items": lane.limit.items,
                           "bytes": lane.bytes, "max_bytes": lane.limit.bytes,
                           "peak_bytes": lane.peak_bytes, "dropped": lane.dropped}
                    for name, lane in self._lanes.items()}
