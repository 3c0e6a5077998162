"""``python -m tools.bench.detector --memory-probe | --latency-probe``: the subprocesses of
the memory and latency parts; each prints one JSON line.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import sys
from typing import TYPE_CHECKING

from services.embedding.settings import DEFAULT_MODEL

if TYPE_CHECKING:
    pass
from .common import jsonable
from .latency import latency_probe
from .memory import memory_probe


def _main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="helpers of `aesop bench detector`")
    probe = parser.add_mutually_exclusive_group(required=True)
    probe.add_argument("--memory-probe", action="store_true")
    probe.add_argument("--latency-probe", action="store_true")
    parser.add_argument("--size", type=int, default=100_000)
    parser.add_argument("--n", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--model", default=DEFAULT_MODEL)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    with contextlib.redirect_stdout(sys.stderr):
        if args.memory_probe:
            result = memory_probe(args.size, args.seed)
        else:
            result = latency_probe(args.n, args.size, args.seed, args.model, args.threads)
    print(json.dumps(jsonable(result), allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(_main())
