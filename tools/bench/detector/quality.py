"""``quality``: accuracy and AUROC vs cache size and concept coverage (paper §V-A).

Accuracy / AUROC vs cache size and vs concept coverage on the synthetic domains (paper §V-A,
``fig:synthetic-results``), top-5 scoring, tau = 95th LOO quantile (eq. 2); plus the
threshold-quantile table of the appendix (``supp:threshold-analysis``) on VTOL.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.tables import table

if TYPE_CHECKING:
    pass
from .common import (
    ALPHA,
    CACHE_FRACTIONS,
    COVERAGE_FRACTIONS,
    HOLDOUT,
    PAPER_MPNET_VTOL,
    QUALITY_DOMAINS,
    QUANTILES,
    Bench,
    K,
)

log = logging.getLogger(__name__)


def bench_quality(bench: Bench, plot: Path | None) -> dict[str, Any]:
    """Accuracy and AUROC vs cache size and vs concept coverage, and the quantile table."""
    domains = {name: _quality_domain(bench, name) for name in QUALITY_DOMAINS}
    result = {
        "model": bench.embedder.name, "k": K, "alpha": ALPHA, "repeats": bench.sizes.repeats,
        "test_set": "held-out 20% of nominal + all anomalies",
        "domains": domains,
        "thresholds": _thresholdtable(bench),
        "text_forms": _text_forms(bench),
    }
    if plot is not None:
        plot_quality(domains, plot)
        result["plot"] = str(plot)
    return result


def _quality_domain(bench: Bench, name: str) -> dict[str, Any]:
    from tools.scenes import concept_subset

    ds = bench.dataset(name)
    nominal, anomalies = bench.vectors(name)
    domain = ds.domain
    n = len(nominal)
    by_size: dict[float, list[dict[str, Any]]] = {f: [] for f in CACHE_FRACTIONS}
    by_coverage: dict[float, list[dict[str, Any]]] = {f: [] for f in COVERAGE_FRACTIONS}
    for r in range(bench.sizes.repeats):
        rng = np.random.default_rng([bench.seed, r, QUALITY_DOMAINS.index(name)])
        held, pool = _split(n, rng)
        test_x = np.concatenate([nominal[held], anomalies])
        test_y = np.r_[np.zeros(len(held), bool), np.ones(len(anomalies), bool)]
        for f in CACHE_FRACTIONS:
            size = min(len(pool), max(K + 1, round(f * n)))
            members = rng.choice(pool, size, replace=False)
            by_size[f].append(_detect(nominal[members], test_x, test_y))
        for f in COVERAGE_FRACTIONS:
            subset = set(concept_subset(domain, f, seed=bench.seed * 1000 + r))
            covered = [i for i in pool if set(ds.nominal[i].concepts) <= subset]
            seen = {c for i in covered for c in ds.nominal[i].concepts}
            point: dict[str, Any] = (_detect(nominal[covered], test_x, test_y)
                                     if len(covered) > K else {"cache_size": len(covered)})
            point["concepts_covered"] = len(seen) / len(domain.nominal_concepts)
            by_coverage[f].append(point)
    return {
        "n_nominal": n, "n_anomaly": len(anomalies), "n_test": len(test_y),
        "n_concepts": len(domain.nominal_concepts),
        "cache_size": [{"fraction": f, **_mean_std(by_size[f])} for f in CACHE_FRACTIONS],
        "coverage": [{"fraction": f, **_mean_std(by_coverage[f])} for f in COVERAGE_FRACTIONS],
    }


def _split(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(held-out, pool) index arrays: HOLDOUT of ``n`` for testing, the rest for caches."""
    perm = rng.permutation(n)
    cut = round(HOLDOUT * n)
    return perm[:cut], perm[cut:]


