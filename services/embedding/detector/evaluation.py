"""Offline evaluation of the fast anomaly detector on labelled text sets.

``aesop detector eval`` builds an in-memory cache from nominal texts, calibrates
tau with the chosen method, scores a labelled test set and reports AUROC and
the confusion-matrix rates at tau. Nothing is written to disk.

``--score detections`` and ``combined`` use each line's ``detections``
(:mod:`services.embedding.detector.detections`): the worst detection against the nominal
set's distinct detections, alone or combined with the whole-observation top-k score
(and, with ``--pairs``, the worst pair of detections) through conformal p-values
(Bonferroni), judged by the service's own cache (``Cache.judge``). Their scores are
``1 - p`` and tau is ``alpha``: an observation is flagged when ``p < 1 - alpha``.

``--adapt FILE`` accepts FILE's nominal lines as reviewed scenes before the test, as the
service accepts one batch review (:func:`accept`, :mod:`.adapt`).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from shared.messages import Detection

from ..models.base import Embedder
from .adapt import ACCEPTED, DEFAULT_WINDOW, Recalibrate, recalibration
from .cache import (
    Cache,
    CacheConfig,
    CalibrationScores,
    Detections,
    Labelled,
    Scored,
    ScoreKind,
    unit_vectors,
)
from .calibration import Calibration, Method, auroc, binary_metrics
from .detections import distinct, embedded_form, floats, p_values_sorted
from .errors import InvalidInput
from .policy import (
    DEFAULT_ALPHA,
    DEFAULT_TPR,
    Components,
    Evidence,
    labelled_components,
    loo_components,
    needs_loo,
    threshold,
)
from .policy import calibrate as calibrate_with

EvalScore = Literal["topk", "mahalanobis", "detections", "combined"]


@dataclass(frozen=True)
class EvalConfig:
    k: int = 5
    alpha: float = DEFAULT_ALPHA
    method: Method = "loo-quantile"
    score: EvalScore = "topk"
    tpr: float = DEFAULT_TPR  # the target of "tpr-target" (the hardware appendix uses 0.9)
    pairs: bool = False  # "combined" with pairs of detections as a third component
    recalibrate: Recalibrate = "window"  # the service's policy after accepted scenes
    window: int = DEFAULT_WINDOW  # accepted scenes the policy "window" calibrates on


def read_jsonl(path: Path) -> list[Labelled]:
    """Lines ``{"text": ..., "label": "nominal"|"anomaly", "detections"?: [...]}``, a
    detection a string or ``{"label", "where"?}``; errors name file and line."""
    out = []
    with open(path, encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, 1):
            if not line.strip():
                continue
            try:
                row = json.loads(line)
                text, label = row["text"], row.get("label", "nominal")
            except (json.JSONDecodeError, KeyError, TypeError) as exc:
                raise InvalidInput(f"{path}:{lineno}: expected a JSON object with 'text' "
                                   f"and 'label' ({exc})", field=str(path)) from None
            if label not in ("nominal", "anomaly") or not isinstance(text, str) or not text:
                raise InvalidInput(f"{path}:{lineno}: 'label' must be nominal|anomaly and "
                                   "'text' a non-empty string", field=str(path))
            out.append(Labelled(text, label == "anomaly",
                                _detections(row.get("detections"), path, lineno)))
    if not out:
        raise InvalidInput(f"{path} has no examples", field=str(path))
    return out


def _detections(value: Any, path: Path, lineno: int) -> tuple[str, ...]:
    if value is None:
        return ()
    wrong = InvalidInput(f"{path}:{lineno}: 'detections' must be a list of strings or of "
                         "{\"label\", \"where\"} objects", field=str(path))
    if not isinstance(value, list):
        raise wrong
    out = []
    for item in value:
        if isinstance(item, str):
            out.append(item)
        elif isinstance(item, dict) and isinstance(item.get("label"), str):
            where = item.get("where")
            out.append(Detection.model_construct(
                label=item["label"], where=where if isinstance(where, str) else None).phrase)
        else:
            raise wrong
    return tuple(d for d in out if d.strip())


def build_cache(vectors: np.ndarray, config: EvalConfig, model: str | None) -> Cache:
    kind: ScoreKind = "mahalanobis" if config.score == "mahalanobis" else "topk"
    cache = Cache(CacheConfig("eval", model, vectors.shape[1], config.k, kind))
    n = len(vectors)
    cache.apply(cache.plan_add(vectors, ids=[str(i) for i in range(n)], texts=[None] * n,
                               metadata=[{}] * n))
    return cache


def calibrate(cache: Cache, config: EvalConfig, cal_scores: np.ndarray | None,
              cal_labels: np.ndarray | None) -> Calibration:
    """Tau of a text-only cache by the service's policy (:mod:`.policy`)."""
    loo = loo_components(cache, pairs=False, k=config.k) if needs_loo(config.method) else None
    labelled = None if cal_scores is None else Components(cal_scores, np.zeros(0), None)
    try:
        return threshold(config.method, Evidence(loo, labelled, cal_labels),
                         alpha=config.alpha, tpr=config.tpr)
    except InvalidInput as exc:
        if exc.field == "calibration":
            raise InvalidInput(f"--method {config.method} needs --calibration ({exc})",
                               field="calibration") from None
        raise


