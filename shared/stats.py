"""The spread of a window of durations or ages, as the services' state routes and the
benchmarks report it."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np


def spread(values_ms: Iterable[float], name: str) -> dict[str, float | None]:
    """``{name}_p50_ms``, ``{name}_p99_ms`` and ``{name}_max_ms`` of ``values_ms``
    (milliseconds, to 3 decimals); None each when there are none."""
    a = np.asarray(list(values_ms), dtype=float)
    if not a.size:
        return {f"{name}_p50_ms": None, f"{name}_p99_ms": None, f"{name}_max_ms": None}
    return {f"{name}_p50_ms": round(float(np.percentile(a, 50)), 3),
            f"{name}_p99_ms": round(float(np.percentile(a, 99)), 3),
            f"{name}_max_ms": round(float(a.max()), 3)}
