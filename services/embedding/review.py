"""The proposal workflow: scenes the slow reasoner let pass, proposed to a cache and reviewed.

A proposal (:mod:`.detector.proposals` holds the pure rules) is made or counted, accepted
(the scene added as a nominal experience in the same transaction as the proposal's new
state) or rejected, each told to the listeners (the worker publishes them as events)."""

from __future__ import annotations

import asyncio
import builtins
import logging
from collections.abc import Callable, Sequence
from contextlib import AbstractAsyncContextManager
from typing import Literal, Protocol

import numpy as np

from shared.jobs import Job
from shared.messages import Detection, Observation

from .detector.adapt import ACCEPTED, recalibration
from .detector.cache import CacheConfig, Op, SetCalibration
from .detector.errors import Conflict, InvalidInput, NotFound
from .detector.proposals import Proposal, State, scene_id
from .entries import Entry
from .schemas import Item
from .settings import EmbeddingSettings
from .storage.pgstore import PostgresStore
from .storage.store import Store

log = logging.getLogger(__name__)

Decided = Literal["accepted", "rejected"]


class Reviewed(Protocol):
    """What the proposal workflow needs of the cache service: its caches, its store, the
    vectors of a scene and the writer's lock and commit."""

    settings: EmbeddingSettings

    @property
    def store(self) -> Store | PostgresStore: ...

    def entry(self, name: str) -> Entry: ...

    async def vectors_for(self, config: CacheConfig, items: Sequence[Item], job: Job | None
                          ) -> np.ndarray: ...

    async def new_phrases(self, entry: Entry, detections: Sequence[Detection]
                          ) -> dict[str, np.ndarray]: ...

    def writing(self, entry: Entry) -> AbstractAsyncContextManager[None]: ...

    async def commit(self, entry: Entry, op: Op, proposal: Proposal | None = None
                     ) -> None: ...


