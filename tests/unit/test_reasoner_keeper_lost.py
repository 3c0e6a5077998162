"""Issue 43, finding 6, without processes: the keeper never sends a decision past its
deadline (a stopped keeper that runs again sent every fallback it held at once, late);
the standby leaves each request to the keeper that has it until that keeper is lost, then
sends its decisions; the worker decides each request once, whoever told of it first.
The processes, the heartbeat and real Zenoh are in
``tests/integration/test_reasoner_keeper.py``."""

from __future__ import annotations

import asyncio
import itertools
import json
import multiprocessing
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from services.reasoner.deciding import Decider, DeciderConfig, FallbackPolicy
from services.reasoner.keeper import Answer, Keeper, Late, Left, Report
from services.reasoner.settings import ReasonerLimits, ReasonerSettings
from services.reasoner.standby import SETTLE_S, Standby, Watched, standby_config, standby_id
from services.reasoner.worker import ReasonerWorker
from shared import topics
from shared.bus import Received
from shared.messages import Observation, Option, ReasonerDecision, ReasonerRequest
from shared.settings import BusSettings
from tests.fakes.chat_backends import Recording

SETTINGS = ReasonerSettings(limits=ReasonerLimits())
MARGIN_S = 0.02
OPTIONS = (Option(index=0, label="continue"),
           Option(index=1, label="alternative landing site"),
           Option(index=2, label="holding zone"))


class HandTimer:
    """A :class:`~services.reasoner.keeper.DeadlineTimer` fired by hand."""

    def __init__(self) -> None:
        self.armed: dict[int, tuple[float, Callable[[], None]]] = {}
        self._order = itertools.count()

    def at(self, due: float, fn: Callable[[], None]) -> int:
        handle = next(self._order)
        self.armed[handle] = (due, fn)
        return handle

    def cancel(self, handle: int) -> None:
        self.armed.pop(handle, None)

    def close(self) -> None:
        self.armed.clear()

    def fire(self, until: float) -> None:
        """Run what is due by ``until``, earliest first (as a timer that woke late)."""
        for handle, (due, fn) in sorted(self.armed.items(), key=lambda kv: kv[1][0]):
            if due <= until and self.armed.pop(handle, None) is not None:
                fn()


