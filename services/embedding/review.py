"""Scenes the slow reasoner let pass, proposed to a cache (:mod:`.proposals` holds the
pure rules): made or counted, accepted (the scene added as a nominal experience in the same
transaction as the proposal's new state) or rejected, each told to the listeners (the
worker publishes them as events)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

from shared.messages import Observation

from .entries import Entry, Item
from .errors import Conflict, NotFound
from .proposals import Proposal, State, scene_id

if TYPE_CHECKING:
    from .service import CacheService

log = logging.getLogger(__name__)


class Review:
    """The proposal workflow of the caches ``caches`` holds."""

    def __init__(self, caches: CacheService) -> None:
        self.caches = caches
        self.settings = caches.settings
        # called with each proposal made, counted, accepted or rejected
        self.listeners: list[Callable[[str, Proposal], None]] = []

    def list(self, name: str, state: State | None = None) -> list[Proposal]:
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
        transaction with the proposal's new state; the calibration goes stale."""
        entry = self.caches.entry(name)
        proposal = self._pending(entry, ident)
        config = entry.cache.config
        item = Item(text=proposal.text, id=ident, detections=proposal.detections, metadata={
            "proposal": {"robot": proposal.robot, "seq": proposal.seq, "count": proposal.count,
                         "request_id": proposal.request_id, "model": proposal.model}})
        vectors = await self.caches.vectors_for(config, [item], None)
        found = await self.caches.new_phrases(entry, item.detections)
        async with entry.writer:
            proposal = self._pending(entry, ident).decided("accepted", now)
            op = entry.cache.plan_add(vectors, ids=[ident], texts=[item.text],
                                      metadata=[item.metadata], detections=[item.detections],
                                      detection_vectors=found)
            await self.caches.commit(entry, op, proposal)
            entry.proposals[ident] = proposal
        self._tell("accepted", proposal)
        return proposal

    async def reject(self, name: str, ident: str, *, now: float) -> Proposal:
        entry = self.caches.entry(name)
        async with entry.writer:
            proposal = self._pending(entry, ident).decided("rejected", now)
            await asyncio.to_thread(self.caches.store.save_proposal, name, proposal)
            entry.proposals[ident] = proposal
        self._tell("rejected", proposal)
        return proposal

    def _pending(self, entry: Entry, ident: str) -> Proposal:
        proposal = entry.proposals.get(ident)
        if proposal is None:
            raise NotFound(f"no proposal {ident!r} on cache {entry.cache.name!r}", field="id")
        if proposal.state != "pending":
            raise Conflict(f"proposal {ident!r} is already {proposal.state}", field="id")
        return proposal

    def _tell(self, what: str, proposal: Proposal) -> None:
        for listener in self.listeners:
            try:
                listener(what, proposal)
            except Exception:
                log.exception("a proposal listener failed")
