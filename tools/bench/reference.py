"""A plain CVXPY statement of eq. 3, the reference for ``aesop bench mpc`` and the tests.

:class:`~.mpc.BranchProblem` assembles eq. 3 as one sparse OSQP problem
that is factorized once and updated per tick. This module writes the same
optimization problem again, directly from the maths, with one
``cp.Variable`` per branch trajectory, and hands it to an interior-point
solver (CLARABEL by default). It shares no matrices or index maps with
``mpc.py``, so agreement of the optimal costs checks the OSQP assembly.

Every branch ``b`` has states ``x_b[0..T]`` and input deviations
``du_b[0..T-1]`` (``u = u_hover + du``)::

    minimise   sum_b w_b [ c_b sum_{j=1..T} |x_b[j] - t_b|_Q^2 + sum_{j=0..T-1} |du_b[j]|_R^2 ]
               + slack_weight * sum(sigma+ + sigma-) + 1e-6 |sigma|^2            (soft only)
    s.t.       x_b[0] = x0,   x_b[j+1] = A x_b[j] + B du_b[j]
               du_lo <= du_b[j] <= du_hi
               gap_lo <= du_b[j][i] - x_b[j][l] <= gap_hi    (each lag state l, its input i)
               lo_b[j] <= x_b[j] - d_b <= hi_b[j]   for j = 1..T,  d_b = sigma+_b - sigma-_b
               du_r[0] = du_nominal[0]              (each recovery branch r, with a nominal)
               du_r[j] = du_r'[j] for j < K         (consecutive recovery branches r, r')

with ``w_b = c_b = 1`` and ``t_b = goal`` for the nominal branch (index 0), and
``w_b = recovery_weight``, ``c_b = recovery_tracking`` and ``t_b`` = its region's
centre for a recovery branch (both 1 when there is no nominal branch). ``d_b`` exists only for
recovery branches of a soft problem and is zero otherwise; ``sigma+, sigma-
>= 0``, one pair per state component, shared by all steps of the branch.

The state box ``[lo_b[j], hi_b[j]]``:

* the state, input and region boxes and the lag gaps are tightened as the OSQP
  problem does (``tightened_states``, ``tightened_inputs``, ``planning_box``,
  ``tightened_lag_gaps``);
* an excess of ``x0`` over the tightened box (at least ``relax_floor`` on the
  symmetric limits) widens the box of step ``j`` by
  ``excess * clip(1 - (j - relax_lag) / relax_steps, 0, 1)``;
* a recovery branch's box is intersected, on steps ``j >= s``, with its
  region's box widened by the same amount.

The reported ``cost`` leaves out the L1 slack price (it keeps the tiny
quadratic one), as :class:`~.mpc.Plan` does, so the two are comparable.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import cvxpy as cp
import numpy as np

from services.control.core.mpc import (
    MPCConfig,
    planning_box,
    tightened_inputs,
    tightened_lag_gaps,
    tightened_states,
)
from services.control.core.planning import PlanningModel
from services.control.core.regions import Region

SLACK_QUADRATIC = 1e-6  # the small quadratic price on the slacks that mpc.py uses


@dataclass(frozen=True)
class ReferenceResult:
    cost: float  # comparable with Plan.cost; inf unless solved
    status: str  # CVXPY's status string
    u0: np.ndarray  # absolute first input of the followed branch (nan unless solved)
    solve_ms: float  # the solver's own time, as it reports it
    total_ms: float  # building the CVXPY problem, canonicalizing and solving
    slack: float = 0.0  # largest slack of a recovery branch


def _within(expr: cp.Expression, lo: np.ndarray, hi: np.ndarray) -> list[cp.Constraint]:
    """``lo <= expr <= hi`` elementwise for an expression of lo's shape, skipping infinite ends."""
    flat = cp.vec(expr, order="C")
    lo, hi = lo.ravel(), hi.ravel()
    out = []
    for bound, sign in ((lo, 1.0), (hi, -1.0)):
        idx = np.flatnonzero(np.isfinite(bound))
        if idx.size:
            out.append(sign * (flat[idx] - bound[idx]) >= 0)
    return out


