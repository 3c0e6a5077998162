"""Offline evaluation of the fast anomaly detector on labelled text sets.

``aesop detector eval`` builds an in-memory cache from nominal texts, calibrates
tau with the chosen method, scores a labelled test set and reports AUROC and
the confusion-matrix rates at tau. Nothing is written to disk.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from services.embedding.cache import Cache, CacheConfig, Labelled, ScoreKind
from services.embedding.calibration import (
    Calibration,
    auroc,
    binary_metrics,
    conformal,
    loo_quantile,
    tpr_target,
)
from services.embedding.embedders import Embedder
from services.embedding.errors import InvalidInput

Method = Literal["loo-quantile", "conformal", "tpr-target"]


@dataclass(frozen=True)
class EvalConfig:
    k: int = 5
    alpha: float = 0.95
    method: Method = "loo-quantile"
    score: ScoreKind = "topk"
    tpr: float = 0.9  # the target of "tpr-target" (the hardware appendix uses 0.9)


def read_jsonl(path: Path) -> list[Labelled]:
    """Lines ``{"text": ..., "label": "nominal"|"anomaly"}``; errors name file and line."""
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
            out.append(Labelled(text, label == "anomaly"))
    if not out:
        raise InvalidInput(f"{path} has no examples", field=str(path))
    return out


def build_cache(vectors: np.ndarray, config: EvalConfig, model: str | None) -> Cache:
    cache = Cache(CacheConfig("eval", model, vectors.shape[1], config.k, config.score))
    n = len(vectors)
    cache.apply(cache.plan_add(vectors, ids=[str(i) for i in range(n)], texts=[None] * n,
                               metadata=[{}] * n))
    return cache


def calibrate(cache: Cache, config: EvalConfig, cal_scores: np.ndarray | None,
              cal_labels: np.ndarray | None) -> Calibration:
    if config.method == "loo-quantile":
        return loo_quantile(cache.loo_scores(config.k), config.alpha)
    if cal_scores is None or cal_labels is None:
        raise InvalidInput(f"--method {config.method} needs --calibration", field="calibration")
    if config.method == "conformal":
        return conformal(cal_scores[~cal_labels], config.alpha)
    return tpr_target(cal_scores, cal_labels, config.tpr)


def evaluate(
    embedder: Embedder,
    nominal: Sequence[Labelled],
    test: Sequence[Labelled],
    calibration: Sequence[Labelled] = (),
    config: EvalConfig = EvalConfig(),
) -> dict[str, Any]:
    """Build, calibrate, test; the ``aesop detector eval --json`` object."""
    cache, cal = fit(embedder, nominal, calibration, config)
    scores = score_all(cache, embedder, [x.text for x in test], config.k)
    labels = np.array([x.is_anomaly for x in test])
    return report(cal, scores, labels, config, embedder.name, len(nominal), len(calibration))


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
