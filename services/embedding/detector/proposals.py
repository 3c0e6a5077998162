"""Proposals: flagged scenes the slow reasoner answered "continue" for, offered to a cache.

The paper leaves it to future work: when the LLM judges an observation the detector
flagged to be safe to continue through, that observation is evidence of nominal
operation the cache did not hold. Here it becomes a *proposal* on the detector's cache,
one per distinct scene (text and detections, :func:`scene_id`) with a count of how often
it was proposed. Under the cache's policy ``review`` (the default) an operator accepts
or rejects it; under ``auto`` it is accepted at once, unless its text, task or a detection
trips or nearly trips the injection tripwire (``flag``: a sign in the camera's view can
talk the LLM into "continue"; such a scene waits for a person under either policy).
Accepting adds the scene as a
nominal experience (a versioned add like any other, id = the scene's id, so accepting
twice or importing the same scene from a recording adds it once).

What the calibration does then is the service's policy (:mod:`.adapt`): under ``window``
(the default) it is recomputed on the most recently accepted scenes once there are enough
to flag; under ``stale`` it is kept and marked stale, not refreshed: an added nominal
experience can only lower later scores (a new neighbour raises the top-k similarity; a
new nominal detection raises the nearest-detection similarity), so the kept calibration
scores give p-values at least as large as a refreshed calibration's would: the
false-positive bound still holds, and the operator recalibrates when the stale flag says
so.

Only an LLM's answer makes a proposal (never a fallback), only for an observation the
detector itself flagged, and only for a request that offered "continue": the worker
checks all three (:mod:`services.embedding.worker`). Pure: the upsert and the state
changes; the store keeps them.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, replace
from typing import Any, Literal

from shared.injection import wary
from shared.messages import Detection, Observation

Policy = Literal["review", "auto"]
State = Literal["pending", "accepted", "rejected"]


def scene_id(obs: Observation) -> str:
    """The same text with the same detections has the same id, wherever it was seen
    (a recording's import, a proposal)."""
    content = json.dumps([obs.text, [d.model_dump() for d in obs.detections]],
                         sort_keys=True)
    return "rec-" + hashlib.sha256(content.encode()).hexdigest()[:24]


@dataclass(frozen=True)
class Proposal:
    """A scene proposed as nominal, with where it came from the first time."""

    id: str
    text: str
    detections: tuple[Detection, ...]
    task: str
    robot: str
    seq: int  # the flagged observation's, first time
    request_id: str
    model: str  # the LLM that answered "continue"
    rationale: str
    score: float  # the detector's score of it, first time
    p_value: float | None
    count: int
    first_at: float
    last_at: float
    state: State = "pending"
    decided_at: float | None = None
    # why a person must decide it (the scene trips, or nearly trips, the injection
    # tripwire: shared.injection.wary); never accepted on its own when set
    flag: str | None = None

    @classmethod
    def first(cls, obs: Observation, *, request_id: str, model: str, rationale: str,
              score: float, p_value: float | None, now: float) -> Proposal:
        return cls(id=scene_id(obs), text=obs.text, detections=obs.detections, task=obs.task,
                   robot=obs.robot, seq=obs.seq, request_id=request_id, model=model,
                   rationale=rationale, score=score, p_value=p_value, count=1, first_at=now,
                   last_at=now, flag=wary(obs.text, obs.task,
                                          *(d.phrase for d in obs.detections)))

    def again(self, now: float) -> Proposal:
        """Proposed once more: counted, whatever its state."""
        return replace(self, count=self.count + 1, last_at=now)

    def decided(self, state: State, now: float) -> Proposal:
        return replace(self, state=state, decided_at=now)

    def detail(self) -> dict[str, Any]:
        """What the store keeps beside the state and the counts (JSON)."""
        return {"text": self.text, "detections": [d.model_dump(exclude_none=True)
                                                  for d in self.detections],
                "task": self.task, "robot": self.robot, "seq": self.seq,
                "request_id": self.request_id, "model": self.model,
                "rationale": self.rationale, "score": self.score, "p_value": self.p_value,
                "flag": self.flag}

    @classmethod
    def stored(cls, ident: str, state: State, count: int, first_at: float, last_at: float,
               decided_at: float | None, detail: dict[str, Any]) -> Proposal:
        found = tuple(Detection(**d) for d in detail.pop("detections"))
        return cls(id=ident, detections=found, count=count, first_at=first_at,
                   last_at=last_at, state=state, decided_at=decided_at, **detail)
