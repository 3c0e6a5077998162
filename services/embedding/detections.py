"""Per-detection scores and their combination with the whole-observation score (pure).

An anomaly that is one odd object among nominal ones stays close to the nominal cache
as a whole observation: its embedding averages the odd object away. Scoring each of an
observation's detections against the distinct detections of the nominal experiences
finds it. The *detection score* of an observation is its worst detection's: minus the
cosine similarity of that detection to its nearest nominal detection (higher is more
anomalous, like the top-k score).

The two scores are one detector through conformal p-values: each score's p-value
against its own nominal calibration scores, ``p = (1 + #{s_cal >= s}) / (n + 1)``,
combined by Bonferroni, ``p = min(1, 2 min(p_obs, p_det))``. For a nominal
observation exchangeable with the calibration set, ``P(p_obs <= t) <= t`` for each
component, so ``P(p <= t) <= t``: flagging ``p <= 1 - alpha`` keeps the false-positive
rate at most ``1 - alpha``, the split-conformal guarantee of one detector. An
observation without detections has only ``p_obs`` (no correction): a text-only
observation is judged exactly as before.

Similarities are rounded to :data:`DECIMALS` places: the same phrase embedded in two
batches can differ in the seventh decimal, and a nominal detection seen again must tie
with its calibration scores, not score a hair above them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

DECIMALS = 4


@dataclass(frozen=True)
class NominalDetections:
    """The distinct detections of a nominal set: their unit vectors, and how many
    nominal observations hold each (a detection only one observation holds is left out
    of that observation's leave-one-out score)."""

    labels: tuple[str, ...]
    vectors: np.ndarray  # (m, d), unit rows
    counts: np.ndarray  # (m,) observations holding each


@dataclass(frozen=True)
class Worst:
    """An observation's worst detection: its score, which detection (index into the
    observation's list), its nearest nominal detection and their similarity."""

    score: float
    detection: int
    nearest: int  # index into NominalDetections.labels
    similarity: float


def distinct(per_observation: Sequence[Sequence[str]]) -> tuple[list[str], np.ndarray]:
    """The distinct detections in first-seen order, and in how many observations each is."""
    order: dict[str, int] = {}
    for labels in per_observation:
        for label in dict.fromkeys(labels):
            order[label] = order.get(label, 0) + 1
    return list(order), np.array(list(order.values()), dtype=np.int64)


def nearest(nominal: NominalDetections, vectors: np.ndarray,
            left_out: Sequence[int] = ()) -> tuple[np.ndarray, np.ndarray]:
    """Each detection's (``vectors``, unit rows) nearest nominal detection (index, -1 when
    all are left out) and their similarity, rounded (-inf when all are left out);
    ``left_out``: nominal detections not to match (leave-one-out)."""
    sims = (vectors @ nominal.vectors.T).astype(np.float64)
    if left_out:
        sims[:, list(left_out)] = -np.inf
    index = np.argmax(sims, axis=1)
    best = np.round(sims[np.arange(len(vectors)), index], DECIMALS)
    return np.where(np.isfinite(best), index, -1), best


def worst(nominal: NominalDetections, vectors: np.ndarray,
          left_out: Sequence[int] = ()) -> Worst | None:
    """The worst of an observation's detections (``vectors``, unit rows), None when it
    has none; ``left_out``: nominal detections not to match (leave-one-out)."""
    if len(vectors) == 0 or len(nominal.labels) == 0:
        return None
    index, best = nearest(nominal, vectors, left_out)
    which = int(np.argmin(best))
    if not np.isfinite(best[which]):  # every nominal detection left out
        return Worst(1.0, which, -1, -1.0)
    return Worst(float(-best[which]), which, int(index[which]), float(best[which]))


def loo_scores(nominal: NominalDetections, observations: Sequence[Sequence[int]],
               vectors: np.ndarray) -> np.ndarray:
    """Each nominal observation's detection score with what only it holds left out;
    ``observations`` lists each one's detections as indices into ``nominal.labels``
    (and rows of ``vectors``). NaN for an observation without detections."""
    out = np.full(len(observations), np.nan)
    for i, ids in enumerate(observations):
        if ids:
            own = [j for j in ids if nominal.counts[j] <= 1]
            got = worst(nominal, vectors[list(ids)], own)
            out[i] = got.score if got is not None else np.nan
    return out


def p_values(calibration: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Conformal p-values of ``scores`` against nominal ``calibration`` scores (NaN ones
    ignored): ``(1 + #{cal >= s}) / (n + 1)``; NaN stays NaN."""
    return p_values_sorted(np.sort(calibration[~np.isnan(calibration)]), scores)


def p_values_sorted(calibration: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """:func:`p_values` against calibration scores already sorted and without NaN (a
    cache's, kept so: sorting a million of them took 17 ms per verdict)."""
    above = len(calibration) - np.searchsorted(calibration, scores, side="left")
    p = (1.0 + above) / (len(calibration) + 1.0)
    return np.where(np.isnan(scores), np.nan, p)


def combined_p(p_observation: np.ndarray, p_detection: np.ndarray) -> np.ndarray:
    """Bonferroni over the two components; ``p_observation`` alone where an observation
    has no detection score (NaN)."""
    both = np.minimum(1.0, 2.0 * np.minimum(p_observation, p_detection))
    return np.where(np.isnan(p_detection), p_observation, both)
