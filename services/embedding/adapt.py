"""Re-learning from reviewed scenes with a false-positive promise that holds again (pure).

When a captioner changes its wording, every frame looks new; a person (or the reasoner,
under the ``auto`` policy) accepts scenes in the new wording as nominal, and the cache
learns them. Its calibration, though, still describes the old wording: kept as it was, its
scores are those of a wording the robot no longer sees; mixed with the new, the
false-positive promise holds for neither.

So each accepted scene is scored against the cache *before* it is added (its *held-out*
scores, kept in the experience's metadata under :data:`HELD_OUT`), which is exactly a
split-conformal calibration score of the cache as it then was. Under the policy
``window`` (the default), the calibration is recomputed after every acceptance from the
held-out scores of the ``window`` most recently accepted scenes, split-conformal at the
calibration's own alpha (with pairs if it had them): a calibration of the wording the
robot sees now. Each score was taken against a cache that held fewer of the new scenes
than today's, so it is at least today's score: the promise is kept, conservatively. Until
the window holds enough scenes to ever flag (``tests/(n+1) < 1 - alpha``, 40 at alpha 0.95
with detections) the calibration is kept and marked stale, as under the policy ``stale``
(which never recalibrates on its own).

The price: the scenes a person accepts were flagged first, so in a steady wording the
window holds the hardest nominal scenes, and its threshold sits higher than a calibration
on all of them would (fewer false alarms, and fewer true ones). ``stale`` keeps the
operator's calibration until they recalibrate. docs/embedding.md says when to choose which.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np

from .cache import Cache, Calibrate, Scored
from .calibration import Calibration, conformal
from .errors import InvalidInput
from .policy import Components, Evidence, kept

Recalibrate = Literal["window", "stale"]

DEFAULT_WINDOW = 100  # accepted scenes the policy "window" calibrates on
HELD_OUT = "held_out"  # the experience metadata key of an accepted scene's held-out scores


def held_out(scored: Scored) -> dict[str, float | None]:
    """What an accepted scene's metadata keeps of its score against the cache without it."""
    return {"observation": scored.score, "detection": scored.detection_score,
            "pair": scored.pair_score}


def window(cache: Cache, size: int) -> list[Mapping[str, Any]]:
    """The held-out scores of the ``size`` most recently accepted scenes, oldest first."""
    found = [e.metadata[HELD_OUT] for _, e in sorted(cache.experiences.items())
             if isinstance(e.metadata.get(HELD_OUT), Mapping)]
    return found[-size:] if size else []


def recalibration(cache: Cache, size: int) -> Calibrate | None:
    """The calibration of the ``size`` most recent accepted scenes, split-conformal at the
    current calibration's alpha (pairs if it had them); None when there is nothing to
    recalibrate (no calibration with an alpha) or the window is too short to ever flag."""
    current = cache.calibration
    if current is None or current.alpha is None or current.method == "tpr-target":
        return None
    scores = window(cache, size)
    if not scores:
        return None
    alpha, pairs = current.alpha, current.pairs

    def column(key: str) -> np.ndarray:
        return np.array([math.nan if s.get(key) is None else float(s[key]) for s in scores])

    part = Components(column("observation"), column("detection"),
                      column("pair") if pairs else None)
    labels = np.zeros(len(scores), dtype=bool)
    evidence = Evidence(None, part, labels)
    try:
        tau = conformal(part.observation, alpha)
        cal = Calibration("conformal", tau.threshold, alpha, tau.n, fpr=tau.fpr, pairs=pairs)
        kept_scores = kept(cal, evidence) if cache.has_detections else None
    except (InvalidInput, ValueError):  # too few scenes yet to ever flag at this alpha
        return None
    return cache.plan_calibration(cal, kept_scores)
