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

A third component is optional (a calibration asks for it): *pairs*. Two nominal objects
can be anomalous together (a person beside a running forklift), and neither component
above sees it. The *pair score* of an observation with two or more detections is its
worst pair's: minus the similarity of the pair to its nearest nominal pair (two
detections held together by one nominal observation), the similarity of two pairs being
the smaller of their members' (either order). With it, ``p = min(1, 3 min(p_obs, p_det,
p_pair))`` for every observation with detections (``p_pair`` counts only for one with a
pair: calibrated on nominal observations with two or more detections, it is valid for
such observations, so ``P(p_pair <= t/3) <= t/3`` overall and the bound holds). It only
helps where the nominal experiences show most nominal pairs (measured per domain in
``aesop bench detector --only kinds``).

Beyond every calibration score a conformal p-value is ``1/(n+1)`` for all: when a new
captioner's wording puts every frame there, the detector could no longer rank. There the
p-value goes on falling with the score, staying above ``1/(2(n+1))``, so it ranks and flags
exactly what the conformal one flags (:func:`p_values_sorted`). A phrase is embedded
without its leading article or count (:func:`embedded_form`: "the red box", "two red boxes"
and "a red box" mean one object); the phrase itself stays the label.

Similarities are rounded to :data:`~.scoring.DECIMALS` places, as the top-k score's are:
the same phrase embedded in two batches can differ in the seventh decimal, and a nominal
detection seen again must tie with its calibration scores, not score a hair above them.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from .scoring import DECIMALS


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


@dataclass(frozen=True)
class NominalPairs:
    """The distinct pairs of detections held together by a nominal observation, as
    indices into ``NominalDetections.labels`` (``first < second``), and how many
    observations hold each (a pair only one holds is left out of its leave-one-out
    score)."""

    first: np.ndarray  # (q,) int64
    second: np.ndarray  # (q,) int64
    counts: np.ndarray  # (q,)


@dataclass(frozen=True)
class WorstPair:
    """An observation's worst pair of detections (indices into its list), its nearest
    nominal pair (index into ``NominalPairs``, -1 when all are left out) and their
    similarity."""

    score: float
    detections: tuple[int, int]
    nearest: int
    similarity: float


def pairs_of(observations: Sequence[Sequence[int]]) -> NominalPairs:
    """The distinct pairs among each observation's detections (indices), with counts."""
    counts: dict[tuple[int, int], int] = {}
    for ids in observations:
        held = sorted(set(ids))
        for pos, a in enumerate(held):
            for b in held[pos + 1:]:
                counts[a, b] = counts.get((a, b), 0) + 1
    keys = list(counts)
    first = np.array([k[0] for k in keys], dtype=np.int64)
    second = np.array([k[1] for k in keys], dtype=np.int64)
    return NominalPairs(first, second, np.array(list(counts.values()), dtype=np.int64))


_LEADING = re.compile(r"^(?:(?:a|an|the|one|two|three|some|several)\s+)+", re.IGNORECASE)


def embedded_form(phrase: str) -> str:
    """What of a detection phrase is embedded: without its leading article or count, its
    spacing collapsed ("two  red boxes" -> "red boxes"), so that a captioner's "the red box"
    and "a red box" mean one object. The phrase itself stays the label."""
    text = " ".join(phrase.split())
    return _LEADING.sub("", text) or text


def similarities(nominal: NominalDetections, vectors: np.ndarray) -> np.ndarray:
    """Each detection's (``vectors``, unit rows) similarity to each nominal detection,
    rounded: (d, m)."""
    sims: np.ndarray = np.round((vectors @ nominal.vectors.T).astype(np.float64), DECIMALS)
    return sims


def worst_pair(pairs: NominalPairs, sims: np.ndarray,
               left_out: Sequence[int] = ()) -> WorstPair | None:
    """The worst pair of an observation's detections, given their :func:`similarities`
    (``sims``, one row per distinct detection); None with fewer than two detections or
    no nominal pair. ``left_out``: nominal pairs not to match (leave-one-out)."""
    if len(sims) < 2 or len(pairs.first) == 0:
        return None
    first, second = sims[:, pairs.first], sims[:, pairs.second]  # (d, q)
    worst: WorstPair | None = None
    for i in range(len(sims)):
        for j in range(i + 1, len(sims)):
            both = np.maximum(np.minimum(first[i], second[j]), np.minimum(first[j], second[i]))
            if left_out:
                both[list(left_out)] = -np.inf
            k = int(np.argmax(both))
            best = float(both[k])
            if not np.isfinite(best):  # every nominal pair left out
                return WorstPair(1.0, (i, j), -1, -1.0)
            if worst is None or -best > worst.score:
                worst = WorstPair(-best, (i, j), k, best)
    return worst