class Clock:
    def __init__(self, now: float = 0.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class Outlets:
    """What a keeper publishes and what it tells the service."""

    def __init__(self) -> None:
        self.published: list[ReasonerDecision] = []
        self.told: list[Report] = []

    def publish(self, key: str, decision: ReasonerDecision) -> None:
        assert key == topics.reasoner_decision("drone7")
        self.published.append(decision)

    def of(self, kind: type) -> list[Any]:
        return [r for r in self.told if isinstance(r, kind)]


def request(request_id: str, deadline_s: float = 1.0) -> ReasonerRequest:
    return ReasonerRequest(robot="drone7", request_id=request_id, deadline_s=deadline_s,
                           observation=Observation(robot="drone7", seq=1, task="land",
                                                   text="a quadrotor on the red box"),
                           options=OPTIONS)


def arrived(request_id: str, at: float, deadline_s: float = 1.0) -> Received[ReasonerRequest]:
    return Received(topics.reasoner_request("drone7"), request(request_id, deadline_s), at)


def answer(request_id: str, choice: int = 2) -> Answer:
    return Answer("drone7", ReasonerDecision(request_id=request_id, choice=choice,
                                             source="llm", latency_ms=1.0, model="m"))


def watched(listening_since: float | None = 0.0) -> Watched:
    return Watched(process=None, pulse=multiprocessing.get_context("spawn").RawValue("d", 0.0),
                   listening_since=listening_since)


# --------------------------------------------------------------------------- the keeper


def test_a_stopped_keeper_that_runs_again_sends_nothing_past_its_deadline() -> None:
    """The keeper was stopped with two fallbacks armed and runs again 3 s later: its timer
    fires both at once, 2 s past their deadlines. Neither leaves (the robot took its own
    fallback at K and ignores them; sent, one could displace the answer to its next
    question); the service is told each, how late. Before, both left, late."""
    out, timer, clock = Outlets(), HandTimer(), Clock(10.0)
    keeper = Keeper(SETTINGS, FallbackPolicy(), MARGIN_S, out.publish, out.told.append, timer,
                    clock=clock)
    keeper.arrived(arrived("a", 10.0))
    keeper.arrived(arrived("b", 10.0))
    clock.now = 13.0
    timer.fire(until=13.0)
    assert out.published == [] and keeper.armed == 0
    late = out.of(Late)
    assert [(x.decision.request_id, x.decision.source) for x in late] == [
        ("a", "timeout"), ("b", "timeout")]
    assert all(x.late_s == pytest.approx(2.0) for x in late)


def test_an_answer_past_its_deadline_is_dropped_and_one_by_it_leaves_stamped() -> None:
    out, timer, clock = Outlets(), HandTimer(), Clock(10.0)
    keeper = Keeper(SETTINGS, FallbackPolicy(), MARGIN_S, out.publish, out.told.append, timer,
                    clock=clock)
    keeper.arrived(arrived("fine", 10.0))
    clock.now = 10.99  # the fallback's timer woke 10 ms late: still by the deadline
    before = time.time()
    timer.fire(until=10.99)
    [fallback] = out.published
    assert fallback.latency_ms == pytest.approx(990.0) and fallback.stamp >= before
    out.published.clear()
    keeper.arrived(arrived("answered", 10.99))
    clock.now = 12.5  # the service's answer reaches a keeper past the deadline
    keeper.answered(answer("answered"))
    assert out.published == []
    assert out.of(Late)[-1].decision.request_id == "answered"
    assert [x.decision.request_id for x in out.of(Left)] == ["fine"]


# --------------------------------------------------------------------------- the standby


def standby(out: Outlets, timer: HandTimer, clock: Clock,
            keeper: Callable[[], Watched | None]) -> Standby:
    return Standby(SETTINGS, FallbackPolicy(), MARGIN_S, out.publish, out.told.append, timer,
                   keeper, clock=clock)


def test_the_standby_leaves_a_request_to_its_keeper_until_that_keeper_is_lost() -> None:
    """While the keeper that has a request is not lost, the standby sends nothing for it
    (its answer is held, its fallback's time passes quietly, the keeper's Left forgets
    it). Once the keeper is lost, the held answer leaves at once and the fallbacks at
    their deadlines."""
    out, timer, clock = Outlets(), HandTimer(), Clock(10.0)
    keeper = watched(listening_since=0.0)  # listening for long: requests reach it
    sb = standby(out, timer, clock, lambda: keeper)
    for name in ("answered", "quiet", "left", "pending"):
        sb.arrived(arrived(name, 10.0, deadline_s=1.0 if name == "quiet" else 3.0))
    assert len(out.of(Received)) == 4  # the service decides them (once: the worker)
    sb.answered(answer("answered"))
    sb.left("drone7", "left")
    clock.now = 11.0
    timer.fire(until=11.0)  # "quiet"'s deadline: the keeper sends it
    assert out.published == [] and sb.armed == 2
    keeper.lost = "stalled"
    assert sb.take_over(keeper) == 1
    [held] = out.published
    assert (held.request_id, held.source, held.choice) == ("answered", "llm", 2)
    clock.now = 12.99
    timer.fire(until=12.99)
    assert [(d.request_id, d.source) for d in out.published[1:]] == [("pending", "timeout")]
    assert [x.decision.request_id for x in out.of(Left)] == ["answered", "pending"]


def test_a_request_no_settled_keeper_has_is_the_standbys_unless_one_says_it_has_it() -> None:
    """No keeper, or one listening for less than SETTLE_S (its subscription may not have
    reached the robot yet): the standby sends, unless that keeper says it has the request
    (its Received: cover)."""
    out, timer, clock = Outlets(), HandTimer(), Clock(10.0)
    current: list[Watched | None] = [None]
    sb = standby(out, timer, clock, lambda: current[0])
    sb.arrived(arrived("nobody", 10.0))
    current[0] = keeper = watched(listening_since=10.0 - SETTLE_S / 2)
    sb.arrived(arrived("new keeper", 10.0))
    sb.arrived(arrived("covered", 10.0))
    sb.cover("drone7", "covered", keeper, until=11.0)
    clock.now = 10.99
    timer.fire(until=10.99)
    assert sorted(d.request_id for d in out.published) == ["new keeper", "nobody"]


def test_a_keepers_word_that_comes_before_the_standby_hears_the_request_still_counts() -> None:
    """Two Zenoh sessions hear a request at their own pace: the new keeper's Received can
    reach the service (its ``cover``) before the standby's own subscriber hears the same
    request. The standby must then leave it to that keeper: it sent the fallback too, and
    the robot got two decisions (CI, test_a_killed_keeper_leaves_no_request_unanswered:
    a request asked just after the SIGKILL, while the next keeper was settling). A word
    for a request that never reaches the standby is forgotten after its deadline."""
    out, timer, clock = Outlets(), HandTimer(), Clock(10.0)
    keeper = watched(listening_since=10.0 - SETTLE_S / 2)  # the next keeper, settling
    sb = standby(out, timer, clock, lambda: keeper)
    sb.cover("drone7", "told first", keeper, until=11.0)
    sb.arrived(arrived("told first", 10.0))
    sb.arrived(arrived("not told", 10.0))
    clock.now = 10.99
    timer.fire(until=10.99)
    assert [d.request_id for d in out.published] == ["not told"]
    for i in range(3):
        clock.now = 20.0 + i
        sb.cover("drone7", f"never heard {i}", keeper, until=clock.now + 1.0)
    assert sb.covered == 1  # the two past their deadline are gone
    keeper.lost = "exited"  # and a word from a keeper since lost counts for nothing
    sb.arrived(arrived("never heard 2", 22.0))
    clock.now = 22.99
    timer.fire(until=22.99)
    assert [d.request_id for d in out.published] == ["not told", "never heard 2"]


# --------------------------------------------------------------------------- the worker


class Conn:
    def __init__(self) -> None:
        self.sent: list[Any] = []

    def send(self, item: Any) -> None:
        self.sent.append(item)


async def test_the_worker_decides_a_request_once_whoever_told_of_it_first() -> None:
    """The keeper and the standby both tell of each request: it is decided once, and the
    one that tells of it after the decision gets the decision at once."""
    backend = Recording()
    worker = ReasonerWorker(Decider([backend], DeciderConfig()), SETTINGS)
    conn = Conn()
    worker._conn = conn  # type: ignore[assignment]
    keeper = watched()
    worker._from_standby(arrived("r1", time.monotonic(), deadline_s=5.0))
    worker.report(arrived("r1", time.monotonic(), deadline_s=5.0), keeper)
    assert len(worker._tasks) == 1
    await asyncio.gather(*worker._tasks)
    assert backend.calls == 1
    assert [(a.robot, a.decision.request_id, a.decision.choice) for a in conn.sent] == [
        ("drone7", "r1", 1)]
    worker.report(arrived("r1", time.monotonic(), deadline_s=5.0), keeper)  # told again
    assert backend.calls == 1 and len(conn.sent) == 2 and not worker._tasks


def test_the_standbys_zenoh_session_is_its_own() -> None:
    """One session per Zenoh ID at a router, and the keeper's listening endpoint is the
    next keeper's: the standby has an ID of its own and listens on none of the keeper's.
    A reasoner that connects nowhere (robots connect to it) gets no standby."""
    assert standby_id("ae5002") == "ae50025b"
    long = "a" * 31 + "0"
    assert standby_id(long) == "a" * 31 + "1" and len(standby_id(long)) == 32
    assert standby_id("f" * 32) == "f" * 31 + "0"
    deployed = standby_config(BusSettings(
        zenoh_config=Path("deploy/zenoh/clients/reasoner.json5"), zenoh_mode="client",
        zenoh_connect=["tcp/127.0.0.1:7447"]))
    assert deployed is not None and json.loads(deployed.get_json("id")) == "ae50025b"
    assert json.loads(deployed.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    peer = standby_config(BusSettings(zenoh_connect=["tcp/127.0.0.1:7447"],
                                      zenoh_listen=["tcp/127.0.0.1:7448"]))
    assert peer is not None
    assert json.loads(peer.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    assert standby_config(BusSettings(zenoh_listen=["tcp/127.0.0.1:7448"])) is None


def test_the_worker_listens_once_its_keeper_has_every_request_alone() -> None:
    """Until its keeper has listened for SETTLE_S, the standby also sends the decision of a
    request (the keeper may not have it): two decisions for one request. The worker (and
    so /readyz) says it listens only from then on (CI: a request sent as soon as it said
    so was decided, and counted, twice)."""
    worker = ReasonerWorker(Decider([Recording()], DeciderConfig()), SETTINGS)

    class Alive:
        def is_alive(self) -> bool:
            return True

    keeper = watched(listening_since=time.monotonic())
    keeper.process = Alive()
    worker._keeper = keeper
    assert not worker.listening
    keeper.listening_since = time.monotonic() - SETTLE_S
    assert worker.listening


def test_a_keeper_that_exited_unnoticed_leaves_its_deadlines_to_the_standby() -> None:
    """CI: a keeper SIGKILLed just before a request's deadline, noticed by the watchdog only
    after it (a loaded machine), left that request unanswered: the standby deferred to a
    keeper that no longer existed. A keeper whose process has exited is not deferred to."""
    out, timer, clock = Outlets(), HandTimer(), Clock(10.0)
    keeper = watched(listening_since=0.0)
    read, write = os.pipe()
    os.close(write)  # its sentinel is ready: the process has exited

    class Exited:
        sentinel = read

    keeper.process = Exited()
    try:
        sb = standby(out, timer, clock, lambda: keeper)
        sb.arrived(arrived("pending", 10.0))
        clock.now = 10.99
        timer.fire(until=10.99)  # its deadline, before the watchdog said the keeper is lost
        assert [(d.request_id, d.source) for d in out.published] == [("pending", "timeout")]
    finally:
        os.close(read)
