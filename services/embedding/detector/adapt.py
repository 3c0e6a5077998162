"""Re-learning from reviewed scenes with a false-positive promise that holds again (pure).

When a captioner changes its wording, every frame looks new; a person (or the reasoner,
under the ``auto`` policy) accepts scenes in the new wording as nominal, and the cache
learns them. Its calibration, though, still describes the old wording: kept as it was, its
scores are those of a wording the robot no longer sees; mixed with the new, the
false-positive promise holds for neither.

Under the policy ``window`` (the default), the calibration is recomputed after every
acceptance (a batch review: once after the batch) from the ``window`` most recently
accepted scenes alone: each one's leave-one-out scores against the cache as it now is
(:meth:`.Cache.loo_members`, the scores eq. 2 calibrates on, for those scenes only),
split-conformal at the calibration's own alpha, with pairs if it had them: a calibration of
the wording the robot sees now. Until the window holds enough scenes to ever flag
(``tests/(n+1) < 1 - alpha``, 40 at alpha 0.95 with detections, 60 with pairs) the
calibration is kept and marked stale, as under the policy ``stale`` (which never
recalibrates on its own).

The price: the scenes a person accepts were flagged first, so in a steady wording the
window holds the hardest nominal scenes, and its threshold sits higher than a calibration
on all of them would (fewer false alarms, and fewer true ones). ``stale`` keeps the
operator's calibration until they recalibrate. docs/embedding.md says when to choose which.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from .cache import Cache, SetCalibration
from .errors import DetectorError
from .policy import Components, Evidence, calibrate

Recalibrate = Literal["window", "stale"]

DEFAULT_WINDOW = 100  # accepted scenes the policy "window" calibrates on
ACCEPTED = "proposal"  # the metadata key an accepted scene's experience carries


def window(cache: Cache, size: int) -> list[int]:
    """The labels of the ``size`` most recently accepted scenes, oldest first."""
    found = [label for label, e in sorted(cache.experiences.items()) if ACCEPTED in e.metadata]
    return found[-size:] if size else []


def recalibration(cache: Cache, size: int) -> SetCalibration | None:
    """The calibration of the ``size`` most recently accepted scenes, split-conformal at the
    current calibration's alpha (pairs if it had them); None when there is nothing to
    recalibrate (no calibration with an alpha) or the window is too short to ever flag."""
    current = cache.calibration
    if current is None or current.alpha is None or current.method == "tpr-target":
        return None
    labels = window(cache, size)
    if not labels:
        return None
    # the accepted scenes as a held-out nominal set, calibrated as the service calibrates one
    evidence = Evidence(None, Components(*cache.loo_members(labels, pairs=current.pairs)),
                        np.zeros(len(labels), dtype=bool))
    try:
        cal, scores = calibrate("conformal", evidence, alpha=current.alpha,
                                pairs=current.pairs)
    except DetectorError:  # too few scenes yet to ever flag
        return None
    return cache.plan_calibration(cal, scores)
