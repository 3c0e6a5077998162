"""Where a simulated flight starts (pure)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from services.control.core.dynamics import N_STATE, POS
from services.control.core.scenario import Scenario


class StartError(ValueError):
    """A start position the scene cannot use."""


def start_state(scenario: Scenario, start: Sequence[float] | None, seed: int) -> np.ndarray:
    """At rest at ``start`` (m, inside the scene's fence), else drawn from its start box
    with ``seed``."""
    if start is None:
        return scenario.sample_start(np.random.default_rng(seed))
    pos = np.asarray(start, dtype=float)
    lo, hi = np.asarray(scenario.limits.position_lo), np.asarray(scenario.limits.position_hi)
    if pos.shape != (3,) or not np.all(np.isfinite(pos)):
        raise StartError("start: expected 3 finite numbers (m)")
    if np.any(pos < lo) or np.any(pos > hi):
        raise StartError(f"start: {pos.tolist()} is outside the position limits "
                         f"{list(scenario.limits.position_lo)}.."
                         f"{list(scenario.limits.position_hi)}")
    x = np.zeros(N_STATE)
    x[POS] = pos
    return x
