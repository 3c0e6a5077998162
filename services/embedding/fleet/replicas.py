"""The live detector replicas as this one sees them on Zenoh, and which robots are its own.

A replica declares the liveliness token ``aesop/health/embedding/<replica>`` and subscribes
to the others' (with history: those alive before it started too); :func:`.sharding.owner`
over that set says whether a robot's observations are this replica's to score. Itself
always counts, so a replica alone, or one that cannot see the others, scores every robot:
a robot is never left unscored because the bus is partitioned (two replicas may then both
answer it, which the control loop handles as two verdicts of one observation). A replica
killed with ``kill -9`` drops its token when its link closes; its robots are the others'
from then on.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import zenoh

from shared import topics

from .sharding import owner

log = logging.getLogger(__name__)

SERVICE = "embedding"


def replica_key(replica: str) -> str:
    return f"{topics.health(SERVICE)}/{replica}"


class Replicas:
    """Membership (thread-safe reads: ``owns`` runs on Zenoh's threads)."""

    def __init__(self, me: str, on_change: Callable[[frozenset[str]], None] | None = None
                 ) -> None:
        if not me or any(c in me for c in "/*$#?") or me != me.strip():
            raise ValueError(f"replica name {me!r}: one key chunk, no '/', '*', '$', '#', '?'")
        self.me = me
        self._others: frozenset[str] = frozenset()
        self._lock = threading.Lock()
        self._on_change = on_change
        self._token: zenoh.LivelinessToken | None = None
        self._subscriber: zenoh.Subscriber[None] | None = None

    @property
    def live(self) -> frozenset[str]:
        return self._others | {self.me}

    def owns(self, robot: str) -> bool:
        return owner(robot, self.live) == self.me

    def seen(self, replica: str, alive: bool) -> None:
        """A replica's token appeared or went away."""
        if replica == self.me:
            return
        with self._lock:
            before = self._others
            self._others = before | {replica} if alive else before - {replica}
            changed = self._others != before
        if changed:
            log.info("detector replicas: %s (this one: %s)", ", ".join(sorted(self.live)),
                     self.me)
            if self._on_change is not None:
                self._on_change(self.live)

    def join(self, session: zenoh.Session) -> None:
        """Declare this replica's token and follow the others' on ``session``."""
        self._subscriber = session.liveliness().declare_subscriber(
            replica_key("*"), self._on_sample, history=True)
        self._token = session.liveliness().declare_token(replica_key(self.me))

    def leave(self) -> None:
        for declared in (self._token, self._subscriber):
            if declared is not None:
                try:
                    declared.undeclare()
                except zenoh.ZError as exc:  # the session is closed already
                    log.debug("undeclare: %s", exc)
        self._token = self._subscriber = None

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.seen(str(sample.key_expr).rsplit("/", 1)[-1],
                  sample.kind == zenoh.SampleKind.PUT)
