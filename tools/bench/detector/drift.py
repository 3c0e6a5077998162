"""``drift``: the detector when the captioner changes its wording (issue 28).

Per synthetic domain (:func:`tools.scenes.wording.drift_set`): a cache of nominal scenes and
a split-conformal calibration (alpha 0.95) in the domains' own wording; then a new
captioner (:class:`~tools.scenes.wording.Captioner`: synonyms, articles, plurals,
reorderings, a new line style) writes the test set (new-wording nominal scenes and every
anomaly) and the reviewed scenes. Measured, per score kind:

* zero-shot: AUROC, AUROC on the anomalies that hold an anomalous object (not only an
  anomalous pair of nominal ones: a new wording cannot hide a pair), FPR at alpha;
* adaptation: AUROC and FPR after 0, 10, 20, 40 and 80 reviewed new-wording scenes
  accepted as the service accepts them (``evaluation.accept``: held-out scores, the
  policy ``window``);
* the drift monitor (:mod:`services.embedding.drift`) on the combined verdicts: frames from
  the switch to the ``drift`` event, and drift events on 10,000 frames of the unchanged
  wording (held-out nominal scenes, drawn with repeats).
"""

from __future__ import annotations

import random
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.tables import table

from .common import ALPHA, QUALITY_DOMAINS, Bench, K, Memo, labelled

if TYPE_CHECKING:
    from services.embedding.cache import Labelled
    from services.embedding.evaluation import EvalScore

KINDS: tuple[EvalScore, ...] = ("topk", "detections", "combined")
ACCEPTED = (0, 10, 20, 40, 80)
NOMINAL_FRAMES = 10_000
TARGETS = {"zero_shot_auroc": 0.90, "adapted_auroc": 0.99, "adapted_after": 60,
           "fpr_slack": 0.01, "frames_to_drift": 50}


def bench_drift(bench: Bench) -> dict[str, Any]:
    from services.embedding.evaluation import EvalConfig, evaluate
    from tools.scenes.registry import get_domain
    from tools.scenes.wording import drift_set

    memo = Memo(bench.embedder)
    quick = bench.sizes.quick
    domains = {}
    for name in QUALITY_DOMAINS:
        data = drift_set(get_domain(name), seed=bench.seed, **(
            {"n_nominal": 200, "n_calibration": 80, "n_test_nominal": 60, "n_anomaly": 40}
            if quick else {}))
        nominal, calibration = labelled(data.nominal), labelled(data.calibration)
        test, reviewed = labelled(data.test), labelled(data.reviewed)
        objects = [x for x, s in zip(test, data.test, strict=True)
                   if s.label == "nominal" or set(s.concepts) & set(data.domain.anomalous)]
        curve = []
        for n in ACCEPTED:
            for kind in KINDS:
                config = EvalConfig(k=K, alpha=ALPHA, method="conformal", score=kind)
                got = evaluate(memo, nominal, test, calibration, config, reviewed[:n])
                row = {"accepted": n, "kind": kind, "auroc": got["auroc"], "fpr": got["fpr"],
                       "tpr": got["tpr"], "calibrated_on": got.get("calibrated_on")}
                if n == 0:
                    row["auroc_objects"] = evaluate(memo, nominal, objects, calibration,
                                                    config)["auroc"]
                curve.append(row)
        domains[name] = {"n_nominal": len(nominal), "n_calibration": len(calibration),
                         "n_test": len(test), "n_reviewed": len(reviewed), "curve": curve,
                         "monitor": _monitor(memo, nominal, calibration, test, bench.seed)}
    return {"model": memo.name, "k": K, "alpha": ALPHA, "domains": domains,
            "targets": TARGETS, "nominal_frames": NOMINAL_FRAMES}


