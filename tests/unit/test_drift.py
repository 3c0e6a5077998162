"""The drift monitor, the held-out wordings and the re-learning policy (issue 28), pure."""

from __future__ import annotations

import random

import numpy as np
import pytest

from services.embedding.detector.adapt import ACCEPTED, recalibration, window
from services.embedding.detector.cache import Cache, CacheConfig, CalibrationScores
from services.embedding.detector.calibration import Calibration
from services.embedding.detector.drift import DriftMonitor
from shared.messages import Detection
from tools.scenes.registry import DOMAINS
from tools.scenes.wording import Captioner, drift_set, reword_phrase


def test_a_wording_switch_is_named_within_fifteen_frames_and_cleared_after() -> None:
    monitor = DriftMonitor()  # 50 verdicts, 1e-7
    rng = random.Random(0)
    for _ in range(200):  # nominal: about 1 in 20 flagged, as alpha 0.95 promises
        assert monitor.observe("r1", rng.random() < 0.05, 0.05, ["a box"]) is None
    reports = [monitor.observe("r1", True, 0.05, ["a carton", "one crate"]) for _ in range(50)]
    frame = next(i for i, r in enumerate(reports, 1) if r is not None)
    assert frame <= 15
    report = reports[frame - 1]
    assert report is not None and report.state == "drift" and report.phrases[0] == "a carton"
    assert "new wording" in report.message and "a carton" in report.message
    assert monitor.drifting() == ["r1"] and monitor.current("r1") is not None
    assert all(r is None for r in reports[frame:])  # named once
    cleared = [monitor.observe("r1", False, 0.05) for _ in range(50)]
    assert [r.state for r in cleared if r is not None] == ["cleared"]
    assert monitor.drifting() == [] and monitor.current("r1") is None


def test_one_anomaly_that_stays_in_view_is_one_scene_not_drift() -> None:
    monitor = DriftMonitor()
    for _ in range(600):  # a minute of one flagged scene at 10 Hz
        assert monitor.observe("r1", True, 0.05, ["a fire"], scene="fire on the belt") is None
    assert monitor.drifting() == []
    reports = [monitor.observe("r1", True, 0.05, ["a carton"], scene=f"s{i}") for i in range(20)]
    assert [r.state for r in reports if r is not None] == ["drift"]  # new scenes do


def test_one_robot_drifting_leaves_the_others_and_nothing_promised_is_not_tested() -> None:
    monitor = DriftMonitor(window=20)
    for _ in range(20):
        monitor.observe("r1", True, 0.05, ["a carton"])
        monitor.observe("r2", False, 0.05)
        assert monitor.observe("r3", True, None) is None  # uncalibrated: fail-safe flags
    assert monitor.drifting() == ["r1"]


def test_ten_thousand_nominal_verdicts_at_the_promised_rate_raise_no_drift() -> None:
    monitor = DriftMonitor()
    rng = random.Random(1)
    assert not any(monitor.observe("r1", rng.random() < 0.06, 0.05) for _ in range(10_000))


def test_a_new_captioner_writes_each_concept_one_way_and_keeps_labels() -> None:
    domain = DOMAINS["warehouse"]
    data = drift_set(domain, n_nominal=40, n_calibration=10, n_reviewed=10,
                     n_test_nominal=10, n_anomaly=10)
    captioner = Captioner(domain)
    assert [s.label for s in data.test] == ["nominal"] * 10 + ["anomaly"] * 10
    old = {d for s in data.nominal for d in s.detections}
    for sample in data.reviewed + data.test:
        assert sample.detections == tuple(captioner.phrase(c) for c in sample.concepts)
        assert sample.brief.startswith(captioner.style.split("{")[0])
    assert not {d for s in data.test for d in s.detections} <= old  # words never seen
    assert drift_set(domain, n_nominal=40, n_calibration=10, n_reviewed=10,
                     n_test_nominal=10, n_anomaly=10) == data  # deterministic
    assert reword_phrase("a red box on the ground", random.Random(3)) != "a red box on the ground"


