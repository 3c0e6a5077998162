"""``aesop detector eval --recording``: a recorded flight's observations against a
detector of today, beside the verdicts they got when they were recorded.

:func:`compare` (pure) pairs each observation with its recorded verdict (by robot and
seq) and its new score, from :func:`scores_offline` (an in-memory cache built from a
nominal set) or :func:`scores_from_cache` (a running cache over REST, each scene with
its detections, judged as the live detector judges it). A scene (text and detections)
seen many times is scored once.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from services.embedding.client import EmbeddingClient
from services.embedding.detector.cache import Labelled
from services.embedding.detector.errors import InvalidInput
from services.embedding.detector.evaluation import (
    EvalConfig,
    fit,
    fit_structured,
    score_all,
    score_structured,
)
from services.embedding.models.base import Embedder
from shared.messages import AnomalyVerdict, Detection, Observation

from .recorded import RecordedObservation

SCORE_CHUNK = 256  # texts per score request: the service's default limit
Scene = tuple[str, tuple[Detection, ...]]  # an observation's text and detections


@dataclass(frozen=True)
class NewScore:
    score: float
    is_anomaly: bool | None  # None: the cache has no threshold


@dataclass(frozen=True)
class Rescored:
    robot: str
    seq: int
    t_s: float  # since the first observation compared
    text: str
    old: AnomalyVerdict | None  # what the detector said when it was recorded
    new: NewScore

    @property
    def changed(self) -> bool:
        return (self.old is not None and self.new.is_anomaly is not None
                and self.old.is_anomaly != self.new.is_anomaly)

    def row(self) -> dict[str, Any]:
        old = self.old
        return {"robot": self.robot, "seq": self.seq, "t_s": round(self.t_s, 3),
                "text": self.text,
                "old": None if old is None else {
                    "score": old.score, "threshold": old.threshold,
                    "is_anomaly": old.is_anomaly, "cache": old.cache,
                    "cache_version": old.cache_version, "model": old.model},
                "new": {"score": self.new.score, "is_anomaly": self.new.is_anomaly},
                "changed": self.changed}


def scene(obs: Observation) -> Scene:
    return obs.text, obs.detections


def distinct_scenes(recorded: Sequence[RecordedObservation]) -> list[Scene]:
    """Each scene once, in the order first seen: what to score."""
    return list(dict.fromkeys(scene(r.observation) for r in recorded))


def compare(recorded: Sequence[RecordedObservation],
            old: Mapping[tuple[str, int], AnomalyVerdict],
            new: Mapping[Scene, NewScore]) -> list[Rescored]:
    """One row per observation; ``new`` maps each distinct scene to its new score."""
    first = recorded[0].log_time_ns if recorded else 0
    return [Rescored(r.observation.robot, r.observation.seq, (r.log_time_ns - first) / 1e9,
                     r.observation.text, old.get((r.observation.robot, r.observation.seq)),
                     new[scene(r.observation)]) for r in recorded]


def summary(rows: Sequence[Rescored], threshold: float | None) -> dict[str, Any]:
    with_old = [r for r in rows if r.old is not None]
    return {
        "observations": len(rows),
        "with_recorded_verdict": len(with_old),
        "threshold": threshold,
        "anomalies_recorded": sum(r.old.is_anomaly for r in with_old if r.old is not None),
        "anomalies_now": sum(bool(r.new.is_anomaly) for r in rows),
        "changed": sum(r.changed for r in rows),
        "now_anomaly": sum(r.changed and bool(r.new.is_anomaly) for r in rows),
        "now_nominal": sum(r.changed and not r.new.is_anomaly for r in rows),
    }


def table(rows: Sequence[Rescored], *, only_changed: bool = False, width: int = 48) -> str:
    """One line per observation: when, the recorded and the new verdict, the scene;
    a ``*`` where they differ."""
    lines = [f"  {'t (s)':>8} {'seq':>6}  {'recorded':<18} {'now':<18} scene"]
    for r in rows:
        if only_changed and not r.changed:
            continue
        text = " / ".join(r.text.splitlines())  # one line per detection: one row here
        text = text if len(text) <= width else text[:width - 1] + "…"
        lines.append(f"{'*' if r.changed else ' '} {r.t_s:8.2f} {r.seq:>6}  "
                     f"{_verdict(r.old.score, r.old.is_anomaly) if r.old else '—':<18} "
                     f"{_verdict(r.new.score, r.new.is_anomaly):<18} {text}")
    return "\n".join(lines)


def _verdict(score: float, is_anomaly: bool | None) -> str:
    word = "no tau" if is_anomaly is None else "ANOMALY" if is_anomaly else "nominal"
    return f"{word} {score:.4f}"


def scores_offline(embedder: Embedder, nominal: Sequence[Labelled],
                   calibration: Sequence[Labelled], config: EvalConfig,
                   scenes: Sequence[Scene]) -> tuple[dict[Scene, NewScore], float, str]:
    """Each scene's score against a cache of ``nominal`` built in memory and calibrated
    by ``config``; with tau and the method's name. ``--score combined`` judges each scene
    with its detections as the service does (``detections`` alone is not a verdict the
    service gives: refused)."""
    if config.score == "detections":
        raise InvalidInput("--recording takes --score topk, mahalanobis or combined",
                           field="score")
    if config.score == "combined":
        cache, _ = fit_structured(embedder, nominal, calibration, config)
        scored = score_structured(cache, embedder, [
            Labelled(text, False, tuple(dict.fromkeys(d.phrase for d in found)))
            for text, found in scenes])
        cal = cache.calibration
        assert cal is not None
        return ({s: NewScore(r.score, r.is_anomaly) for s, r in zip(scenes, scored,
                                                                    strict=True)},
                cal.threshold, cal.method)
    cache, cal = fit(embedder, nominal, calibration, config)
    scores = score_all(cache, embedder, [text for text, _ in scenes], config.k)
    new = {s: NewScore(float(x), bool(x > cal.threshold))
           for s, x in zip(scenes, scores, strict=True)}
    return new, cal.threshold, cal.method


async def scores_from_cache(client: EmbeddingClient, cache: str, scenes: Sequence[Scene]
                            ) -> tuple[dict[Scene, NewScore], float | None, int]:
    """Each scene's score and verdict from a running cache; with its tau and version."""
    info = await client.cache(cache)
    new: dict[Scene, NewScore] = {}
    threshold = info.threshold
    for i in range(0, len(scenes), SCORE_CHUNK):
        chunk = scenes[i:i + SCORE_CHUNK]
        detections = [found for _, found in chunk] if any(f for _, f in chunk) else []
        got = await client.score(cache, [text for text, _ in chunk], detections=detections)
        threshold = got.threshold
        new |= {s: NewScore(r.score, r.is_anomaly)
                for s, r in zip(chunk, got.results, strict=True)}
    return new, threshold, info.version