class Review:
    """The proposal workflow of the caches ``caches`` holds."""

    def __init__(self, caches: Reviewed) -> None:
        self.caches = caches
        self.settings = caches.settings
        # called with each proposal made, counted, accepted or rejected
        self.listeners: list[Callable[[str, Proposal], None]] = []

    def list(self, name: str, state: State | None = None) -> builtins.list[Proposal]:
        entry = self.caches.entry(name)
        return [p for p in entry.proposals.values() if state is None or p.state == state]

    async def propose(self, name: str, obs: Observation, *, request_id: str, model: str,
                      rationale: str, score: float, p_value: float | None,
                      now: float) -> Proposal | None:
        """The slow reasoner answered "continue" for ``obs``, which this detector flagged:
        propose the scene to cache ``name`` (counted if it was proposed before; accepted at
        once under the policy ``auto``, unless its ``flag`` says a person must decide).
        None when the cache holds the scene already, or has ``max_pending_proposals``
        pending and this one is new."""
        entry = self.caches.entry(name)
        ident = scene_id(obs)
        async with entry.writer:
            if ident in entry.cache.labels_by_id:
                return None
            known = entry.proposals.get(ident)
            if known is not None and known.state == "accepted":
                known = None  # its experience was deleted since: propose it afresh
            if known is None:
                pending = sum(p.state == "pending" for p in entry.proposals.values())
                if pending >= self.settings.limits.max_pending_proposals:
                    log.warning("cache %s: %d proposals pending "
                                "(AESOP_EMBEDDING_LIMITS__MAX_PENDING_PROPOSALS): %s not proposed",
                                name, pending, ident)
                    return None
            proposal = known.again(now) if known is not None else Proposal.first(
                obs, request_id=request_id, model=model, rationale=rationale, score=score,
                p_value=p_value, now=now)
            await asyncio.to_thread(self.caches.store.save_proposal, name, proposal)
            entry.proposals[ident] = proposal
        self._tell("proposed", proposal)
        if proposal.state == "pending" and entry.cache.config.proposals == "auto":
            if proposal.flag is not None:  # a person decides, whatever the policy
                log.warning("cache %s: %s not accepted on its own (%s): it waits for a "
                            "person", name, ident, proposal.flag)
                return proposal
            return await self.accept(name, ident, now=now)
        return proposal

    async def accept(self, name: str, ident: str, *, now: float) -> Proposal:
        """Add a pending proposal's scene as a nominal experience (id = the scene's): one
        transaction with the proposal's new state; then the calibration by the policy
        ``AESOP_EMBEDDING_ADAPT__RECALIBRATE`` (:mod:`.detector.adapt`)."""
        self._pending(self.caches.entry(name), ident)  # an error names "id"
        return (await self.decide_many(name, [ident], "accepted", now=now))[0]

    async def reject(self, name: str, ident: str, *, now: float) -> Proposal:
        self._pending(self.caches.entry(name), ident)
        return (await self.decide_many(name, [ident], "rejected", now=now))[0]

    async def decide_many(self, name: str, idents: Sequence[str], state: Decided, *,
                          now: float) -> builtins.list[Proposal]:
        """Accept or reject pending proposals in the order given (a batch review). Every
        id is checked first (unknown: NotFound, decided: Conflict, twice: InvalidInput,
        each naming ``ids[n]``), so a batch with a bad id changes nothing; the calibration
        follows the batch once."""
        entry = self.caches.entry(name)
        for n, ident in enumerate(idents):
            self._pending(entry, ident, field=f"ids[{n}]")
            if ident in idents[:n]:
                raise InvalidInput(f"proposal {ident!r} is named twice", field=f"ids[{n}]")
        done: builtins.list[Proposal] = []
        try:
            for ident in idents:
                done.append(await (self._accept(entry, ident, now) if state == "accepted"
                                   else self._reject(entry, ident, now)))
        finally:  # what was decided is told, and calibrated on, even if a later one failed
            for proposal in done:
                self._tell(state, proposal)
            if state == "accepted" and done:
                await self._recalibrate(entry)
        return done

    async def _accept(self, entry: Entry, ident: str, now: float) -> Proposal:
        proposal = self._pending(entry, ident)
        config = entry.cache.config
        item = Item(text=proposal.text, id=ident, detections=proposal.detections, metadata={
            ACCEPTED: {"robot": proposal.robot, "seq": proposal.seq, "count": proposal.count,
                         "request_id": proposal.request_id, "model": proposal.model}})
        vectors = await self.caches.vectors_for(config, [item], None)
        found = await self.caches.new_phrases(entry, item.detections)
        async with self.caches.writing(entry):
            proposal = self._pending(entry, ident).decided("accepted", now)
            op = entry.cache.plan_add(vectors, ids=[ident], texts=[item.text],
                                      metadata=[item.metadata], detections=[item.detections],
                                      detection_vectors=found)
            await self.caches.commit(entry, op, proposal)
            entry.proposals[ident] = proposal
        return proposal

    async def _recalibrate(self, entry: Entry) -> None:
        adapt = self.settings.adapt
        if adapt.recalibrate != "window":
            return
        async with self.caches.writing(entry):
            op = await asyncio.to_thread(self._planned, entry, adapt.window)
            if op is not None:
                await self.caches.commit(entry, op)
                log.info("cache %s recalibrated on its %d most recently accepted scenes",
                         entry.cache.name, op.calibration.n)

    @staticmethod
    def _planned(entry: Entry, size: int) -> SetCalibration | None:
        with entry.rw.read():
            return recalibration(entry.cache, size)

    async def _reject(self, entry: Entry, ident: str, now: float) -> Proposal:
        async with entry.writer:
            proposal = self._pending(entry, ident).decided("rejected", now)
            await asyncio.to_thread(self.caches.store.save_proposal, entry.cache.name,
                                    proposal)
            entry.proposals[ident] = proposal
        return proposal

    @staticmethod
    def _pending(entry: Entry, ident: str, field: str = "id") -> Proposal:
        proposal = entry.proposals.get(ident)
        if proposal is None:
            raise NotFound(f"no proposal {ident!r} on cache {entry.cache.name!r}", field=field)
        if proposal.state != "pending":
            raise Conflict(f"proposal {ident!r} is already {proposal.state}", field=field)
        return proposal

    def _tell(self, what: str, proposal: Proposal) -> None:
        for listener in self.listeners:
            try:
                listener(what, proposal)
            except Exception:
                log.exception("a proposal listener failed")
