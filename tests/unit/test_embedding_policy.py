"""The calibration policy, one table: what each method needs, what it keeps, what it refuses.

The service (POST /v1/caches/{name}/calibrate) and offline evaluation (aesop detector eval)
both calibrate through it, so the rule and its defaults exist once.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.embedding.detector import policy
from services.embedding.detector.errors import InvalidInput
from services.embedding.detector.evaluation import EvalConfig
from services.embedding.detector.policy import Components, Evidence

RNG = np.random.default_rng(0)
LOO = Components(RNG.normal(size=60), RNG.normal(size=60), None)
SCORES = np.concatenate([RNG.normal(size=50), RNG.normal(3.0, size=10)])
LABELS = np.array([False] * 50 + [True] * 10)
LABELLED = Components(SCORES, RNG.normal(size=60), None)
NOMINAL_ONLY = Evidence(labelled=Components(SCORES[:50], LABELLED.detection[:50], None),
                        labels=LABELS[:50])


@pytest.mark.parametrize(("method", "evidence", "field"), [
    ("conformal", Evidence(loo=LOO), "calibration"),  # no held-out nominal examples
    ("conformal", Evidence(labelled=Components(SCORES[50:], SCORES[50:], None),
                           labels=LABELS[50:]), "calibration"),  # anomalies only
    ("tpr-target", Evidence(loo=LOO), "calibration"),  # no labelled set
    ("tpr-target", NOMINAL_ONLY, "calibration"),  # one class: no TPR to aim at
])
def test_what_each_method_needs_is_named_when_missing(method: str, evidence: Evidence,
                                                      field: str) -> None:
    with pytest.raises(InvalidInput) as info:
        policy.threshold(method, evidence)  # type: ignore[arg-type]
    assert info.value.field == field


def test_pairs_with_tpr_target_are_refused_before_anything_is_computed() -> None:
    with pytest.raises(InvalidInput) as info:
        policy.calibrate("tpr-target", Evidence(labelled=LABELLED, labels=LABELS), pairs=True)
    assert info.value.field == "pairs"


@pytest.mark.parametrize(("method", "evidence", "kept_n", "auroc"), [
    ("loo-quantile", Evidence(loo=LOO), 60, False),
    ("loo-quantile", Evidence(loo=LOO, labelled=LABELLED, labels=LABELS), 60, True),
    ("conformal", Evidence(labelled=LABELLED, labels=LABELS), 50, True),
    ("conformal", NOMINAL_ONLY, 50, False),
    ("tpr-target", Evidence(labelled=LABELLED, labels=LABELS), None, True),
])
def test_tau_and_the_nominal_scores_kept(method: str, evidence: Evidence,
                                         kept_n: int | None, auroc: bool) -> None:
    cal, kept = policy.calibrate(method, evidence)  # type: ignore[arg-type]
    assert cal.method == method and np.isfinite(cal.threshold)
    assert (cal.auroc is not None) == auroc
    if kept_n is None:
        assert kept is None  # tpr-target verdicts are s > tau: nothing behind a p-value
    else:
        assert kept is not None and len(kept.observation) == kept_n
        assert len(kept.detection) == kept_n


def test_the_defaults_are_the_same_for_the_service_and_offline_evaluation() -> None:
    by_default, _ = policy.calibrate("loo-quantile", Evidence(loo=LOO))
    assert by_default.alpha == policy.DEFAULT_ALPHA == EvalConfig().alpha
    assert EvalConfig().tpr == policy.DEFAULT_TPR


def test_a_calibration_that_could_never_flag_is_refused_naming_alpha() -> None:
    few = Components(LOO.observation[:10], LOO.detection[:10], None)
    with pytest.raises(InvalidInput) as info:
        policy.calibrate("loo-quantile", Evidence(loo=few), alpha=0.95)  # 2/11 >= 0.05
    assert info.value.field == "alpha"
    cal, kept = policy.calibrate("loo-quantile", Evidence(loo=few), alpha=0.8)  # 2/11 < 0.2
    assert kept is not None and cal.alpha == 0.8