def _monitor(memo: Memo, nominal: Sequence[Labelled], calibration: Sequence[Labelled],
             test: Sequence[Labelled], seed: int) -> dict[str, Any]:
    """The drift monitor on the combined verdicts: a stream of the old wording (held-out
    nominal scenes, :data:`NOMINAL_FRAMES` frames drawn with repeats), then the new."""
    from services.embedding.drift import DriftMonitor
    from services.embedding.evaluation import EvalConfig, fit_structured, score_structured

    half = len(calibration) // 2
    cache, _ = fit_structured(memo, nominal, calibration[:half],
                              EvalConfig(k=K, alpha=ALPHA, method="conformal",
                                         score="combined"))
    old = [bool(r.is_anomaly) for r in score_structured(cache, memo, calibration[half:])]
    new_nominal = [x for x in test if not x.is_anomaly]
    new = [bool(r.is_anomaly) for r in score_structured(cache, memo, new_nominal)]
    rng = random.Random(f"aesop:drift-stream:{seed}")
    monitor = DriftMonitor()
    false_drifts = 0
    for _ in range(NOMINAL_FRAMES):
        if monitor.observe("robot", rng.choice(old), 1 - ALPHA) is not None:
            false_drifts += 1
    to_drift = None
    for frame in range(1, 1001):
        if monitor.observe("robot", rng.choice(new), 1 - ALPHA) is not None:
            to_drift = frame
            break
    return {"old_flag_rate": float(np.mean(old)), "new_flag_rate": float(np.mean(new)),
            "false_drifts": false_drifts, "frames_to_drift": to_drift}


def render_drift(r: Mapping[str, Any]) -> str:
    t = r["targets"]
    rows = []
    for name, d in r["domains"].items():
        zero = {row["kind"]: row for row in d["curve"] if row["accepted"] == 0}
        rows.append({"domain": name, "cache / cal / test": f"{d['n_nominal']} / "
                     f"{d['n_calibration']} / {d['n_test']}",
                     **{f"AUROC {k}": zero[k]["auroc"] for k in KINDS},
                     "AUROC combined, object anomalies": zero["combined"]["auroc_objects"],
                     **{f"FPR {k}": zero[k]["fpr"] for k in KINDS}})
    out = table(f"[drift] zero-shot on a new captioner's wording, {r['model']}, k {r['k']}, "
                f"split-conformal alpha {r['alpha']} (target: combined AUROC >= "
                f"{t['zero_shot_auroc']})", rows)
    rows = [{"domain": name, "accepted": n,
             **{f"AUROC / FPR {k}": _pair(d, n, k) for k in ("topk", "combined")},
             "calibrated on": _row(d, n, "combined")["calibrated_on"] or "old set"}
            for name, d in r["domains"].items() for n in ACCEPTED]
    out += "\n" + table(f"[drift] after n reviewed new-wording scenes accepted (policy "
                        f"window; target after {t['adapted_after']}: AUROC >= "
                        f"{t['adapted_auroc']}, FPR <= {1 - r['alpha'] + t['fpr_slack']:.2f})",
                        rows)
    rows = [{"domain": name, "flag rate old / new wording":
             f"{d['monitor']['old_flag_rate']:.3f} / {d['monitor']['new_flag_rate']:.3f}",
             f"drift events in {r['nominal_frames']} old-wording frames":
             d["monitor"]["false_drifts"],
             "frames from the switch to the drift event": d["monitor"]["frames_to_drift"]}
            for name, d in r["domains"].items()]
    return out + "\n" + table(f"[drift] the drift monitor on combined verdicts (target: "
                              f"none on the old wording, within {t['frames_to_drift']} "
                              "frames of the switch)", rows)


def _row(d: Mapping[str, Any], n: int, kind: str) -> Mapping[str, Any]:
    return next(row for row in d["curve"] if row["accepted"] == n and row["kind"] == kind)


def _pair(d: Mapping[str, Any], n: int, kind: str) -> str:
    row = _row(d, n, kind)
    return f"{row['auroc']:.3f} / {row['fpr']:.3f}"