def reference_solve(model: PlanningModel, config: MPCConfig,
                    regions: Sequence[Region], x0: np.ndarray, goal: np.ndarray,
                    consensus: int | None = None, region_step: int | None = None,
                    nominal: bool = True, soft: bool = False,
                    solver: str = "CLARABEL") -> ReferenceResult:
    """Solve eq. 3 as ``BranchProblem(..., len(regions), nominal, soft).solve(...)`` does."""
    start = time.perf_counter()
    n, m, horizon = model.n, model.m, config.horizon
    if not nominal and len(regions) != 1:
        raise ValueError("a problem without a nominal branch has exactly one recovery branch")
    k = config.consensus if consensus is None else consensus
    s = min(max(horizon if region_step is None else region_step, 1), horizon)
    x0, goal = np.asarray(x0, dtype=float), np.asarray(goal, dtype=float)
    du_lo, du_hi = tightened_inputs(model, config)
    q_state, r_input = config.weights.state(model), config.weights.input(model)
    a_dyn, b_dyn = model.linear.a, model.linear.b

    # the state box of steps 1..T (rows), tightened and then widened by the tapered excess
    x_lo, x_hi = tightened_states(model, config)
    floor = np.zeros(n)
    floor[list(model.symmetric)] = config.relax_floor
    excess = np.maximum(np.maximum(x0 - x_hi, x_lo - x0), floor)
    steps = np.arange(1, horizon + 1)
    taper = np.clip(1.0 - (steps - config.relax_lag) / config.relax_steps, 0.0, 1.0)
    widen = taper[:, None] * excess[None, :]
    box_lo, box_hi = x_lo - widen, x_hi + widen

    # branches: (target, weight, share of it on tracking the target, region or None)
    branches: list[tuple[np.ndarray, float, float, Region | None]] = []
    if nominal:
        branches.append((goal, 1.0, 1.0, None))
    for region in regions:
        weight, share = (config.recovery_weight, config.recovery_tracking) if nominal \
            else (1.0, 1.0)
        branches.append((model.region_center(region), weight, share, region))

    constraints: list[cp.Constraint] = []
    tracking = 0
    xs, dus, sigmas = [], [], []
    for target, weight, share, branch_region in branches:
        x = cp.Variable((horizon + 1, n))
        du = cp.Variable((horizon, m))
        xs.append(x)
        dus.append(du)
        constraints += [x[0] == x0, x[1:] == x[:-1] @ a_dyn.T + du @ b_dyn.T]
        constraints += _within(du, np.tile(du_lo, (horizon, 1)), np.tile(du_hi, (horizon, 1)))
        for state, channel, gap_lo, gap_hi in tightened_lag_gaps(model, config):
            constraints += _within(du[:, channel] - x[:-1, state], np.full(horizon, gap_lo),
                                   np.full(horizon, gap_hi))
        lo, hi = box_lo.copy(), box_hi.copy()
        shifted = x[1:]
        if branch_region is not None:
            # steps s..T are rows s-1..T-1
            r_lo, r_hi = planning_box(model, branch_region, config)
            lo[s - 1:] = np.maximum(lo[s - 1:], r_lo - widen[s - 1:])
            hi[s - 1:] = np.minimum(hi[s - 1:], r_hi + widen[s - 1:])
            if soft:
                sigma_plus, sigma_minus = cp.Variable(n, nonneg=True), cp.Variable(n, nonneg=True)
                sigmas += [sigma_plus, sigma_minus]
                shifted = x[1:] - np.ones((horizon, 1)) @ cp.reshape(
                    sigma_plus - sigma_minus, (1, n), order="C")
        constraints += _within(shifted, lo, hi)
        state_cost = cp.sum(cp.multiply(np.tile(q_state, (horizon, 1)),
                                        cp.square(x[1:] - target[None, :])))
        input_cost = cp.sum(cp.multiply(np.tile(r_input, (horizon, 1)), cp.square(du)))
        tracking = tracking + weight * (share * state_cost + input_cost)

    # consensus: recovery branches follow the nominal's first input and each other's first K
    first_recovery = int(nominal)
    recovery_inputs = dus[first_recovery:]
    if nominal:
        constraints += [du[0] == dus[0][0] for du in recovery_inputs]
    if min(k, horizon) > 0:
        constraints += [a[:k] == b[:k] for a, b in zip(recovery_inputs, recovery_inputs[1:],
                                                      strict=False)]

    slack_l1 = sum((cp.sum(sig) for sig in sigmas), start=cp.Constant(0.0))
    slack_quad = sum((cp.sum_squares(sig) for sig in sigmas), start=cp.Constant(0.0))
    reported = tracking + SLACK_QUADRATIC * slack_quad
    problem = cp.Problem(cp.Minimize(reported + config.slack_weight * slack_l1), constraints)
    problem.solve(solver=solver)
    total_ms = (time.perf_counter() - start) * 1e3
    stats = problem.solver_stats
    solve_ms = (stats.solve_time * 1e3 if stats is not None and stats.solve_time is not None
                else total_ms)
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
        return ReferenceResult(float("inf"), problem.status, np.full(m, np.nan), solve_ms,
                               total_ms)
    slack = max((float(np.max(np.abs(_solved(sig)))) for sig in sigmas), default=0.0)
    return ReferenceResult(float(reported.value), problem.status,
                           _solved(dus[0])[0] + model.linear.u_hover, solve_ms, total_ms, slack)


def _solved(variable: cp.Variable) -> np.ndarray:
    """A variable's value after an optimal solve (CVXPY sets every one then)."""
    if variable.value is None:
        raise RuntimeError("CVXPY reported an optimum but left a variable without a value")
    return variable.value