def accepted_cache(n_accepted: int, alpha: float = 0.9) -> Cache:
    """A cache of 30 plain scenes and ``n_accepted`` accepted ones (each a direction of its
    own, with a phrase of its own), calibrated at ``alpha`` on the plain ones."""
    cache = Cache(CacheConfig("c", "m", 3, k=1))
    n = 30 + n_accepted
    rng = np.random.default_rng(0)
    vectors = np.vstack([np.tile([1.0, 0.0, 0.0], (30, 1)),
                         rng.normal(size=(n_accepted, 3)) + [0.0, 3.0, 0.0]])
    phrases = ["box"] * 30 + [f"carton {i}" for i in range(n_accepted)]
    meta = [{}] * 30 + [{ACCEPTED: {"robot": "r1"}}] * n_accepted
    found = {p: v for p, v in zip(phrases, rng.normal(size=(n, 3)), strict=True)}
    cache.apply(cache.plan_add(vectors, ids=[str(i) for i in range(n)], texts=[None] * n,
                               metadata=meta,
                               detections=[(Detection(label=p),) for p in phrases],
                               detection_vectors=found))
    cal = Calibration("loo-quantile", -1.0, alpha, 30)
    cache.apply(cache.plan_calibration(cal, CalibrationScores.of(np.full(30, -1.0),
                                                                  np.full(30, -1.0))))
    return cache


def test_the_window_recalibrates_on_the_latest_accepted_scenes_at_the_same_alpha() -> None:
    cache = accepted_cache(40)
    labels = window(cache, 25)
    assert labels == sorted(cache.experiences)[-25:]
    op = recalibration(cache, 25)
    assert op is not None and op.calibration.method == "conformal"
    assert op.calibration.alpha == 0.9 and op.calibration.n == 25
    assert op.scores is not None and len(op.scores.detection) == 25
    observation, _, _ = cache.loo_members(labels)
    # the conformal quantile of the window's leave-one-out scores, ceil(26 * 0.9) = 24th
    assert op.calibration.threshold == pytest.approx(np.sort(observation)[23])
    cache.apply(op)
    assert cache.stale is False


def test_leave_one_out_of_some_members_is_the_whole_caches_for_those() -> None:
    cache = accepted_cache(40)
    labels = window(cache, 10)
    observation, detection, pair = cache.loo_members(labels)
    where = [sorted(cache.experiences).index(label) for label in labels]
    assert np.allclose(observation, cache.loo_scores()[where])
    assert np.allclose(detection, cache.loo_detection_scores()[where]) and pair is None


def test_too_short_a_window_keeps_the_calibration() -> None:
    assert recalibration(accepted_cache(12), 50) is None  # 2/(n+1) < 0.1 needs n >= 20
    assert recalibration(Cache(CacheConfig("c", "m", 2, k=1)), 50) is None  # uncalibrated


def test_eval_adapt_defaults_to_the_service_policy() -> None:
    import argparse

    from services.embedding.settings import EmbeddingAdapt
    from tools.detector import register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["detector", "eval", "--nominal", "n", "--test", "t"])
    assert (args.recalibrate, args.window) == (EmbeddingAdapt().recalibrate,
                                               EmbeddingAdapt().window)


def test_metrics_show_each_drifting_robot() -> None:
    from prometheus_client import CollectorRegistry, generate_latest

    from services.embedding.metrics import EmbeddingMetrics

    registry = CollectorRegistry()
    metrics = EmbeddingMetrics(registry, service=None)  # type: ignore[arg-type]
    monitor = DriftMonitor(window=10)
    metrics.drifting.source = monitor.drifting
    for i in range(10):
        monitor.observe("r1", True, 0.05, scene=f"s{i}")
        monitor.observe("r2", False, 0.05, scene=f"s{i}")
    text = generate_latest(registry).decode()
    assert 'aesop_embedding_drifting{robot="r1"} 1.0' in text
    assert 'robot="r2"' not in text