def loo_pair_scores(nominal: NominalDetections, pairs: NominalPairs,
                    observations: Sequence[Sequence[int]]) -> np.ndarray:
    """Each nominal observation's pair score with the pairs only it holds left out
    (``observations``: each one's detections as indices into ``nominal.labels``); NaN
    for one with fewer than two detections. A pair two observations hold matches itself
    (similarity 1), so only observations with a pair of their own are searched."""
    where = {(int(a), int(b)): k for k, (a, b) in enumerate(zip(pairs.first, pairs.second,
                                                                  strict=True))}
    out = np.full(len(observations), np.nan)
    for i, ids in enumerate(observations):
        held = sorted(set(ids))
        if len(held) < 2:
            continue
        own = [where[a, b] for p, a in enumerate(held) for b in held[p + 1:]
               if pairs.counts[where[a, b]] <= 1]
        if not own:
            out[i] = -1.0
            continue
        got = worst_pair(pairs, similarities(nominal, nominal.vectors[held]), own)
        out[i] = got.score if got is not None else np.nan
    return out


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


def floats(values: Iterable[float | None]) -> np.ndarray:
    """Scores as float64, None as NaN (a component an observation does not have)."""
    return np.array([np.nan if v is None else v for v in values], dtype=np.float64)


def p_values(calibration: np.ndarray, scores: np.ndarray,
             bound: float | None = 1.0) -> np.ndarray:
    """Conformal p-values of ``scores`` against nominal ``calibration`` scores (NaN ones
    ignored): ``(1 + #{cal >= s}) / (n + 1)``, ranked beyond them all as
    :func:`p_values_sorted` says; NaN stays NaN."""
    return p_values_sorted(np.sort(calibration[~np.isnan(calibration)]), scores, bound)


def p_values_sorted(calibration: np.ndarray, scores: np.ndarray,
                    bound: float | None = 1.0) -> np.ndarray:
    """:func:`p_values` against calibration scores already sorted and without NaN (a
    cache's, kept so: sorting a million of them took 17 ms per verdict).

    Beyond every calibration score the conformal p-value is ``1/(n+1)`` for all, and a
    detector seeing new wording cannot rank what it flags: there the p-value goes on
    falling with the score, ``(1 - g/2)/(n+1)``, ``g`` the score's way from the largest
    calibration score to the score's ``bound`` (1: a negated cosine similarity), in
    (0, 1] (``None``: an unbounded score, ``g = 1 - 1/(1 + excess)``). Every such p-value
    stays in ``[1/(2(n+1)), 1/(n+1))``, below any p-value of a score within the
    calibration set, so a threshold at or above ``1/(n+1)`` flags exactly what the
    conformal p-value flags: the false-positive bound is unchanged."""
    n = len(calibration)
    above = n - np.searchsorted(calibration, scores, side="left")
    p = (1.0 + above) / (n + 1.0)
    if n:
        top = float(calibration[-1])
        excess = np.maximum(np.nan_to_num(scores, nan=top) - top, 0.0)
        if bound is None or bound <= top:
            g = 1.0 - 1.0 / (1.0 + excess)
        else:
            g = np.minimum(excess / (bound - top), 1.0)
        p = np.where(above == 0, (1.0 - g / 2.0) / (n + 1.0), p)
    return np.where(np.isnan(scores), np.nan, p)


def combined_p(p_observation: np.ndarray, p_detection: np.ndarray,
               p_pair: np.ndarray | None = None) -> np.ndarray:
    """Bonferroni over the components: two, or three when ``p_pair`` is given (the
    calibration has pair scores), whether or not an observation has a pair (NaN: none);
    ``p_observation`` alone where an observation has no detection score (NaN)."""
    if p_pair is None:
        least = np.minimum(p_observation, p_detection)
        tests = 2.0
    else:
        least = np.fmin(np.minimum(p_observation, p_detection), p_pair)
        tests = 3.0
    return np.where(np.isnan(p_detection), p_observation, np.minimum(1.0, tests * least))
