"""The calibration policy: what each method needs and what it keeps (pure).

One policy for the service (``POST /v1/caches/{name}/calibrate``) and for offline evaluation
(``aesop detector eval``).

- ``loo-quantile`` (eq. 2) needs the members' leave-one-out scores; tau is their alpha
  quantile and they are kept as the nominal scores behind the p-values;
- ``conformal`` needs held-out nominal examples (a labelled set's nominal ones); tau is
  their conformal quantile and they are kept;
- ``tpr-target`` needs a labelled set with both classes; it keeps nothing (its verdicts
  are ``s > tau``) and takes no pairs.

A labelled set with both classes adds its AUROC. A calibration whose combined p-value could
never fall below ``1 - alpha`` is refused naming ``alpha`` (:meth:`CalibrationScores.check_power`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from .cache import Cache, CalibrationScores, Labelled, Scored
from .calibration import (
    Calibration,
    CalibrationError,
    Method,
    auroc,
    conformal,
    loo_quantile,
    tpr_target,
)
from .detections import floats
from .errors import InvalidInput

DEFAULT_ALPHA = 0.95
DEFAULT_TPR = 0.9


class Components(NamedTuple):
    """Nominal scores of each component, one per calibration example or member, NaN
    where it has none (raw: ``CalibrationScores.of`` sorts them and drops the NaN)."""

    observation: np.ndarray
    detection: np.ndarray
    pair: np.ndarray | None  # None: pairs not asked for


@dataclass(frozen=True)
class Evidence:
    """What a calibration is made from: the cache members' leave-one-out scores (for
    ``loo-quantile``) and a labelled set's scores with its labels (True: anomaly)."""

    loo: Components | None = None
    labelled: Components | None = None
    labels: np.ndarray | None = None

    @property
    def both_classes(self) -> bool:
        return self.labels is not None and bool(self.labels.any() and (~self.labels).any())


def loo_components(cache: Cache, *, pairs: bool, k: int | None = None) -> Components:
    """The members' leave-one-out scores of each component (``loo-quantile``'s evidence):
    the whole observation's at ``k`` (the cache's by default), the detections' where the
    cache has any, the pairs' if asked for."""
    return Components(cache.loo_scores(k),
                      cache.loo_detection_scores() if cache.has_detections else np.zeros(0),
                      cache.loo_pair_scores() if pairs else None)


def labelled_components(scored: Sequence[Scored], labelled: Sequence[Labelled], *,
                        pairs: bool) -> tuple[Components, np.ndarray]:
    """A labelled set's scores of each component (``scored``, one per item of
    ``labelled``) and its labels (True: anomaly)."""
    return (Components(np.array([r.score for r in scored]),
                       floats(r.detection_score for r in scored),
                       floats(r.pair_score for r in scored) if pairs else None),
            np.array([x.is_anomaly for x in labelled], dtype=bool))


def check(method: Method, pairs: bool) -> None:
    """Refuse what no evidence can make: pairs with ``tpr-target``."""
    if pairs and method == "tpr-target":
        raise InvalidInput("pairs are calibrated by loo-quantile or conformal, not "
                           "tpr-target", field="pairs")


# what each method needs beyond the cache (the module's docstring says why)
NEEDS_LABELLED: tuple[Method, ...] = ("conformal", "tpr-target")  # a labelled set


def needs_loo(method: Method) -> bool:
    """The members' leave-one-out scores: ``loo-quantile``."""
    return method not in NEEDS_LABELLED


def needs_labelled(method: Method) -> bool:
    """A labelled calibration set (``conformal``: its nominal lines; ``tpr-target``: both
    classes)."""
    return method in NEEDS_LABELLED


def threshold(method: Method, evidence: Evidence, *, alpha: float | None = None,
              tpr: float | None = None) -> Calibration:
    """Tau by ``method`` from ``evidence`` (InvalidInput naming what is missing)."""
    alpha = DEFAULT_ALPHA if alpha is None else alpha
    scores = None if evidence.labelled is None else evidence.labelled.observation
    labels = evidence.labels
    try:
        if method == "loo-quantile":
            if evidence.loo is None:
                raise ValueError("loo-quantile needs the members' leave-one-out scores")
            cal = loo_quantile(evidence.loo.observation, alpha)
        elif method == "conformal":
            if scores is None or labels is None or not (~labels).any():
                raise InvalidInput("conformal calibration needs held-out nominal examples",
                                   field="calibration")
            cal = conformal(scores[~labels], alpha)
        else:
            if scores is None or labels is None:
                raise InvalidInput("tpr-target calibration needs a labelled calibration set",
                                   field="calibration")
            return tpr_target(scores, labels, DEFAULT_TPR if tpr is None else tpr)
    except CalibrationError as exc:
        raise InvalidInput(str(exc), field=exc.field) from None
    if evidence.both_classes:
        assert scores is not None and labels is not None
        cal = replace(cal, auroc=auroc(scores, labels))
    return cal


def kept(cal: Calibration, evidence: Evidence, *, tests: int | None = None
         ) -> CalibrationScores | None:
    """The nominal scores behind ``cal``'s p-values: the leave-one-out scores of the
    components (loo-quantile) or the labelled set's nominal ones (conformal); None for
    tpr-target. Refused when the combined p-value could never flag (``tests``: the
    components combined, by default those kept)."""
    if cal.method == "loo-quantile" and evidence.loo is not None:
        scores = CalibrationScores.of(*evidence.loo)
    elif cal.method == "conformal" and evidence.labelled is not None \
            and evidence.labels is not None:
        nominal = ~evidence.labels
        part = evidence.labelled
        scores = CalibrationScores.of(part.observation[nominal], part.detection[nominal],
                                      None if part.pair is None else part.pair[nominal])
    else:
        return None
    if cal.alpha is not None:
        scores.check_power(cal.alpha, tests=tests)
    return scores


def calibrate(method: Method, evidence: Evidence, *, alpha: float | None = None,
              tpr: float | None = None, pairs: bool = False, tests: int | None = None
              ) -> tuple[Calibration, CalibrationScores | None]:
    """Tau and the nominal scores kept with it."""
    check(method, pairs)
    cal = replace(threshold(method, evidence, alpha=alpha, tpr=tpr), pairs=pairs)
    return cal, kept(cal, evidence, tests=tests)


__all__ = ["DEFAULT_ALPHA", "DEFAULT_TPR", "Components", "Evidence", "calibrate", "check",
           "kept", "labelled_components", "loo_components", "needs_labelled", "needs_loo",
           "NEEDS_LABELLED", "threshold"]