def evaluate(
    embedder: Embedder,
    nominal: Sequence[Labelled],
    test: Sequence[Labelled],
    calibration: Sequence[Labelled] = (),
    config: EvalConfig = EvalConfig(),
    adapt: Sequence[Labelled] = (),
) -> dict[str, Any]:
    """Build, calibrate, accept the nominal ``adapt`` scenes in order as the service
    accepts reviewed scenes (:func:`accept`), test; the ``aesop detector eval --json``
    object."""
    if config.score in ("detections", "combined"):
        return evaluate_structured(embedder, nominal, test, calibration, config, adapt)
    cache, cal = fit(embedder, nominal, calibration, config)
    if adapt:
        cache.apply(cache.plan_calibration(cal))
        accept(cache, embedder, adapt, config)
        assert cache.calibration is not None
        cal = cache.calibration
    scores = score_all(cache, embedder, [x.text for x in test], config.k)
    labels = np.array([x.is_anomaly for x in test])
    return report(cal, scores, labels, config, embedder.name, len(nominal),
                  len(calibration)) | _adapted(cache, adapt, config)


def accept(cache: Cache, embedder: Embedder, scenes: Sequence[Labelled],
           config: EvalConfig) -> None:
    """The nominal scenes of ``scenes`` accepted in order, as the service accepts one batch
    review of them (:mod:`.adapt`): each added, marked accepted; then the calibration by
    ``config.recalibrate`` (the window's leave-one-out scores depend on the cache after
    the batch alone, so one batch or one review per scene ends the same)."""
    for n, scene in enumerate(x for x in scenes if not x.is_anomaly):
        held = tuple(Detection.model_construct(label=d, where=None) for d in scene.detections)
        new = [p for p in dict.fromkeys(scene.detections) if p not in cache.detection_vectors]
        cache.apply(cache.plan_add(
            embedder.embed([scene.text]), ids=[f"adapt-{n}"], texts=[scene.text],
            metadata=[{ACCEPTED: {"adapt": n}}], detections=[held],
            detection_vectors=phrase_vectors(embedder, new)))
    if scenes and config.recalibrate == "window":  # as after one batch review of them all
        op = recalibration(cache, config.window)
        if op is not None:
            cache.apply(op)


def _adapted(cache: Cache, adapt: Sequence[Labelled], config: EvalConfig) -> dict[str, Any]:
    if not adapt:
        return {}
    cal = cache.calibration
    return {"adapted": sum(not x.is_anomaly for x in adapt), "recalibrate": config.recalibrate,
            "window": config.window, "calibrated_on": None if cal is None else cal.n,
            "stale": cache.stale}


def phrase_vectors(embedder: Embedder, phrases: Sequence[str]) -> dict[str, np.ndarray]:
    """Unit vectors of detection phrases, as the service embeds them (:func:`embedded_form`)."""
    if not phrases:
        return {}
    rows = embedder.embed([embedded_form(p) for p in phrases])
    return dict(zip(phrases, unit_vectors(rows), strict=True))


def fit(embedder: Embedder, nominal: Sequence[Labelled],
        calibration: Sequence[Labelled] = (), config: EvalConfig = EvalConfig()
        ) -> tuple[Cache, Calibration]:
    """An in-memory cache of ``nominal`` and its tau by ``config.method``."""
    if any(x.is_anomaly for x in nominal):
        raise InvalidInput("the nominal set contains anomalies", field="nominal")
    cache = build_cache(embedder.embed([x.text for x in nominal]), config, embedder.name)
    cal_scores = cal_labels = None
    if calibration:
        cal_scores = score_all(cache, embedder, [x.text for x in calibration], config.k)
        cal_labels = np.array([x.is_anomaly for x in calibration])
    return cache, calibrate(cache, config, cal_scores, cal_labels)


def score_all(cache: Cache, embedder: Embedder, texts: Sequence[str], k: int) -> np.ndarray:
    vectors = embedder.embed(list(texts))
    return np.array([r.score for r in cache.score(vectors, k, neighbors=0)])


def report(cal: Calibration, scores: np.ndarray, labels: np.ndarray, config: EvalConfig,
           model: str, n_nominal: int, n_calibration: int) -> dict[str, Any]:
    both = bool(labels.any() and (~labels).any())
    m = binary_metrics(scores, labels, cal.threshold)
    return {
        "auroc": auroc(scores, labels) if both else None,
        "threshold": cal.threshold,
        "tpr": m.tpr,
        "fpr": m.fpr,
        "accuracy": m.accuracy,
        "balanced_accuracy": m.balanced_accuracy,
        "n_nominal": n_nominal,
        "n_calibration": n_calibration,
        "n_test": len(labels),
        "method": cal.method,
        "k": config.k,
        "alpha": cal.alpha,
        "model": model,
    }


