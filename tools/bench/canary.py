"""The platform's own scheduling lateness, the reference for a deadline measured beside it.

``python -m tools.bench.canary``: a process that does nothing but sleep ``PERIOD_S`` at a
time on a thread of the keeper's timer class (:func:`shared.realtime.urgent`, one level
above the lowest real-time one) and note how late each wake-up is, until SIGTERM; then it
prints ``{"priority", "n", "p50_ms", "p99_ms", "max_ms"}`` as one JSON line. Nothing in it
waits for a lock, a GIL held by another thread or a collection: how late it wakes is what
the machine (its kernel, or the hypervisor under a virtual one) adds to any deadline.
"""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from shared.realtime import urgent

PERIOD_S = 0.02


def main() -> None:
    stop = False

    def done(*_: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, done)
    priority = urgent(above=1)
    late: list[float] = []
    while not stop:
        due = time.monotonic() + PERIOD_S
        time.sleep(PERIOD_S)
        late.append((time.monotonic() - due) * 1e3)
    ms = np.asarray(late or [0.0])
    print(json.dumps({"priority": priority, "n": len(late),
                      "p50_ms": float(np.percentile(ms, 50)),
                      "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max())}),
          flush=True)


@contextlib.contextmanager
def canary() -> Iterator[dict[str, Any]]:
    """Run the canary for the block; the dict it yields holds its report afterwards."""
    report: dict[str, Any] = {}
    proc = subprocess.Popen([sys.executable, "-m", "tools.bench.canary"],
                            stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
    try:
        yield report
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=10)
        with contextlib.suppress(ValueError):
            report.update(json.loads(out.strip().splitlines()[-1]))


if __name__ == "__main__":
    main()