def _detect(cache_x: np.ndarray, test_x: np.ndarray, test_y: np.ndarray,
            alphas: Sequence[float] = (ALPHA,)) -> dict[str, Any]:
    """Detector built on ``cache_x`` with tau from eq. (2), evaluated on the test set."""
    from services.embedding.detector.calibration import auroc, binary_metrics, loo_quantile
    from services.embedding.detector.evaluation import EvalConfig, build_cache

    cache = build_cache(cache_x, EvalConfig(k=K), None)
    loo = cache.loo_scores(K)
    scores = np.array([r.score for r in cache.score(test_x, K, neighbors=0)])
    out: dict[str, Any] = {"cache_size": len(cache_x), "auroc": auroc(scores, test_y)}
    for alpha in alphas:
        m = binary_metrics(scores, test_y, loo_quantile(loo, alpha).threshold)
        suffix = "" if len(alphas) == 1 else f"@{alpha:g}"
        out |= {f"accuracy{suffix}": m.accuracy, f"balanced_accuracy{suffix}":
                m.balanced_accuracy, f"tpr{suffix}": m.tpr, f"fpr{suffix}": m.fpr}
    return out


def _mean_std(points: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean of every numeric field over repeats, plus ``<field>_std`` for the metrics."""
    out: dict[str, Any] = {}
    for key in dict.fromkeys(k for p in points for k in p):
        values = [p[key] for p in points if p.get(key) is not None]
        out[key] = float(np.mean(values)) if values else None
        if key in ("accuracy", "auroc", "balanced_accuracy") and values:
            out[f"{key}_std"] = float(np.std(values))
    return out


def _text_forms(bench: Bench) -> list[dict[str, Any]]:
    """Full prompt vs brief form (no preamble), cache = 80% of nominal, one split each."""
    rows = []
    for name in QUALITY_DOMAINS:
        held, pool = _split(len(bench.dataset(name).nominal),
                            np.random.default_rng([bench.seed, 77]))
        for form in ("prompt", "brief"):
            nominal, anomalies = bench.vectors(name, form)
            test_x = np.concatenate([nominal[held], anomalies])
            test_y = np.r_[np.zeros(len(held), bool), np.ones(len(anomalies), bool)]
            rows.append({"domain": name, "form": form,
                         **_detect(nominal[pool], test_x, test_y)})
    return rows


def _thresholdtable(bench: Bench) -> dict[str, Any]:
    """VTOL, cache = random 80% of nominal: accuracy at the 75..95th LOO quantiles."""
    nominal, anomalies = bench.vectors("vtol")
    runs = []
    for s in range(bench.sizes.threshold_seeds):
        held, pool = _split(len(nominal), np.random.default_rng([bench.seed, s, 99]))
        test_x = np.concatenate([nominal[held], anomalies])
        test_y = np.r_[np.zeros(len(held), bool), np.ones(len(anomalies), bool)]
        runs.append(_detect(nominal[pool], test_x, test_y, QUANTILES))
    rows = []
    for q in QUANTILES:
        acc = [r[f"accuracy@{q:g}"] for r in runs]
        bal = [r[f"balanced_accuracy@{q:g}"] for r in runs]
        rows.append({"quantile": q, "accuracy": float(np.mean(acc)),
                     "accuracy_std": float(np.std(acc)), "balanced_accuracy": float(np.mean(bal)),
                     "paper_mpnet": PAPER_MPNET_VTOL[q]})
    return {"domain": "vtol", "cache_fraction": 1 - HOLDOUT, "seeds": len(runs),
            "auroc": float(np.mean([r["auroc"] for r in runs])), "rows": rows}


def plot_quality(domains: Mapping[str, Mapping[str, Any]], path: Path) -> None:
    """2 x 3 figure like ``fig:synthetic-results``: vs cache size (top), vs coverage (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    fig, axes = plt.subplots(2, len(domains), figsize=(4.2 * len(domains), 7), squeeze=False)
    for col, (name, d) in enumerate(domains.items()):
        for row, (key, xlabel) in enumerate((("cache_size", "experiences in cache (log)"),
                                             ("coverage", "nominal concept coverage (%)"))):
            ax = axes[row][col]
            points = [p for p in d[key] if p.get("accuracy") is not None]
            x = [p["cache_size"] if row == 0 else 100 * p["fraction"] for p in points]
            for metric, label, style in (("accuracy", "accuracy", "o-"), ("auroc", "AUROC", "s--"),
                                         ("balanced_accuracy", "balanced accuracy", "^-.")):
                y = np.array([p[metric] for p in points])
                err = np.array([p.get(f"{metric}_std", 0.0) for p in points])
                ax.plot(x, y, style, label=label)
                ax.fill_between(x, y - err, y + err, alpha=0.2)
            ax.axhline(d["n_anomaly"] / d["n_test"], color="grey", lw=0.8, ls=":",
                       label="all-anomaly accuracy")
            if row == 0:
                ax.set_xscale("log")
                ax.xaxis.set_major_formatter(ScalarFormatter())
                ax.xaxis.set_minor_formatter(NullFormatter())
            ax.set_ylim(0.0, 1.02)
            ax.set_xlabel(xlabel)
            ax.grid(True, alpha=0.3)
            ax.set_title(f"{name} ({d['n_nominal']} nominal, {d['n_anomaly']} anomalies)",
                         fontsize=10)
            if col == 0:
                ax.set_ylabel("accuracy / AUROC")
                ax.legend(loc="lower right")
    fig.suptitle(f"Fast anomaly detector, all-MiniLM-L6-v2, top-{K}, "
                 f"tau = {ALPHA:.0%} LOO quantile")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    log.info("wrote %s", path)


def render_quality(r: Mapping[str, Any]) -> str:
    out = []
    for name, d in r["domains"].items():
        head = (f"[quality] {name}: {d['n_nominal']} nominal, {d['n_anomaly']} anomalies, "
                f"test {d['n_test']}; mean (std) over {r['repeats']} splits")
        for key, label in (("cache_size", "cache fraction"), ("coverage", "concept coverage")):
            rows = [{label: f"{p['fraction']:.0%}", "cache size": round(p["cache_size"]),
                     **({"concepts": f"{p['concepts_covered']:.0%}"} if key == "coverage"
                        else {}),
                     "accuracy": _pm(p, "accuracy"), "balanced": _pm(p, "balanced_accuracy"),
                     "AUROC": _pm(p, "auroc"), "TPR": p.get("tpr"), "FPR": p.get("fpr")}
                    for p in d[key]]
            out.append(table(f"{head} -- vs {label}", rows))
    t = r["thresholds"]
    rows = [{"LOO quantile": f"{row['quantile']:.0%}",
             "accuracy": f"{row['accuracy']:.3f} ({row['accuracy_std']:.3f})",
             "balanced": row["balanced_accuracy"], "paper MPNet": row["paper_mpnet"]}
            for row in t["rows"]]
    out.append(table(f"[quality] threshold quantiles, VTOL, cache = random 80% of nominal, "
                      f"{t['seeds']} seeds, MiniLM (AUROC {t['auroc']:.3f}) vs paper MPNet", rows))
    rows = [{"domain": f["domain"], "text embedded": f["form"], "AUROC": f["auroc"],
             "accuracy": f["accuracy"], "balanced": f["balanced_accuracy"], "TPR": f["tpr"],
             "FPR": f["fpr"]} for f in r["text_forms"]]
    out.append(table("[quality] full prompt vs brief observation (no preamble), cache = 80% "
                      "of nominal, tau = 95% LOO quantile", rows))
    if "plot" in r:
        out.append(f"figure: {r['plot']}\n")
    return "\n".join(out)


def _pm(point: Mapping[str, Any], key: str) -> str:
    if point.get(key) is None:
        return "-"
    return f"{point[key]:.3f}" + (f" ({point[key + '_std']:.3f})" if key + "_std" in point else "")
