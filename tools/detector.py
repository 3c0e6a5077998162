"""``aesop detector eval|domains``: the fast detector offline, on labelled JSONL sets or a
recorded flight, and the synthetic domains written as such sets."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tools import progress
from tools.commands import CliError, add_url_argument, emit


def register(sub: argparse._SubParsersAction) -> None:
    detector = sub.add_parser("detector", help="offline tools for the fast anomaly detector")
    dsub = detector.add_subparsers(dest="detector_command", required=True)
    ev = dsub.add_parser("eval", help="evaluate the detector on labelled JSONL text sets")
    ev.add_argument("--nominal", type=Path, help="JSONL of nominal experiences (required "
                    "but with --recording against a running cache: --cache)")
    ev.add_argument("--calibration", type=Path, help="JSONL labelled calibration set")
    what = ev.add_mutually_exclusive_group(required=True)
    what.add_argument("--test", type=Path, help="JSONL labelled test set")
    what.add_argument("--recording", type=Path, metavar="FILE.mcap",
                      help="re-score a recorded flight: each observation's recorded verdict "
                           "and today's, and where they differ")
    ev.add_argument("--cache", help="with --recording: score against this cache of a running "
                    "embedding service (--url) instead of --nominal")
    add_url_argument(ev)
    ev.add_argument("--robot", help="with --recording: only this robot's observations")
    ev.add_argument("--changed-only", action="store_true",
                    help="with --recording: list only the observations whose verdict changed")
    ev.add_argument("--k", type=int, default=5,
                    help="neighbours a score averages over (default 5)")
    ev.add_argument("--alpha", type=float, default=0.95,
                    help="the calibration's quantile: about 1 - alpha of nominal scenes "
                         "flagged (default 0.95)")
    ev.add_argument("--tpr", type=float, default=0.9,
                    help="target TPR for tpr-target (default 0.9)")
    ev.add_argument("--method", choices=["loo-quantile", "conformal", "tpr-target"],
                    default="loo-quantile", help="how tau is calibrated (default "
                    "loo-quantile: eq. 2's leave-one-out quantile)")
    ev.add_argument("--score", choices=["topk", "mahalanobis", "detections", "combined"],
                    default="topk", help="detections, combined: each line's 'detections' "
                    "against the nominal set's (combined: with topk, as conformal p-values)")
    ev.add_argument("--pairs", action="store_true",
                    help="with --score combined: pairs of detections no nominal line holds "
                         "together as a third component")
    ev.add_argument("--adapt", type=Path, metavar="FILE", help="JSONL whose nominal lines "
                    "are accepted, in order, as reviewed scenes before the test set is "
                    "scored, as the service accepts one batch review of them (then the "
                    "calibration by --recalibrate)")
    ev.add_argument("--recalibrate", choices=["window", "stale"], default="window",
                    help="with --adapt: the service's policy (AESOP_EMBEDDING_ADAPT__RECALIBRATE; "
                    "default window)")
    ev.add_argument("--window", type=int, default=100, help="with --adapt and --recalibrate "
                    "window: the accepted scenes calibrated on (AESOP_EMBEDDING_ADAPT__WINDOW; "
                    "default 100)")
    ev.add_argument("--model", default=None, help="embedding model (default: all-MiniLM-L6-v2)")
    ev.add_argument("--json", action="store_true",
                    help="print the result as one JSON object instead of tables")
    ev.set_defaults(func=cmd_detector_eval)

    dd = dsub.add_parser("domains", help="write the synthetic domains as JSONL sets for "
                         "eval: <domain>-nominal.jsonl (80%% of the nominal samples) and "
                         "<domain>-test.jsonl (the other 20%% and every anomaly), with "
                         "their detections")
    dd.add_argument("--out", type=Path, required=True, help="the folder")
    dd.add_argument("--seed", type=int, default=0,
                    help="random seed of what is drawn (default 0)")
    dd.add_argument("--form", choices=["brief", "prompt"], default="brief",
                    help="the text: the observation (brief) or the paper's whole prompt")
    dd.add_argument("--drift", action="store_true", help="instead, each synthetic domain "
                    "before and after a new captioner's wording: <domain>-drift-nominal, "
                    "-calibration (the old wording), -reviewed (new nominal scenes, for "
                    "eval --adapt) and -test (new wording, with every anomaly)")
    dd.set_defaults(func=cmd_detector_domains)


def cmd_detector_eval(args: argparse.Namespace) -> int:
    from services.embedding.detector.errors import DetectorError
    from services.embedding.detector.evaluation import EvalConfig, evaluate, read_jsonl
    from services.embedding.models.base import EmbedderError
    from services.embedding.models.loading import load_embedder
    from services.embedding.settings import DEFAULT_MODEL
    from tools.counted import Counted

    for name in ("nominal", "calibration", "test", "recording", "adapt"):
        path = getattr(args, name)
        if path is not None and not path.is_file():
            raise CliError(f"--{name}: no such file: {path}")
    if not 0 < args.alpha < 1:
        raise CliError("--alpha must be in (0, 1)")
    if args.k < 1:
        raise CliError("--k must be at least 1")
    if args.window < 1:
        raise CliError("--window must be at least 1")
    if args.adapt is not None and args.recording is not None:
        raise CliError("--adapt goes with --test, not --recording")
    if args.recording is None and (args.cache or args.robot or args.changed_only):
        raise CliError("--cache, --robot and --changed-only go with --recording")
    if args.recording is not None:
        from tools.recording.cli import rescore_recording

        return rescore_recording(args)
    if args.nominal is None:
        raise CliError("--nominal is required (the JSONL of nominal experiences)")
    try:
        config = EvalConfig(k=args.k, alpha=args.alpha, method=args.method, score=args.score,
                            tpr=args.tpr, pairs=args.pairs, recalibrate=args.recalibrate,
                            window=args.window)
        nominal = read_jsonl(args.nominal)
        test = read_jsonl(args.test)
        calibration = read_jsonl(args.calibration) if args.calibration else []
        adapt = read_jsonl(args.adapt) if args.adapt else []
        with progress.shown("aesop detector eval"):
            progress.step(f"loading {args.model or DEFAULT_MODEL}")
            embedder = Counted(load_embedder(args.model or DEFAULT_MODEL))
            progress.step(f"embedding and scoring {len(nominal)} nominal, {len(calibration)} "
                          f"calibration, {len(adapt)} adapted and {len(test)} test lines")
            result = evaluate(embedder, nominal, test, calibration, config, adapt)
    except (DetectorError, EmbedderError, ValueError) as exc:
        raise CliError(str(exc)) from None
    emit(result, args.json)
    return 0


def cmd_detector_domains(args: argparse.Namespace) -> int:
    from tools.scenes.base import write_jsonl
    from tools.scenes.registry import DOMAINS, generate

    if args.drift:
        return _drift_domains(args)
    for name in DOMAINS:
        nominal, test = generate(name, seed=args.seed).split_for_eval(args.seed)
        write_jsonl(args.out / f"{name}-nominal.jsonl", nominal, args.form)
        write_jsonl(args.out / f"{name}-test.jsonl", test, args.form)
        print(f"{name}: {len(nominal)} nominal, {len(test)} test -> {args.out}",
              file=sys.stderr)
    return 0


def _drift_domains(args: argparse.Namespace) -> int:
    from tools.scenes.base import write_jsonl
    from tools.scenes.registry import DOMAINS
    from tools.scenes.wording import drift_set

    for name in ("warehouse", "vehicle", "vtol"):
        data = drift_set(DOMAINS[name], seed=args.seed)
        for part in ("nominal", "calibration", "reviewed", "test"):
            write_jsonl(args.out / f"{name}-drift-{part}.jsonl", getattr(data, part), args.form)
        print(f"{name}: {len(data.nominal)} nominal, {len(data.calibration)} calibration "
              f"(old wording); {len(data.reviewed)} reviewed, {len(data.test)} test (new "
              f"wording) -> {args.out}", file=sys.stderr)
    return 0
