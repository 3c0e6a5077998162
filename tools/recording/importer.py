"""``aesop cache import``: a recorded nominal flight becomes a cache's experiences.

The paper built its cache by flying nominal circles and keeping what the detector
saw. A camera sees the same scene many times a second, so the observations are
taken once per distinct scene (text and detections): a hundred copies of one scene
would make every copy its neighbours' perfect match, and the leave-one-out
calibration (eq. 2) would then learn a threshold of nothing. Each scene gets an id
made from its content, so importing a recording twice (or two recordings of the
same flight) adds nothing the second time. Its metadata say where it came from; its
detections become the experience's (the cache's nominal detections). An import whose
window holds no observation is refused before the service is asked anything: no
empty cache is made, and a cache there is stays as it was.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.embedding.client import EmbeddingClient
from services.embedding.detector.proposals import scene_id
from shared.client import Progress, ServiceError

from .recorded import RecordedObservation, RecordingError, observations

Say = Callable[[str], None]
BATCH = 500  # items per add request (one job each, progress per batch)


@dataclass(frozen=True)
class Scene:
    """One distinct scene of a recording: its first observation and how often it was seen."""

    first: RecordedObservation
    seen: int

    @property
    def id(self) -> str:
        return scene_id(self.first.observation)

    def item(self) -> dict[str, Any]:
        """The experience to add (``POST /v1/caches/{name}/experiences``)."""
        obs = self.first.observation
        return {"text": obs.text, "id": self.id, "metadata": {
            "source": self.first.source, "robot": obs.robot, "seq": obs.seq, "stamp": obs.stamp,
            "task": obs.task, "seen": self.seen},
            "detections": [d.model_dump(exclude_none=True) for d in obs.detections]}


def distinct_scenes(recorded: Iterable[RecordedObservation]) -> list[Scene]:
    """The scenes in the order first seen, each with its count."""
    firsts: dict[str, RecordedObservation] = {}
    counts: dict[str, int] = {}
    for item in recorded:
        key = scene_id(item.observation)
        firsts.setdefault(key, item)
        counts[key] = counts.get(key, 0) + 1
    return [Scene(first, counts[key]) for key, first in firsts.items()]


@dataclass(frozen=True)
class Imported:
    observations: int  # in the window
    scenes: int  # distinct
    already: int  # scenes the cache had
    added: int
    size: int  # the cache's size after
    version: int


async def import_recording(client: EmbeddingClient, cache: str, paths: Sequence[Path], *,
                           robot: str | None = None, since: str | None = None,
                           until: str | None = None, model: str | None = None,
                           k: int | None = None, say: Say, progress: Progress | None = None
                           ) -> Imported:
    """Add the distinct scenes of the recordings (each in its window) that ``cache`` does
    not have yet (creating the cache with ``model`` and ``k`` if there is none)."""
    recorded: list[RecordedObservation] = []
    for path in paths:
        some = list(observations(path, robot=robot, since=since, until=until))
        say(f"{len(some)} observations, {len(distinct_scenes(some))} distinct scenes in "
            f"{path.name}")
        recorded += some
    if not recorded:  # before the service is asked anything: no empty cache made
        raise RecordingError(_nothing(paths, robot, since, until))
    scenes = distinct_scenes(recorded)
    try:
        info = await client.cache(cache)
    except ServiceError as exc:
        if exc.status != 404:
            raise
        info = await client.create_cache(cache, model=model, k=k)
        say(f"created cache {cache!r} (model {info.model})")
    new = [s for s in scenes if not await _has(client, cache, s.id)] if info.size else scenes
    added = 0
    size, version = info.size, info.version
    for batch in _batches(new, BATCH):
        done = await client.add_items(cache, [s.item() for s in batch],
                                      progress=progress)
        added += len(done.ids)
        size, version = done.size, done.version
        say(f"added {added} of {len(new)}")
    return Imported(len(recorded), len(scenes), len(scenes) - len(new), added, size, version)


def _nothing(paths: Sequence[Path], robot: str | None, since: str | None,
             until: str | None) -> str:
    """Why an import selected no observation, for the operator."""
    asked = " ".join(f"--{name} {value}" for name, value in (
        ("robot", robot), ("since", since), ("until", until)) if value is not None)
    where = ", ".join(p.name for p in paths)
    if not asked:
        return f"no observations in {where}: nothing to import, the cache is left as it was"
    return (f"no observations in {where} with {asked} (seconds count from each recording's "
            "first observation): nothing to import, the cache is left as it was")


async def _has(client: EmbeddingClient, cache: str, ident: str) -> bool:
    try:
        await client.experience(cache, ident)
    except ServiceError as exc:
        if exc.status == 404:
            return False
        raise
    return True


def _batches(items: Sequence[Scene], size: int) -> Iterable[Sequence[Scene]]:
    for i in range(0, len(items), size):
        yield items[i:i + size]
