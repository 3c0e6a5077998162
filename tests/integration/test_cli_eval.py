"""``aesop detector eval`` as a user runs it: real model, JSONL files, one JSON object out."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

KEYS = {"auroc", "threshold", "tpr", "fpr", "accuracy", "balanced_accuracy", "n_nominal",
        "n_calibration", "n_test", "method", "k", "alpha", "model"}
OBJECTS = ["a cardboard package", "a padded envelope", "a plastic tote", "a shrink-wrapped box",
           "a barcode label", "a small parcel", "a shipping crate", "a sealed carton"]
PLACES = ["on the conveyor belt", "next to the storage shelf", "on a pallet"]
ANOMALIES = ["a smoking lithium battery on the conveyor belt", "a leaking bleach bottle",
             "two forklifts in collision", "a fire next to the storage shelf",
             "a person lying on the conveyor belt", "a broken glass bottle with sharp shards"]


def write(path: Path, rows: list[tuple[str, str]]) -> Path:
    path.write_text("".join(json.dumps({"text": t, "label": lab}) + "\n" for t, lab in rows))
    return path


def aesop(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "tools.cli", *args], capture_output=True,
                          text=True, timeout=240, stdin=subprocess.DEVNULL)


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("eval")
    nominal = [(f"{o} {p}", "nominal") for o in OBJECTS for p in PLACES]
    return {
        "nominal": write(d / "nominal.jsonl", nominal[::2]),
        "calibration": write(d / "cal.jsonl", nominal[1::4] + [(a, "anomaly") for a in
                                                              ANOMALIES[:3]]),
        "test": write(d / "test.jsonl", nominal[3::4] + [(a, "anomaly") for a in ANOMALIES[3:]]),
        "bad": write(d / "bad.jsonl", [("x", "weird")]),
    }


@pytest.mark.parametrize("method", ["loo-quantile", "conformal", "tpr-target"])
def test_eval_prints_exactly_one_json_object(files: dict[str, Path], method: str) -> None:
    args = ["detector", "eval", "--nominal", str(files["nominal"]), "--test", str(files["test"]),
            "--calibration", str(files["calibration"]), "--method", method, "--k", "2",
            "--alpha", "0.75", "--json"]
    r = aesop(*args)
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout)  # the whole of stdout is one object
    assert set(result) == KEYS
    assert result["method"] == method and result["k"] == 2
    assert result["n_nominal"] == 12 and result["n_calibration"] == 9 and result["n_test"] == 9
    assert result["model"] == "sentence-transformers/all-MiniLM-L6-v2"
    assert 0.0 <= result["auroc"] <= 1.0 and 0.0 <= result["accuracy"] <= 1.0
    # overtly abnormal warehouse concepts are far from packages on a conveyor belt
    assert result["auroc"] > 0.8
    # stderr not a terminal: a line a step, none a batch of texts embedded
    steps = [line for line in r.stderr.splitlines() if line.startswith("aesop detector eval")]
    assert [re.sub(r"\[\d+:\d\d\] ", "", line) for line in steps] == [
        "aesop detector eval loading sentence-transformers/all-MiniLM-L6-v2",
        "aesop detector eval embedding and scoring 12 nominal, 9 calibration, 0 adapted and 9 "
        "test lines"], r.stderr


def test_eval_mahalanobis_runs(files: dict[str, Path]) -> None:
    r = aesop("detector", "eval", "--nominal", str(files["nominal"]), "--test",
              str(files["test"]), "--score", "mahalanobis", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["threshold"] > 0  # a distance, not a negated similarity


@pytest.mark.parametrize(("extra", "message"), [
    (["--alpha", "1.5"], "--alpha"),
    (["--k", "0"], "--k"),
    (["--method", "conformal"], "--calibration"),
    (["--model", "no-such-model-anywhere"], "no-such-model-anywhere"),
])
def test_eval_user_errors_exit_non_zero_with_a_message(files: dict[str, Path],
                                                        extra: list[str], message: str) -> None:
    r = aesop("detector", "eval", "--nominal", str(files["nominal"]), "--test",
              str(files["test"]), *extra, "--json")
    assert r.returncode == 2 and r.stdout == ""
    assert message in r.stderr and "Traceback" not in r.stderr


def test_eval_bad_files(files: dict[str, Path], tmp_path: Path) -> None:
    r = aesop("detector", "eval", "--nominal", str(tmp_path / "missing.jsonl"), "--test",
              str(files["test"]))
    assert r.returncode == 2 and "missing.jsonl" in r.stderr
    r = aesop("detector", "eval", "--nominal", str(files["bad"]), "--test", str(files["test"]))
    assert r.returncode == 2 and "bad.jsonl:1" in r.stderr


# --------------------------------------------------------------------------- structured scores
# (issue 12: an odd object among nominal ones is averaged away in the whole observation,
# not in its own detection; on the synthetic domains that lifts AUROC, see the README)

ODD = ["a smoking lithium battery", "a leaking bleach bottle", "a broken glass bottle",
       "a live snake", "a burning cigarette"]


def scene(objects: list[str]) -> dict[str, object]:
    return {"text": "\n".join(objects), "detections": [{"label": o} for o in objects]}


@pytest.fixture(scope="module")
def structured(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    import itertools

    d = tmp_path_factory.mktemp("structured")
    triples = [list(t) for t in itertools.combinations(OBJECTS, 3)]  # 56 nominal scenes
    nominal = [scene(t) | {"label": "nominal"} for t in triples[::2]]
    test = [scene(t) | {"label": "nominal"} for t in triples[1::2]]
    test += [scene(t[:2] + [odd]) | {"label": "anomaly"} for t, odd in
             zip(triples[1::2], ODD * 6, strict=False)]
    out = {}
    for name, rows in (("nominal", nominal), ("test", test)):
        out[name] = d / f"{name}.jsonl"
        out[name].write_text("".join(json.dumps(r) + "\n" for r in rows))
    return out


def test_each_detection_is_scored_and_every_odd_object_flagged(
        structured: dict[str, Path]) -> None:
    got = {}
    for score in ("topk", "detections", "combined"):  # 28 nominal scenes: alpha 0.9 (below)
        r = aesop("detector", "eval", "--nominal", str(structured["nominal"]), "--test",
                  str(structured["test"]), "--score", score, "--alpha", "0.9", "--json")
        assert r.returncode == 0, r.stderr
        got[score] = json.loads(r.stdout)
    assert got["detections"]["nominal_detections"] == len(OBJECTS)
    assert got["detections"]["score"] == "detections" and got["combined"]["score"] == "combined"
    assert got["detections"]["auroc"] >= got["topk"]["auroc"]  # (the domains: README)
    assert got["combined"]["auroc"] >= got["topk"]["auroc"]
    # flagged at p < 1 - alpha: few nominal scenes, every odd object
    assert got["combined"]["fpr"] <= 0.2 and got["combined"]["tpr"] == 1.0
    # at 0.95 the 28 scenes are too few for the corrected p-value to ever be that small
    r = aesop("detector", "eval", "--nominal", str(structured["nominal"]), "--test",
              str(structured["test"]), "--score", "combined", "--json")
    assert r.returncode == 2 and "28 nominal calibration scores with detections cannot flag " \
        "anything" in r.stderr


def test_pairs_flag_two_nominal_objects_never_seen_together(tmp_path: Path) -> None:
    # nominal: each object beside its neighbours in OBJECTS (a ring); anomalous: two
    # nominal objects far apart in it, never seen together; one text for all, so that
    # only the pairs can tell
    n = len(OBJECTS)

    def two(a: int, b: int, label: str) -> dict[str, object]:
        return scene([OBJECTS[a % n], OBJECTS[b % n]]) | {"text": "the loading bay",
                                                          "label": label}

    nominal = [two(i, i + 1, "nominal") for i in range(4 * n)]
    test = [two(i, i + 1, "nominal") for i in range(n)]
    test += [two(i, i + n // 2, "anomaly") for i in range(n)]
    paths = {}
    for name, rows in (("nominal", nominal), ("test", test)):
        paths[name] = tmp_path / f"{name}.jsonl"
        paths[name].write_text("".join(json.dumps(r) + "\n" for r in rows))
    got = {}
    for pairs in ([], ["--pairs"]):
        r = aesop("detector", "eval", "--nominal", str(paths["nominal"]), "--test",
                  str(paths["test"]), "--score", "combined", "--alpha", "0.9", "--json", *pairs)
        assert r.returncode == 0, r.stderr
        got[bool(pairs)] = json.loads(r.stdout)
    assert got[True]["pairs"] is True and got[False]["pairs"] is False
    assert got[False]["tpr"] == 0.0  # every object is nominal on its own
    assert got[True]["tpr"] == 1.0 and got[True]["fpr"] == 0.0
    r = aesop("detector", "eval", "--nominal", str(paths["nominal"]), "--test",
              str(paths["test"]), "--score", "detections", "--pairs")
    assert r.returncode == 2 and "--pairs" in r.stderr and "Traceback" not in r.stderr


def test_structured_user_errors(structured: dict[str, Path], files: dict[str, Path]) -> None:
    r = aesop("detector", "eval", "--nominal", str(structured["nominal"]), "--test",
              str(structured["test"]), "--calibration", str(structured["test"]),
              "--score", "combined", "--method", "tpr-target", "--json")
    assert r.returncode == 2 and "--method" in r.stderr and "Traceback" not in r.stderr
    r = aesop("detector", "eval", "--nominal", str(files["nominal"]), "--test",
              str(structured["test"]), "--score", "detections", "--json")
    assert r.returncode == 2 and "needs 'detections'" in r.stderr and "Traceback" not in r.stderr
