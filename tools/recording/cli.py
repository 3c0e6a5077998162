"""The ``aesop`` commands on recordings: their flags and handlers.

``record``, ``replay``, ``cache import``, ``cache calibrate``, and ``detector eval --recording``
(:mod:`tools.detector` calls it). Each turns user errors into a
:class:`~tools.commands.CliError`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from tools import progress
from tools.commands import ROBOT_LOGIN, CliError, add_url_argument, emit, joined, not_joined


def register(sub: argparse._SubParsersAction) -> None:
    rec = sub.add_parser("record", help="the stack's Zenoh topics into an MCAP file "
                         "(Foxglove opens it); Ctrl-C stops")
    rec.add_argument("--out", type=Path, default=None,
                     help="the file (default ./aesop-<robot or all>-<UTC time>.mcap)")
    rec.add_argument("--robot", help="only this robot (default: every robot)")
    rec.add_argument("--topics", nargs="+", metavar="TOPIC",
                     help="only these: observation anomaly state plan reasoner/request "
                          "reasoner/decision event regions vehicle/state vehicle/setpoint "
                          "(default: all)")
    rec.add_argument("--connect", action="append", metavar="ENDPOINT",
                     help="Zenoh endpoint (repeatable; default: AESOP_ZENOH_CONNECT)")
    rec.set_defaults(func=record_command)

    rp = sub.add_parser("replay", help="publish a recording on Zenoh again with its timing "
                        "(the dashboard and aesop watch show the flight); Ctrl-C stops")
    rp.add_argument("file", type=Path, metavar="FILE.mcap",
                    help="a recording of `aesop record` (or any MCAP of the stack's keys)")
    rp.add_argument("--speed", type=float, default=1.0, help="time scale (2: twice as fast)")
    rp.add_argument("--topics", nargs="+", metavar="TOPIC",
                    help="only these (e.g. observation: a live stack's detector sees the "
                         "recorded scenes; default: all)")
    rp.add_argument("--loop", action="store_true", help="start over at the end")
    rp.add_argument("--connect", action="append", metavar="ENDPOINT",
                    help="Zenoh endpoint (repeatable; default: AESOP_ZENOH_CONNECT)")
    rp.add_argument("--listen", action="append", metavar="ENDPOINT",
                    help="listen here instead, for a dashboard to connect to (repeatable)")
    rp.set_defaults(func=replay_command)

    ca = sub.add_parser("cache", help="nominal experience caches of a running embedding service")
    casub = ca.add_subparsers(dest="cache_command", required=True)
    ci = casub.add_parser("import", help="add a recorded flight's distinct scenes as nominal "
                          "experiences (then calibrate)")
    ci.add_argument("--recording", type=Path, required=True, action="append",
                    metavar="FILE.mcap", help="a recorded flight (repeatable)")
    ci.add_argument("--cache", required=True, help="the cache (created if there is none)")
    ci.add_argument("--since", help="from here: seconds from each recording's first "
                    "observation (12.5) or an ISO 8601 time (UTC unless it says)")
    ci.add_argument("--until", help="up to here, as --since")
    ci.add_argument("--robot", help="only this robot's observations (default: all)")
    ci.add_argument("--model", default=None, help="embedding model of a new cache")
    ci.add_argument("--k", type=int, default=None,
                    help="neighbours a new cache scores with (default 5; the paper's "
                         "hardware cache: 1)")
    add_url_argument(ci)
    ci.add_argument("--json", action="store_true",
                    help="print the result as one JSON object instead of tables")
    ci.set_defaults(func=cache_import_command)
    cc = casub.add_parser("calibrate", help="tau of a cache from its own experiences (eq. 2: "
                          "the alpha quantile of the leave-one-out scores)")
    cc.add_argument("--cache", required=True, help="the cache to calibrate")
    cc.add_argument("--alpha", type=float, default=0.95,
                    help="the quantile: about 1 - alpha of nominal scenes flagged "
                         "(default 0.95)")
    cc.add_argument("--pairs", action="store_true",
                    help="score pairs of detections too (two nominal objects never seen "
                         "together)")
    add_url_argument(cc)
    cc.add_argument("--json", action="store_true",
                    help="print the result as one JSON object instead of tables")
    cc.set_defaults(func=cache_calibrate_command)


def record_command(args: argparse.Namespace) -> int:
    import threading
    import time

    import zenoh

    from shared.process import stop_on
    from shared.settings import BusSettings
    from tools.recording.record import key_exprs, record

    try:
        key_exprs(args.robot, args.topics)
    except ValueError as exc:
        raise CliError(f"--topics: {exc}") from None
    overrides = {"zenoh_connect": args.connect} if args.connect else {}
    settings = BusSettings(**overrides)
    out = args.out or Path(f"aesop-{args.robot or 'all'}-"
                           f"{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}.mcap")
    if out.parent != Path() and not out.parent.is_dir():
        raise CliError(f"--out: no directory {out.parent}")
    joined(settings, "record")  # exits 2 unless the endpoints let it in (no file made)
    stop = threading.Event()
    stop_on(stop)  # also where SIGINT started ignored
    try:
        totals = record(settings, out, robot=args.robot, wanted=args.topics, stop=stop,
                        say=lambda line: print(line, file=sys.stderr, flush=True))
    except zenoh.ZError as exc:
        raise not_joined(exc) from None
    rate = totals.messages / totals.seconds if totals.seconds > 0 else 0.0
    print(f"recorded {totals.messages} messages ({totals.bytes / 1e3:.1f} kB, {rate:.1f} "
          f"messages/s) in {totals.seconds:.1f} s into {out}", file=sys.stderr)
    return 0


def replay_command(args: argparse.Namespace) -> int:
    import threading

    import zenoh

    from shared.process import stop_on
    from shared.settings import BusSettings
    from tools.recording.recorded import RecordingError, check_recording
    from tools.recording.replay import replay, topic_filter

    try:
        topic_filter(args.topics)
    except ValueError as exc:
        raise CliError(f"--topics: {exc}") from None
    if not args.speed > 0:
        raise CliError("--speed must be > 0")
    try:
        check_recording(args.file)
    except RecordingError as exc:
        raise CliError(str(exc)) from None
    overrides = {k: v for k, v in (("zenoh_connect", args.connect),
                                   ("zenoh_listen", args.listen)) if v}
    settings = BusSettings(**overrides)
    # exits 2 unless the endpoints let it in (a session that met no one published the
    # recording into nothing, for ever with --loop)
    joined(settings, "replay", ROBOT_LOGIN)
    stop = threading.Event()
    stop_on(stop)
    try:
        done = replay(settings, args.file, speed=args.speed, wanted=args.topics,
                      loop=args.loop, stop=stop,
                      say=lambda line: print(line, file=sys.stderr, flush=True))
    except zenoh.ZError as exc:
        raise not_joined(exc) from None
    print(f"replayed {done.messages} messages ({done.bytes / 1e3:.1f} kB) in "
          f"{done.seconds:.1f} s", file=sys.stderr)
    return 0


def _admin_token() -> str | None:
    return os.environ.get("AESOP_ADMIN_TOKEN") or None


def _service_failure(exc: Exception, url: str) -> CliError:
    """A service that answered with an error, or none that answered."""
    import httpx

    if isinstance(exc, httpx.TransportError):
        return CliError(f"no embedding service at {url} ({exc.__class__.__name__}): is the "
                        "stack up? (--url)")
    return CliError(str(exc))


def cache_import_command(args: argparse.Namespace) -> int:
    import asyncio

    import httpx

    from services.embedding.client import EmbeddingClient
    from shared.client import ServiceError
    from tools.recording.importer import import_recording
    from tools.recording.recorded import RecordingError, check_recording

    def embedded(job: Any) -> None:  # each poll of a job: on the live line only
        if job.total:
            progress.count(job.done, job.total, "scenes embedded")

    async def run() -> Any:
        async with EmbeddingClient(args.url, token=_admin_token(), timeout_s=120) as client:
            return await import_recording(client, args.cache, args.recording,
                                          robot=args.robot, since=args.since,
                                          until=args.until, model=args.model, k=args.k,
                                          say=progress.say, progress=embedded)
    try:
        for path in args.recording:
            check_recording(path)
        with progress.shown("aesop cache import"):
            done = asyncio.run(run())
    except RecordingError as exc:
        raise CliError(str(exc)) from None
    except (ServiceError, httpx.TransportError) as exc:
        raise _service_failure(exc, args.url) from None
    result = {"cache": args.cache, "observations": done.observations, "scenes": done.scenes,
              "already_in_cache": done.already, "added": done.added, "size": done.size,
              "version": done.version}
    emit(result, args.json)
    if not args.json:
        print(f"next: aesop cache calibrate --cache {args.cache}", file=sys.stderr)
    return 0


def cache_calibrate_command(args: argparse.Namespace) -> int:
    import asyncio

    import httpx

    from services.embedding.client import EmbeddingClient
    from shared.client import ServiceError

    if not 0 < args.alpha < 1:
        raise CliError("--alpha must be in (0, 1)")

    async def run() -> Any:
        async with EmbeddingClient(args.url, token=_admin_token(), timeout_s=120) as client:
            return await client.calibrate(args.cache, "loo-quantile", alpha=args.alpha,
                                          pairs=args.pairs)
    try:
        done = asyncio.run(run())
    except (ServiceError, httpx.TransportError) as exc:
        raise _service_failure(exc, args.url) from None
    emit({"cache": done.cache, "method": done.method, "alpha": done.alpha,
          "threshold": done.threshold, "n": done.n, "pairs": done.pairs,
          "version": done.version}, args.json)
    return 0


def rescore_recording(args: argparse.Namespace) -> int:
    """``aesop detector eval --recording``: see :mod:`tools.recording.rescore`."""
    from tools.recording.recorded import (
        RecordingError,
        check_recording,
        observations,
        verdicts,
    )
    from tools.recording.rescore import compare, distinct_scenes, summary, table

    if (args.nominal is None) == (args.cache is None):
        raise CliError("--recording needs either --nominal (a JSONL set to build a cache "
                       "from) or --cache (a cache of the running service at --url)")
    try:
        check_recording(args.recording)
        recorded = list(observations(args.recording, robot=args.robot))
        old = verdicts(args.recording, args.robot)
    except RecordingError as exc:
        raise CliError(str(exc)) from None
    if not recorded:
        raise CliError(f"{args.recording} has no observations"
                       + (f" of robot {args.robot}" if args.robot else ""))
    scenes = distinct_scenes(recorded)
    print(f"{len(recorded)} observations, {len(scenes)} distinct scenes, {len(old)} recorded "
          "verdicts", file=sys.stderr)
    with progress.shown("aesop detector eval"):
        if args.cache is not None:
            progress.step(f"scoring {len(scenes)} distinct scenes against cache {args.cache} "
                          f"at {args.url}")
            new, threshold, source = _scores_over_rest(args, scenes)
        else:
            new, threshold, source = _scores_offline(args, scenes)
    rows = compare(recorded, old, new)
    result = {"recording": str(args.recording), "against": source} | summary(rows, threshold)
    if args.json:
        print(json.dumps(result | {"rows": [r.row() for r in rows
                                            if r.changed or not args.changed_only]},
                         allow_nan=False))
        return 0
    print(table(rows, only_changed=args.changed_only))
    print()
    emit(result, False)
    return 0


def _scores_offline(args: argparse.Namespace, scenes: list[Any]
                    ) -> tuple[dict[Any, Any], float | None, str]:
    from services.embedding.detector.errors import DetectorError
    from services.embedding.detector.evaluation import EvalConfig, read_jsonl
    from services.embedding.models.base import EmbedderError
    from services.embedding.models.loading import load_embedder
    from services.embedding.settings import DEFAULT_MODEL
    from tools.counted import Counted
    from tools.recording.rescore import scores_offline

    try:
        config = EvalConfig(k=args.k, alpha=args.alpha, method=args.method, score=args.score,
                            tpr=args.tpr, pairs=args.pairs)
        calibration = read_jsonl(args.calibration) if args.calibration else []
        progress.step(f"loading {args.model or DEFAULT_MODEL}")
        embedder = Counted(load_embedder(args.model or DEFAULT_MODEL))
        progress.step(f"embedding {args.nominal} and scoring {len(scenes)} distinct scenes")
        new, threshold, method = scores_offline(embedder, read_jsonl(args.nominal),
                                                calibration, config, scenes)
    except (DetectorError, EmbedderError, ValueError) as exc:
        raise CliError(str(exc)) from None
    return new, threshold, f"{args.nominal} ({embedder.name}, {method})"


def _scores_over_rest(args: argparse.Namespace, scenes: list[Any]
                      ) -> tuple[dict[Any, Any], float | None, str]:
    import asyncio

    import httpx

    from services.embedding.client import EmbeddingClient
    from shared.client import ServiceError
    from tools.recording.rescore import scores_from_cache

    async def run() -> tuple[dict[Any, Any], float | None, int]:
        async with EmbeddingClient(args.url, token=_admin_token(), timeout_s=120) as client:
            return await scores_from_cache(client, args.cache, scenes)
    try:
        new, threshold, version = asyncio.run(run())
    except (ServiceError, httpx.TransportError) as exc:
        raise _service_failure(exc, args.url) from None
    return new, threshold, f"cache {args.cache} v{version} at {args.url}"
