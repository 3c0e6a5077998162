"""A new captioner's wording, with the real model (issue 28): the drift monitor on real
verdicts of the synthetic domains, and ``aesop detector eval --adapt`` as a user runs it."""

from __future__ import annotations

import json
import random
import subprocess
import sys
from pathlib import Path

import pytest

from services.embedding.detector.cache import Labelled
from services.embedding.detector.drift import DriftMonitor
from services.embedding.detector.evaluation import EvalConfig, fit_structured, score_structured
from tools.scenes.base import Sample
from tools.scenes.registry import DOMAINS
from tools.scenes.wording import drift_set

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

ALPHA = 0.95


def labelled_of(samples: tuple[Sample, ...]) -> list[Labelled]:
    """The brief line with its detections, as a robot publishes it."""
    return [Labelled(s.brief, s.label == "anomaly", s.detections) for s in samples]


@pytest.fixture(scope="module")
def embedder():  # type: ignore[no-untyped-def]
    from services.embedding.models.loading import load_embedder
    from services.embedding.settings import DEFAULT_MODEL
    from tools.bench.detector.common import Memo

    return Memo(load_embedder(DEFAULT_MODEL))


@pytest.mark.parametrize("domain", ["warehouse", "vehicle", "vtol"])
def test_drift_is_never_raised_on_ten_thousand_nominal_frames_and_within_50_of_a_switch(
        embedder: object, domain: str) -> None:
    """Real combined verdicts (split-conformal at 0.95) of held-out nominal scenes in the
    domain's own wording, 10,000 frames drawn with repeats, then the same robot's frames in
    a new captioner's wording."""
    data = drift_set(DOMAINS[domain], n_nominal=400, n_calibration=200,
                     n_test_nominal=100, n_anomaly=20)
    calibration = labelled_of(data.calibration)
    cache, _ = fit_structured(embedder, labelled_of(data.nominal),  # type: ignore[arg-type]
                              calibration[:100], EvalConfig(alpha=ALPHA, method="conformal",
                                                            score="combined"))
    old = [bool(r.is_anomaly) for r in score_structured(
        cache, embedder, calibration[100:])]  # type: ignore[arg-type]
    new = [bool(r.is_anomaly) for r in score_structured(
        cache, embedder, [x for x in labelled_of(data.test) if not x.is_anomaly])]  # type: ignore[arg-type]
    monitor, rng = DriftMonitor(), random.Random(domain)

    def frame(verdicts: list[bool], wording: str) -> object:
        i = rng.randrange(len(verdicts))  # a scene seen again within the window counts once
        return monitor.observe("r", verdicts[i], 1 - ALPHA, scene=f"{wording} {i}")

    raised = [frame(old, "old") for _ in range(10_000)]
    assert not any(raised), f"old-wording flag rate {sum(old) / len(old):.3f}"
    after = [frame(new, "new") for _ in range(50)]
    assert any(getattr(r, "state", None) == "drift" for r in after), \
        f"new-wording flag rate {sum(new) / len(new):.3f}"


def aesop(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "tools.cli", *args], capture_output=True,
                          text=True, timeout=400, stdin=subprocess.DEVNULL)


def test_eval_adapt_accepts_the_new_wording_and_the_false_positive_promise_holds_again(
        tmp_path: Path) -> None:
    r = aesop("detector", "domains", "--drift", "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    sets = {part: str(tmp_path / f"warehouse-drift-{part}.jsonl")
            for part in ("nominal", "calibration", "reviewed", "test")}
    reviewed = Path(sets["reviewed"]).read_text().splitlines()
    sixty = tmp_path / "sixty.jsonl"
    sixty.write_text("\n".join(reviewed[:60]) + "\n")
    base = ["detector", "eval", "--nominal", sets["nominal"], "--calibration",
            sets["calibration"], "--test", sets["test"], "--method", "conformal",
            "--score", "combined", "--alpha", str(ALPHA), "--json"]
    r = aesop(*base)
    assert r.returncode == 0, r.stderr
    zero_shot = json.loads(r.stdout)
    assert zero_shot["fpr"] > 0.5  # the new wording: nearly every nominal frame flagged
    assert zero_shot["auroc"] > 0.8  # yet it still ranks (the p-values do not saturate)
    r = aesop(*base, "--adapt", str(sixty))
    assert r.returncode == 0, r.stderr
    adapted = json.loads(r.stdout)
    assert adapted["adapted"] == 60 and adapted["recalibrate"] == "window"
    assert adapted["calibrated_on"] == 60 and adapted["stale"] is False
    assert adapted["method"] == "conformal"
    assert adapted["fpr"] <= 1 - ALPHA + 0.01
    assert adapted["auroc"] > zero_shot["auroc"]
    r = aesop(*base, "--adapt", str(sixty), "--recalibrate", "stale")
    stale = json.loads(r.stdout)
    assert stale["stale"] is True and stale["fpr"] > 1 - ALPHA + 0.01  # the promise broken
    r = aesop(*base, "--adapt", str(tmp_path / "missing.jsonl"))
    assert r.returncode != 0 and "--adapt" in r.stderr
