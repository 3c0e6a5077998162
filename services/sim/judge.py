"""Judging a flight on the truth: did it stay within the scene's limits, is it inside a region.

The simulated vehicle knows where it really flew; these functions judge that truth (a
12-state trajectory and the inputs the planning model commanded) against the scene, with
the tolerances every benchmark, test and the demo share.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.control.core.regions import Tolerance
from services.control.core.scenario import Scenario, planning_model

TOLERANCE = Tolerance()  # how close to a region's box counts as inside (control's regions.py)


@dataclass(frozen=True)
class LimitTolerance:
    """How far the nonlinear truth may exceed a limit before it counts as a violation."""

    position: float = 0.05  # m
    velocity: float = 0.05  # m/s
    tilt: float = 0.02  # rad
    rate: float = 0.05  # rad/s
    input: float = 1e-6  # the model's input units (the plant clips; the controller must
    # not ask beyond)

    def state(self) -> np.ndarray:
        return np.repeat([self.position, self.velocity, self.tilt, self.rate], 3)


LIMIT_TOLERANCE = LimitTolerance()


def count_violations(states: np.ndarray, inputs: np.ndarray, scenario: Scenario,
                     tol: LimitTolerance = LIMIT_TOLERANCE) -> int:
    """Ticks at which a 12-state ``states`` row left the scenario's limits or an ``inputs``
    row the planning model's input box, beyond ``tol``."""
    states, inputs = np.asarray(states, dtype=float), np.asarray(inputs, dtype=float)
    if not len(states):
        return 0
    lo, hi = scenario.limits.box()
    slack = tol.state()
    bad = np.any((states > hi + slack) | (states < lo - slack) | ~np.isfinite(states), axis=1)
    if len(inputs):
        model = planning_model(scenario)
        bad_u = np.any((inputs > model.u_hi + tol.input) | (inputs < model.u_lo - tol.input),
                       axis=1)
        n = min(len(bad), len(bad_u))
        bad[:n] |= bad_u[:n]
    return int(np.sum(bad))


LIMITS = ("position", "velocity", "tilt", "rate")  # the 12-state row's four triples


def over_limits(states: np.ndarray, inputs: np.ndarray, scenario: Scenario,
                tol: LimitTolerance = LIMIT_TOLERANCE) -> dict[str, tuple[int, float]]:
    """Which limits :func:`count_violations` found exceeded: per limit (``position`` (the
    fence), ``velocity``, ``tilt`` (roll and pitch), ``rate`` (body rates), ``input`` (the
    planning model's box)) the rows over it and the worst excess beyond the limit, in its
    units (a non-finite value counts as infinite); only the limits exceeded."""
    states, inputs = np.asarray(states, dtype=float), np.asarray(inputs, dtype=float)
    out: dict[str, tuple[int, float]] = {}
    if len(states):
        lo, hi = scenario.limits.box()
        slack = tol.state()
        excess = np.maximum(states - hi, lo - states)
        excess = np.where(np.isfinite(states), excess, np.inf)
        for i, name in enumerate(LIMITS):
            cols = slice(3 * i, 3 * i + 3)
            rows = np.any(excess[:, cols] > slack[cols], axis=1)
            if rows.any():
                out[name] = (int(rows.sum()), float(excess[:, cols].max()))
    if len(inputs):
        model = planning_model(scenario)
        excess_u = np.maximum(inputs - model.u_hi, model.u_lo - inputs)
        rows = np.any(excess_u > tol.input, axis=1)
        if rows.any():
            out["input"] = (int(rows.sum()), float(excess_u.max()))
    return out
