"""The service's own sender: the decisions its deadline keeper cannot send.

The keeper (:mod:`.keeper`) owns the reasoner's Zenoh session, so when it is killed (the
OOM killer, a local process) or stopped (``SIGSTOP``, a starved core) nobody else would
send a decision: the requests it held, and every request until another keeper listened,
went unanswered, and a stopped keeper sent all it held at once, late, when it ran again.

So the service keeps a second Zenoh session (:func:`standby_config`: no liveliness token,
a Zenoh ID of its own, none of the keeper's listening endpoints) and on it a
:class:`Standby`: the keeper's own logic
(:class:`~.keeper.Keeper`: the same limits and caps, the fallback armed at the same
deadline, nothing sent after it) that hears every request too, but leaves each to the
keeper that has it (its ``owner``) while that keeper is not lost. The service watches its
keeper (:class:`Watched`: its process, and the heartbeat the keeper's timer thread writes
into shared memory every ``HEARTBEAT_S``) and declares it lost when it exits or its
heartbeat stops for ``STALL_S``; a stalled keeper is killed, so that nothing it holds can
leave late. From then on the standby sends the decisions of that keeper's requests (the
answers the service had handed it at once, the fallbacks at their deadlines) and of every
request that arrives until another keeper has it.

A keeper whose process has exited is never deferred to, whether or not the watchdog has
noticed yet (on a loaded machine it notices late, and a deadline may come first).

A request is the keeper's (``owner``) when the keeper told the service it has it
(:meth:`Standby.cover`; its word can come before the standby's own session hears the
request, and is kept for it until the deadline), or when it arrived after the keeper had
been listening for ``SETTLE_S`` (its subscription has reached every publisher by then).
Otherwise it is the standby's to send. The standby's timer is a thread of the service's
process, so it is late by what the service's GIL makes it (collections of up to 110 ms
under load: see :mod:`.keeper`); it is the second line, and what it cannot send by the
deadline it drops.

What it cannot cover: a keeper stopped less than ``STALL_S`` before a deadline misses that
one (the robot's own fallback at K); requests that waited in a stopped keeper's socket
are stamped when it reads them, up to ``STALL_S`` late; and a reasoner that connects to no
endpoint (the robots connect to the keeper's) has no standby, which would reach nobody.
"""

from __future__ import annotations

import json
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import wait as ready_of
from typing import Any

import zenoh

from shared.bus import Bus, zenoh_config
from shared.messages import ReasonerDecision
from shared.settings import BusSettings

from .deciding import FallbackPolicy
from .keeper import DeadlineTimer, Keeper, Report, _Armed
from .settings import ReasonerSettings

# a keeper's subscription has reached the publishers this long after it says it listens
SETTLE_S = 0.5


@dataclass(eq=False)
class Watched:
    """One keeper process as the service watches it: ``pulse`` is its heartbeat (a shared
    ``double``: ``time.monotonic()`` of its latest beat, 0 before the first),
    ``listening_since`` when it said it listens, ``lost`` why it was given up."""

    process: Any
    pulse: Any
    listening_since: float | None = None
    lost: str | None = None

    def beat_age(self, now: float) -> float | None:
        """Seconds since its latest heartbeat (None: none yet)."""
        beat = float(self.pulse.value)
        return None if beat == 0.0 else now - beat

    def exited(self) -> bool:
        """Whether its process has exited, noticed or not yet by the watchdog (which looks
        every ``WATCH_S``, later on a loaded machine)."""
        if self.process is None:
            return False
        return bool(ready_of([self.process.sentinel], 0))

    def settled(self, at: float) -> bool:
        """Whether a request arriving ``at`` reaches it (listening for ``SETTLE_S``)."""
        return (self.lost is None and self.listening_since is not None
                and at - self.listening_since >= SETTLE_S)


