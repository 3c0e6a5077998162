"""``drift``: the detector when the captioner changes its wording (issue 28).

Per synthetic domain (:func:`tools.scenes.wording.drift_set`): a cache of nominal scenes and
a split-conformal calibration (alpha 0.95) in the domains' own wording; then a new
captioner (:class:`~tools.scenes.wording.Captioner`: synonyms, articles, plurals,
reorderings, a new line style) writes the test set (new-wording nominal scenes and every
anomaly) and the reviewed scenes. Measured, per score kind:

* zero-shot: AUROC, AUROC on the anomalies that hold an anomalous object (not only an
  anomalous pair of nominal ones, which no single phrase shows), FPR at alpha; beside it the
  same detector on the same scenes in the old wording (no drift: the domain's own ceiling);
* adaptation: AUROC and FPR after 0, 10, 20, 40, 60 and 80 reviewed new-wording scenes
  accepted as the service accepts them (``evaluation.accept``: held-out scores, the
  policy ``window``);

each for a captioner that changes its words only (the robot's own line template kept) and
for one that changes its line style too;
* the drift monitor (:mod:`services.embedding.detector.drift`) on the combined verdicts: frames from
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
    from services.embedding.detector.cache import Labelled
    from services.embedding.detector.evaluation import EvalScore
    from tools.scenes.wording import DriftSet

KINDS: tuple[EvalScore, ...] = ("topk", "detections", "combined")
ACCEPTED = (0, 10, 20, 40, 60, 80)
NOMINAL_FRAMES = 10_000
# the captioner's two ways: its words only (the robot's own line template kept), and its
# words and its line style
VARIANTS = {"words": False, "words + line": True}
TARGETS = {"zero_shot_auroc": 0.90, "adapted_auroc": 0.99, "adapted_after": 60,
           "fpr_slack": 0.01, "frames_to_drift": 50}


def bench_drift(bench: Bench) -> dict[str, Any]:
    from tools.scenes.registry import get_domain
    from tools.scenes.wording import drift_set

    memo = Memo(bench.embedder)
    sizes = ({"n_nominal": 200, "n_calibration": 80, "n_test_nominal": 60, "n_anomaly": 40}
             if bench.sizes.quick else {})
    variants: dict[str, Any] = {}
    for variant, lines in VARIANTS.items():
        domains = {}
        for name in QUALITY_DOMAINS:
            data = drift_set(get_domain(name), seed=bench.seed, lines=lines, **sizes)
            domains[name] = _domain(memo, data)
            if lines:  # the monitor sees the harder switch
                domains[name]["monitor"] = _monitor(memo, labelled(data.nominal),
                                                    labelled(data.calibration),
                                                    labelled(data.test), bench.seed)
        variants[variant] = domains
    return {"model": memo.name, "k": K, "alpha": ALPHA, "variants": variants,
            "targets": TARGETS, "nominal_frames": NOMINAL_FRAMES}


def _domain(memo: Memo, data: DriftSet) -> dict[str, Any]:
    """Zero-shot per kind, the curve, and the same detector without drift (the ceiling),
    each on every anomaly and on the object anomalies alone."""
    from services.embedding.detector.evaluation import EvalConfig, evaluate

    nominal, calibration = labelled(data.nominal), labelled(data.calibration)
    test, reviewed = labelled(data.test), labelled(data.reviewed)
    odd = set(data.domain.anomalous)
    objects = [x for x, s in zip(test, data.test, strict=True)
               if s.label == "nominal" or set(s.concepts) & odd]

    def run(kind: EvalScore, on: Sequence[Labelled], n: int = 0) -> dict[str, Any]:
        config = EvalConfig(k=K, alpha=ALPHA, method="conformal", score=kind)
        return evaluate(memo, nominal, on, calibration, config, reviewed[:n])

    curve = []
    for n in ACCEPTED:
        for kind in KINDS if n == 0 else ("topk", "combined"):
            got = run(kind, test, n)
            curve.append({"accepted": n, "kind": kind, "auroc": got["auroc"],
                          "auroc_objects": run(kind, objects, n)["auroc"], "fpr": got["fpr"],
                          "tpr": got["tpr"], "calibrated_on": None if got.get("stale", True)
                          else got["calibrated_on"]})
    ceiling = run("combined", labelled(data.original))
    return {"n_nominal": len(nominal), "n_calibration": len(calibration),
            "n_test": len(test), "n_reviewed": len(reviewed), "curve": curve,
            "no_drift": {"auroc": ceiling["auroc"], "fpr": ceiling["fpr"]}}


def _monitor(memo: Memo, nominal: Sequence[Labelled], calibration: Sequence[Labelled],
             test: Sequence[Labelled], seed: int) -> dict[str, Any]:
    """The drift monitor on the combined verdicts: a stream of the old wording (held-out
    nominal scenes, :data:`NOMINAL_FRAMES` frames drawn with repeats), then the new."""
    from services.embedding.detector.drift import DriftMonitor
    from services.embedding.detector.evaluation import EvalConfig, fit_structured, score_structured

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
    for _ in range(NOMINAL_FRAMES):  # a scene seen again within the window counts once
        i = rng.randrange(len(old))
        if monitor.observe("robot", old[i], 1 - ALPHA, scene=f"old {i}") is not None:
            false_drifts += 1
    to_drift = None
    for frame in range(1, 1001):
        i = rng.randrange(len(new))
        if monitor.observe("robot", new[i], 1 - ALPHA, scene=f"new {i}") is not None:
            to_drift = frame
            break
    return {"old_flag_rate": float(np.mean(old)), "new_flag_rate": float(np.mean(new)),
            "false_drifts": false_drifts, "frames_to_drift": to_drift}


def render_drift(r: Mapping[str, Any]) -> str:
    t = r["targets"]
    out = []
    for variant, domains in r["variants"].items():
        rows = []
        for name, d in domains.items():
            zero = {row["kind"]: row for row in d["curve"] if row["accepted"] == 0}
            rows.append({"domain": name, "cache / cal / test": f"{d['n_nominal']} / "
                         f"{d['n_calibration']} / {d['n_test']}",
                         **{f"AUROC {k} (objects)": _both(zero[k]) for k in KINDS},
                         **{f"FPR {k}": zero[k]["fpr"] for k in KINDS},
                         "no drift: AUROC combined": d["no_drift"]["auroc"]})
        out.append(table(
            f"[drift] zero-shot on a new captioner's {variant}, {r['model']}, k {r['k']}, "
            f"split-conformal alpha {r['alpha']}; AUROC on every anomaly (on the object "
            f"anomalies alone) (target: combined >= {t['zero_shot_auroc']})", rows))
        rows = [{"domain": name, "accepted": n,
                 **{f"AUROC (objects) / FPR {k}": f"{_both(_row(d, n, k))} / "
                    f"{_row(d, n, k)['fpr']:.3f}" for k in ("topk", "combined")},
                 "calibrated on": _row(d, n, "combined")["calibrated_on"] or
                 "old set (stale)"}
                for name, d in domains.items() for n in ACCEPTED]
        out.append(table(
            f"[drift] {variant}: after n reviewed new-wording scenes accepted (policy window;"
            f" target after {t['adapted_after']}: AUROC >= {t['adapted_auroc']}, FPR <= "
            f"{1 - r['alpha'] + t['fpr_slack']:.2f})", rows))
    rows = [{"domain": name, "flag rate old / new wording":
             f"{d['monitor']['old_flag_rate']:.3f} / {d['monitor']['new_flag_rate']:.3f}",
             f"drift events in {r['nominal_frames']} old-wording frames":
             d["monitor"]["false_drifts"],
             "frames from the switch to the drift event": d["monitor"]["frames_to_drift"]}
            for name, d in r["variants"]["words + line"].items()]
    out.append(table(f"[drift] the drift monitor on combined verdicts, words + line (target: "
                     f"none on the old wording, within {t['frames_to_drift']} frames of the "
                     "switch)", rows))
    return "\n".join(out)


def _row(d: Mapping[str, Any], n: int, kind: str) -> Mapping[str, Any]:
    return next(row for row in d["curve"] if row["accepted"] == n and row["kind"] == kind)


def _both(row: Mapping[str, Any]) -> str:
    return f"{row['auroc']:.3f} ({row['auroc_objects']:.3f})"