def evaluate_structured(embedder: Embedder, nominal: Sequence[Labelled],
                        test: Sequence[Labelled], calibration: Sequence[Labelled],
                        config: EvalConfig, adapt: Sequence[Labelled] = ()
                        ) -> dict[str, Any]:
    """``--score detections|combined``: see the module docstring. The calibration scores
    are the nominal set's leave-one-out scores (``loo-quantile``) or the calibration
    set's nominal ones (``conformal``), kept and judged by the cache as the service
    does."""
    cache, kept = fit_structured(embedder, nominal, calibration, config)
    accept(cache, embedder, adapt, config)
    kept = cache.calibration_scores or kept
    scored = score_structured(cache, embedder, test)
    p_whole = p_values_sorted(kept.observation, np.array([r.score for r in scored]))
    if config.score == "combined":
        p = np.array([p_whole[i] if r.p_value is None else r.p_value
                      for i, r in enumerate(scored)])
    else:  # the worst detection's own p-value; the whole observation's without detections
        p_det = p_values_sorted(kept.detection, floats(r.detection_score for r in scored))
        p = np.where(np.isnan(p_det), p_whole, p_det)
    labels_test = np.array([x.is_anomaly for x in test])
    method = config.method if cache.calibration is None else cache.calibration.method
    cal = Calibration(method, config.alpha, config.alpha, len(kept.observation),
                      pairs=config.pairs)
    return report(cal, 1.0 - p, labels_test, config, embedder.name, len(nominal),
                  len(calibration)) | {"score": config.score, "pairs": config.pairs,
                                       "nominal_detections": len(cache.detection_counts)
                                       } | _adapted(cache, adapt, config)


def fit_structured(embedder: Embedder, nominal: Sequence[Labelled],
                   calibration: Sequence[Labelled], config: EvalConfig
                   ) -> tuple[Cache, CalibrationScores]:
    """An in-memory cache of ``nominal`` with their detections, calibrated by
    ``config.method`` with the components' nominal scores kept, as the service keeps
    them (``score: detections`` keeps no pair scores)."""
    if config.method == "tpr-target":
        raise InvalidInput(f"--score {config.score} takes --method loo-quantile or conformal",
                           field="method")
    if config.pairs and config.score != "combined":
        raise InvalidInput("--pairs is a component of --score combined", field="pairs")
    if any(x.is_anomaly for x in nominal):
        raise InvalidInput("the nominal set contains anomalies", field="nominal")
    cache = structured_cache(embedder, nominal, config)
    if not cache.has_detections:
        raise InvalidInput(f"--score {config.score} needs 'detections' in the nominal set",
                           field="nominal")
    pairs = config.pairs
    if pairs and not cache.pair_counts:
        raise InvalidInput("--pairs needs nominal lines with two or more detections",
                           field="pairs")
    loo = labelled = labels = None
    if needs_loo(config.method):
        loo = loo_components(cache, pairs=pairs, k=config.k)
    else:
        if not any(not x.is_anomaly for x in calibration):
            raise InvalidInput("--method conformal needs nominal lines in --calibration",
                               field="calibration")
        scored = score_structured(cache, embedder, calibration, pairs=pairs)
        labelled, labels = labelled_components(scored, calibration, pairs=pairs)
    # the whole observation's tau serves observations without detections
    cal, kept = calibrate_with(config.method, Evidence(loo, labelled, labels),
                               alpha=config.alpha, pairs=pairs,
                               tests=1 if config.score == "detections" else None)
    assert kept is not None
    cache.apply(cache.plan_calibration(cal, kept))
    return cache, kept


def structured_cache(embedder: Embedder, nominal: Sequence[Labelled],
                     config: EvalConfig) -> Cache:
    """An in-memory cache of ``nominal`` with their detections (phrases)."""
    vectors = embedder.embed([x.text for x in nominal])
    cache = Cache(CacheConfig("eval", embedder.name, vectors.shape[1], config.k, "topk"))
    phrases, _ = distinct([x.detections for x in nominal])
    found = phrase_vectors(embedder, phrases)
    n = len(nominal)
    # a phrase is one label here (a JSONL line's "label where", joined as Detection.phrase)
    held = [tuple(Detection.model_construct(label=d, where=None) for d in x.detections)
            for x in nominal]
    cache.apply(cache.plan_add(vectors, ids=[str(i) for i in range(n)], texts=[None] * n,
                               metadata=[{}] * n, detections=held, detection_vectors=found))
    return cache


def score_structured(cache: Cache, embedder: Embedder, items: Sequence[Labelled], *,
                     pairs: bool = False) -> list[Scored]:
    """Each item scored and judged by ``cache`` with its detections."""
    vectors = embedder.embed([x.text for x in items])
    phrases = list(dict.fromkeys(d for x in items for d in x.detections))
    rows = phrase_vectors(embedder, phrases)
    found = [Detections(tuple(dict.fromkeys(x.detections)),
                        np.stack([rows[d] for d in dict.fromkeys(x.detections)]))
             if x.detections else None for x in items]
    return cache.score(vectors, cache.config.k, 0, found, pairs=pairs)