class Standby(Keeper):
    """See the module docstring. ``keeper()``: the keeper now (None when there is none)."""

    def __init__(self, settings: ReasonerSettings, policy: FallbackPolicy, margin_s: float,
                 publish: Callable[[str, ReasonerDecision], None],
                 tell: Callable[[Report], None], timer: DeadlineTimer,
                 keeper: Callable[[], Watched | None], **kw: Any) -> None:
        super().__init__(settings, policy, margin_s, publish, tell, timer, **kw)
        self._keeper = keeper
        # a keeper's word for a request this session has not heard yet: (keeper, deadline)
        self._told: OrderedDict[tuple[str, str], tuple[Watched, float]] = OrderedDict()

    @property
    def covered(self) -> int:
        """Requests a keeper said it has that this session has not heard (yet)."""
        return len(self._told)

    def _owner(self, ident: tuple[str, str], received_at: float) -> Any:
        told = self._told.pop(ident, None)
        if told is not None:
            return told[0]  # the keeper said it has it before this session heard it
        keeper = self._keeper()
        return keeper if keeper is not None and keeper.settled(received_at) else None

    def _defers(self, armed: _Armed) -> bool:
        # a keeper that has exited sends nothing more, even before the watchdog says so:
        # a deadline that comes first is the standby's (CI: a keeper SIGKILLed just before
        # a deadline, noticed after it, left that request unanswered)
        owner = armed.owner
        return owner is not None and owner.lost is None and not owner.exited()

    def cover(self, robot: str, request_id: str, keeper: Watched, *, until: float) -> None:
        """``keeper`` has the request (its deadline: ``until``): it sends the decision
        while it is not lost. The keeper's word may come before this session hears the
        request (two sessions, each at its own pace): it is kept for when it does, until
        the deadline."""
        ident = (robot, request_id)
        with self._lock:
            armed = self._armed.get(ident)
            if armed is not None:
                armed.owner = keeper
                return
            now = self._clock()
            while self._told and (next(iter(self._told.values()))[1] <= now
                                  or len(self._told) >= self._max_pending):
                self._told.popitem(last=False)
            self._told[ident] = (keeper, until)

    def left(self, robot: str, request_id: str) -> None:
        """The keeper sent the request's decision: forget it."""
        with self._lock:
            armed = self._disarm((robot, request_id))
        if armed is not None:
            self._timer.cancel(armed.handle)

    def close(self) -> None:
        """Stop its timer: nothing armed leaves any more."""
        self._timer.close()

    def take_over(self, keeper: Watched) -> int:
        """``keeper`` is lost: send the answers it held now (its fallbacks leave from here
        at their deadlines); how many were sent."""
        with self._lock:
            held = [ident for ident, armed in self._armed.items()
                    if armed.owner is keeper and armed.answer is not None]
            ready = [armed for armed in map(self._disarm, held) if armed is not None]
        for armed in ready:
            self._timer.cancel(armed.handle)
            assert armed.answer is not None
            self._send(armed, armed.answer)
        return len(ready)


def standby_id(zid: str) -> str:
    """The standby session's Zenoh ID beside the keeper's ``zid`` (one session per ID at a
    router): ``zid`` and ``5b``, or its last digit changed when that is too long."""
    if len(zid) <= 30:
        return zid + "5b"
    return zid[:-1] + ("1" if zid[-1] == "0" else "0")


def standby_config(settings: BusSettings) -> zenoh.Config | None:
    """The standby session's Zenoh configuration: the keeper's (user, TLS, mode, where it
    connects) under an ID of its own, listening on no endpoint of the keeper's (a peer
    on a loopback port of its own: the keeper's must stay free for the next keeper).
    None when it would reach nobody: a reasoner that connects nowhere and does not scout
    is reached only on the keeper's own endpoints."""
    conf = zenoh_config(settings)
    zid = json.loads(conf.get_json("id"))
    if zid:
        conf.insert_json5("id", json.dumps(standby_id(str(zid))))
    mode = json.loads(conf.get_json("mode")) or "peer"
    if mode == "peer":
        conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
    connect = json.loads(conf.get_json("connect/endpoints"))
    scouting = json.loads(conf.get_json("scouting/multicast/enabled"))
    if not connect and not (mode == "peer" and scouting):
        return None
    return conf


def open_bus(conf: zenoh.Config) -> Bus:
    """The standby's Zenoh session on ``conf`` (:func:`standby_config`), with no
    liveliness token (the keeper's says the reasoner is on the bus). Blocks while Zenoh
    connects."""
    session = zenoh.open(conf)
    try:
        return Bus(session, "reasoner", alive=False)
    except BaseException:
        session.close()
        raise
