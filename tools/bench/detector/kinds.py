"""``kinds``: each score kind's AUROC, balanced accuracy and FPR, per domain.

Per domain (three synthetic, quadrotor), brief form with detections: AUROC,
balanced accuracy and FPR of the top-k, detection and combined scores, and the
split-conformal FPR of the combined score against alpha.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from services.embedding.models.base import Embedder
from shared.tables import table

if TYPE_CHECKING:
    from services.embedding.detector.evaluation import EvalScore
from .common import ALPHA, HOLDOUT, PAPER_MPNET_VTOL, QUANTILES, Bench, K, Memo, labelled
from .quality import _split

# label: (score kind, pairs as a third component)
KINDS: dict[str, tuple[EvalScore, bool]] = {
    "topk": ("topk", False), "detections": ("detections", False),
    "combined": ("combined", False), "combined+pairs": ("combined", True)}


CONFORMAL_KINDS = ("combined", "combined+pairs")


KIND_DOMAINS = ("warehouse", "vehicle", "vtol", "quadrotor")


CONFORMAL_ALPHAS = (0.8, 0.9, 0.95, 0.99)


def bench_kinds(bench: Bench) -> dict[str, Any]:
    """Per domain, the brief form (what a robot publishes) with its detections, split as
    ``aesop detector domains`` splits it (80% of nominal the cache, the rest and every
    anomaly the test): AUROC, balanced accuracy and FPR of each score kind, loo-quantile
    at alpha 0.95, k 5; then ``combined`` (with and without pairs) calibrated
    split-conformal (the cache's nominal set halved: cache and calibration) at each alpha:
    its FPR on the held-out nominal test samples against the ``1 - alpha`` it promises."""
    from services.embedding.detector.errors import InvalidInput
    from services.embedding.detector.evaluation import EvalConfig, evaluate

    memo = Memo(bench.embedder)
    domains = {}
    for name in KIND_DOMAINS:
        nominal, test = (labelled(x)
                         for x in bench.dataset(name, kinds=True).split_for_eval(bench.seed))
        kinds = {label: evaluate(memo, nominal, test, config=EvalConfig(
            k=K, alpha=ALPHA, method="loo-quantile", score=score, pairs=pairs))
            for label, (score, pairs) in KINDS.items()}
        half = len(nominal) // 2
        conformal = []
        for label, alpha in itertools.product(CONFORMAL_KINDS, CONFORMAL_ALPHAS):
            score, pairs = KINDS[label]
            try:
                got = evaluate(memo, nominal[:half], test, nominal[half:], EvalConfig(
                    k=K, alpha=alpha, method="conformal", score=score, pairs=pairs))
            except InvalidInput as exc:  # too few calibration samples to ever flag
                conformal.append({"kind": label, "alpha": alpha, "fpr": None,
                                  "promised": 1 - alpha, "note": exc.message})
                continue
            conformal.append({"kind": label, "alpha": alpha, "fpr": got["fpr"],
                              "promised": 1 - alpha, "tpr": got["tpr"],
                              "n_calibration": got["n_calibration"]})
        domains[name] = {"n_nominal": len(nominal), "n_test": len(test),
                         "kinds": {k: {m: v[m] for m in ("auroc", "balanced_accuracy", "fpr")}
                                   for k, v in kinds.items()},
                         "conformal": conformal}
    return {"model": memo.name, "k": K, "alpha": ALPHA, "domains": domains,
            "quantiles": _kind_quantiles(bench, memo)}


def _kind_quantiles(bench: Bench, memo: Embedder) -> dict[str, Any]:
    """The paper's VTOL quantile table for the combined kinds: cache = a random 80% of the
    nominal samples (brief form, with detections), loo-quantile at alpha = each quantile,
    accuracy on the rest and every anomaly, averaged over ``threshold_seeds`` splits
    (the same splits as the top-k table of the quality part)."""
    from services.embedding.detector.evaluation import EvalConfig, evaluate

    ds = bench.dataset("vtol", kinds=True)
    nominal, anomalies = labelled(ds.nominal), labelled(ds.anomalies)
    runs: dict[tuple[str, float], list[dict[str, Any]]] = {}
    for s in range(bench.sizes.threshold_seeds):
        held, pool = _split(len(nominal), np.random.default_rng([bench.seed, s, 99]))
        test = [nominal[i] for i in held] + anomalies
        for label, q in itertools.product(CONFORMAL_KINDS, QUANTILES):
            score, pairs = KINDS[label]
            runs.setdefault((label, q), []).append(evaluate(
                memo, [nominal[i] for i in pool], test,
                config=EvalConfig(k=K, alpha=q, method="loo-quantile", score=score,
                                  pairs=pairs)))
    rows = [{"kind": label, "quantile": q,
             "accuracy": float(np.mean([r["accuracy"] for r in got])),
             "accuracy_std": float(np.std([r["accuracy"] for r in got])),
             "balanced_accuracy": float(np.mean([r["balanced_accuracy"] for r in got])),
             "paper_mpnet": PAPER_MPNET_VTOL[q]}
            for (label, q), got in runs.items()]
    return {"domain": "vtol", "cache_fraction": 1 - HOLDOUT,
            "seeds": bench.sizes.threshold_seeds, "rows": rows}


def render_kinds(r: Mapping[str, Any]) -> str:
    rows = [{"domain": name, "cache / test": f"{d['n_nominal']} / {d['n_test']}",
             **{f"AUROC {k}": d["kinds"][k]["auroc"] for k in KINDS},
             **{f"bal.acc {k}": d["kinds"][k]["balanced_accuracy"] for k in KINDS},
             **{f"FPR {k}": d["kinds"][k]["fpr"] for k in CONFORMAL_KINDS}}
            for name, d in r["domains"].items()]
    out = table(f"[kinds] score kinds, brief form with detections, {r['model']}, k {r['k']}, "
                f"loo-quantile alpha {r['alpha']} (target AUROC >= 0.95)", rows)
    def fpr(c: Mapping[str, Any]) -> str:
        if c["fpr"] is None:
            return "n too small"
        return f"{c['fpr']:.3f} {'ok' if c['fpr'] <= c['promised'] + 0.01 else 'OVER'}"

    rows = [{"domain": name, "kind": kind,
             **{f"FPR @ {c['alpha']:g} (<= {c['promised']:.2f})": fpr(c)
                for c in d["conformal"] if c["kind"] == kind}}
            for name, d in r["domains"].items() for kind in CONFORMAL_KINDS]
    out += "\n" + table("[kinds] split conformal: held-out nominal FPR vs 1 - alpha "
                        "(target: at most 1 - alpha + 1%)", rows)
    q = r["quantiles"]
    rows = [{"kind": row["kind"], "quantile": row["quantile"],
             "accuracy": f"{row['accuracy']:.3f} ± {row['accuracy_std']:.3f}",
             "balanced acc": row["balanced_accuracy"], "paper MPNet": row["paper_mpnet"],
             "target": "met" if row["accuracy"] >= row["paper_mpnet"] else "missed"}
            for row in q["rows"]]
    return out + "\n" + table(
        f"[kinds] threshold quantiles, VTOL brief form with detections, cache = random "
        f"{q['cache_fraction']:.0%} of nominal, {q['seeds']} splits (target: at or above "
        "the paper's MPNet)", rows)
