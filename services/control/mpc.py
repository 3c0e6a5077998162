"""The AESOP multi-branch MPC, eq. 3 of the paper, on OSQP.

``J_t(Y, K, T)``: one nominal branch (index 0) and one recovery branch per
region in ``Y``, each a trajectory of the hover model over ``T`` steps:

* every branch starts at the measured state ``x_t``;
* every recovery branch shares its first input with the nominal branch;
* the recovery branches share their first ``K`` inputs with each other;
* recovery branch ``i`` lies in region ``X_R^i`` from step ``s`` on (``s = T``
  in nominal operation, ``T - k`` while a decision is pending); regions are
  sets of equilibria, so holding them to the end of the horizon changes no
  feasibility and keeps the problem's shape fixed;
* state and input boxes on every step of every branch.

The cost is the nominal task cost ``C`` (quadratic tracking of the goal plus
input effort) plus a small, ``recovery``-weighted tracking cost on each
recovery branch toward its region's centre, which makes the recovery plans
unique and smooth without moving the optimum of ``C`` noticeably.

The hover model splits into chains that do not interact: ``(x, vx, theta,
q)`` driven by the pitch torque, ``(y, vy, phi, p)`` by the roll torque,
``(z, vz)`` by thrust and ``(psi, r)`` by the yaw torque. The weights are
diagonal, the constraints are boxes and the consensus equalities hold input
by input, so eq. 3 separates *exactly* into one small QP per chain: the cost
is the sum of the chains' costs and the plan is feasible when every chain is.
:func:`decouple` finds the chains from the model's sparsity (nothing is
hard-coded), and :class:`BranchProblem` solves one :class:`ChainQP` per chain
and stitches the plan together. Small QPs converge in fewer, cheaper ADMM
iterations than the coupled one, and many subsets share a chain problem
(both grass fields lie at the same ``x``), which a shared cache of chain QPs
turns into one solve.

A :class:`ChainQP` has a fixed shape (number of branches, horizon) and is
built and factorized once; each tick only vectors change (initial state,
bounds that encode ``s`` and ``K``, targets), and OSQP warm-starts from the
previous solution shifted one step. Shrinking horizons and consensus are
bound updates, not new problems.

Two robustness details for a plant that is not the linear model:

* constraints on velocity, tilt and rates are tightened by ``shrink`` (3 %),
  and velocity by ``velocity_margin`` more (0.25 m/s, the overshoot measured
  on the nonlinear plant when a turn-around is planned at the limit), so
  model errors do not violate the true limits;
* if the measured state already exceeds a tightened bound (model error), the
  bounds of the first ``relax_steps`` steps are widened by that excess,
  tapering linearly to zero, so the problem stays feasible while the plan
  brings the state back.

With ``soft=True`` every recovery branch carries an L1-priced slack per
state component that shifts its state box (limits and region alike; the
shift moves the box, it does not widen it, and the nominal branch has none).
A region out of reach then costs slack instead of making the problem
infeasible; a plan is *feasible* when the solver converged and the largest
slack is below ``slack_tolerance``. The baselines need this (their
least-violating plan); AESOP's selector uses it so that an inexact solve at
the edge of feasibility does not read as "infeasible" on the next tick.
Caveat, measured against the CVXPY reference: OSQP's slack estimate at
``eps = 1e-3`` runs at about ``10 eps``, as large as the default tolerance.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np
import osqp
import scipy.sparse as sp

from .dynamics import LinearModel
from .regions import Region


class SolveStatus(StrEnum):
    SOLVED = "solved"
    INACCURATE = "solved_inaccurate"
    INFEASIBLE = "infeasible"
    MAX_ITER = "max_iter"
    FAILED = "failed"

    @property
    def feasible(self) -> bool:
        return self is SolveStatus.SOLVED


_OSQP_STATUS = {
    osqp.SolverStatus.OSQP_SOLVED: SolveStatus.SOLVED,
    osqp.SolverStatus.OSQP_SOLVED_INACCURATE: SolveStatus.INACCURATE,
    osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE: SolveStatus.INFEASIBLE,
    osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE: SolveStatus.INFEASIBLE,
    osqp.SolverStatus.OSQP_MAX_ITER_REACHED: SolveStatus.MAX_ITER,
}


@dataclass(frozen=True)
class Weights:
    """Diagonal quadratic weights of the tracking cost (per unit of state/input)."""

    position: float = 1.0  # 1/m^2
    velocity: float = 0.2  # s^2/m^2
    attitude: float = 0.5  # 1/rad^2
    rate: float = 0.1  # s^2/rad^2
    thrust: float = 0.05  # 1/N^2
    torque: float = 1.0  # 1/(N m)^2

    def state(self) -> np.ndarray:
        return np.repeat([self.position, self.velocity, self.attitude, self.rate], 3)

    def input(self) -> np.ndarray:
        return np.array([self.thrust, self.torque, self.torque, self.torque])


@dataclass(frozen=True)
class MPCConfig:
    horizon: int = 40  # T, steps
    consensus: int = 15  # K, steps
    weights: Weights = field(default_factory=Weights)
    recovery_weight: float = 0.01  # scale of the recovery branches' own tracking cost
    shrink: float = 0.03  # fraction by which velocity/tilt/rate and input limits are tightened
    position_margin: float = 0.05  # m: fence and region boxes planned this far inside
    # m/s: velocity limits planned this much further inside. The plant's horizontal
    # acceleration is g tan(theta), not the model's g theta, and the attitude chain
    # reverses slowly: a turn-around planned at the limit overshoots it by ~0.2 m/s.
    velocity_margin: float = 0.25
    input_margin: float = 0.005  # N, N m: least tightening of an input bound (OSQP is eps-exact)
    relax_steps: int = 20  # steps over which an initial-state excess is tapered out (2 s: the
    # attitude chain needs about 1 s before it can take off the velocity margin)
    min_region_step: int = 5  # earliest step a shrinking horizon may pin a region to
    late_region_steps: int = 5  # how far an unreachable region deadline is pushed back per try
    slack_weight: float = 1000.0  # L1 price per unit of constraint violation
    slack_tolerance: float = 1e-2  # largest slack (m, m/s, rad) a feasible plan may have
    eps_abs: float = 1e-3
    eps_rel: float = 1e-3
    eps_prim_inf: float = 1e-3  # OSQP's primal-infeasibility tolerance (certificate accuracy)
    max_iter: int = 1000  # per warm solve; a capped solve reads as infeasible (safe side)
    max_iter_cold: int = 10000  # the first solve of a problem has no warm start

    def __post_init__(self) -> None:
        if not 0 <= self.consensus < self.horizon:
            raise ValueError("need 0 <= consensus < horizon")
        if not 1 <= self.min_region_step <= self.horizon:
            raise ValueError("need 1 <= min_region_step <= horizon")
        if self.late_region_steps < 1:
            raise ValueError("need late_region_steps >= 1")


@dataclass(frozen=True)
class Plan:
    """One solve of eq. 3. Trajectories are ``(T+1, 12)`` state arrays."""

    status: SolveStatus
    cost: float
    u0: np.ndarray  # absolute first input [N, N m]
    inputs: np.ndarray  # (T, 4) absolute inputs of the branch the robot follows
    nominal: np.ndarray | None
    recovery: dict[int, np.ndarray]
    recovery_inputs: dict[int, np.ndarray]  # (T, 4) absolute inputs per region
    consensus: int
    region_step: int
    iterations: int
    solve_ms: float
    slack: float = 0.0  # largest constraint violation of a recovery branch
    slack_tolerance: float = 1e-2

    @property
    def feasible(self) -> bool:
        return self.status.feasible and self.slack <= self.slack_tolerance


@dataclass(frozen=True)
class Chain:
    """One decoupled part of the linear model: its states, inputs, bounds and weights."""

    states: tuple[int, ...]  # indices into the full state
    inputs: tuple[int, ...]  # indices into the full input
    a: np.ndarray
    b: np.ndarray
    x_lo: np.ndarray  # tightened state box
    x_hi: np.ndarray
    du_lo: np.ndarray  # input box, relative to hover
    du_hi: np.ndarray
    q_state: np.ndarray  # diagonal weights
    r_input: np.ndarray


@dataclass(frozen=True)
class Box:
    """A recovery region restricted to one chain's states, with its tracking target."""

    lo: np.ndarray
    hi: np.ndarray
    center: np.ndarray

    def key(self) -> bytes:
        return self.lo.tobytes() + self.hi.tobytes() + self.center.tobytes()


@dataclass(frozen=True)
class ChainSolution:
    """One chain's solve; trajectories are per branch, nominal first."""

    status: SolveStatus
    cost: float
    states: np.ndarray | None  # (branches, T+1, n_chain)
    du: np.ndarray | None  # (branches, T, m_chain), relative to hover
    slack: float
    iterations: int
    solve_ms: float


def tightened_states(x_bounds: tuple[np.ndarray, np.ndarray], config: MPCConfig
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The state box the MPC plans in: symmetric limits (velocity, tilt, rates) scaled by
    ``1 - shrink``, the position fence moved ``position_margin`` inward; yaw (bounded by
    +-pi only to keep angles unwrapped) untouched."""
    lo, hi = (np.asarray(v, dtype=float) for v in x_bounds)
    span = np.where(np.isfinite(hi) & np.isfinite(lo) & (lo == -hi), 1.0 - config.shrink, 1.0)
    span[8] = 1.0
    lo, hi = lo * span, hi * span
    lo[:3] += config.position_margin
    hi[:3] -= config.position_margin
    lo[3:6] += config.velocity_margin
    hi[3:6] -= config.velocity_margin
    return lo, hi


def planning_box(region: Region, config: MPCConfig) -> tuple[np.ndarray, np.ndarray]:
    """A region's ``(lo, hi)`` as the MPC aims for it: its position box shrunk by
    ``position_margin`` (at most to a quarter of its width), so that the nonlinear
    truth, a little off the linear plan, still lands inside."""
    lo, hi = region.lo.copy(), region.hi.copy()
    margin = np.minimum(config.position_margin, (hi[:3] - lo[:3]) / 4)
    lo[:3] += margin
    hi[:3] -= margin
    return lo, hi


def tightened_inputs(model: LinearModel, u_bounds: tuple[np.ndarray, np.ndarray],
                     config: MPCConfig) -> tuple[np.ndarray, np.ndarray]:
    """The input box the MPC plans in, relative to hover: each bound moved inward by
    ``shrink`` of its distance from hover, and at least ``input_margin``, so that a
    solution accurate to OSQP's tolerance still respects the true actuator limits."""
    du_lo, du_hi = u_bounds[0] - model.u_hover, u_bounds[1] - model.u_hover
    hi = du_hi - np.maximum(config.shrink * np.abs(du_hi), config.input_margin)
    lo = du_lo + np.maximum(config.shrink * np.abs(du_lo), config.input_margin)
    if np.any(lo >= hi):
        raise ValueError("input bounds too narrow for the configured margins")
    return lo, hi


def decouple(a: np.ndarray, b: np.ndarray) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
    """Groups ``(states, inputs)`` of ``x+ = A x + B u`` that never influence each other.

    The connected components of the graph whose nodes are states and inputs
    and whose edges are the nonzero entries of ``A`` and ``B``.
    """
    n, m = b.shape
    parent = list(range(n + m))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in zip(*np.nonzero(a), strict=True):
        parent[find(int(i))] = find(int(j))
    for i, j in zip(*np.nonzero(b), strict=True):
        parent[find(int(i))] = find(n + int(j))
    groups: dict[int, list[int]] = {}
    for node in range(n + m):
        groups.setdefault(find(node), []).append(node)
    out = [(tuple(i for i in g if i < n), tuple(i - n for i in g if i >= n))
           for g in groups.values()]
    return sorted((g for g in out if g[0]), key=lambda g: g[0])


class ChainQP:
    """Eq. 3 for one decoupled chain of the model, with a fixed shape.

    ``nominal`` (0 or 1) + ``n_recovery`` branches over the chain's states and
    inputs. Built and factorized once; :meth:`solve` updates vectors only and
    warm-starts from the previous solution shifted one step. Recovery targets
    come as :class:`Box` es in slot order.
    """

    def __init__(self, chain: Chain, config: MPCConfig, n_recovery: int,
                 nominal: bool = True, soft: bool = False) -> None:
        self.chain, self.config = chain, config
        self.n, self.m = chain.a.shape[0], chain.b.shape[1]
        self.n_rec, self.has_nominal, self.soft = n_recovery, nominal, soft
        self.n_branches = n_recovery + int(nominal)
        horizon = config.horizon
        self.branch_size = (horizon + 1) * self.n + horizon * self.m
        self.n_var = self.n_branches * self.branch_size + (2 * self.n * n_recovery if soft else 0)
        self._build()
        self._var_shift, self._con_shift = self._shift_maps()
        self._previous: tuple[np.ndarray, np.ndarray] | None = None
        self._memo: tuple[bytes, ChainSolution] | None = None
        self._warm = False
        self.solver = osqp.OSQP()
        self.solver.setup(self._p, self._q.copy(), self._a, self._lower.copy(), self._upper.copy(),
                          eps_abs=config.eps_abs, eps_rel=config.eps_rel,
                          eps_prim_inf=config.eps_prim_inf, max_iter=config.max_iter_cold,
                          verbose=False, warm_starting=True, polishing=False,
                          check_termination=5)

    # -- layout -----------------------------------------------------------------------------
    def _x(self, branch: int, step: int) -> int:
        return branch * self.branch_size + step * self.n

    def _u(self, branch: int, step: int) -> int:
        n, horizon = self.n, self.config.horizon
        return branch * self.branch_size + (horizon + 1) * n + step * self.m

    def _sigma(self, slot: int) -> int:
        """First of ``2 n`` slack variables (sigma+, then sigma-) of recovery slot ``slot``."""
        return self.n_branches * self.branch_size + 2 * slot * self.n

    def _slot_branch(self, slot: int) -> int:
        """Branch number of recovery slot ``slot`` (0-based)."""
        return slot + int(self.has_nominal)

    def _build(self) -> None:
        n, m, horizon = self.n, self.m, self.config.horizon
        a_dyn, b_dyn = self.chain.a, self.chain.b
        rows: list[sp.spmatrix] = []
        lows: list[np.ndarray] = []
        highs: list[np.ndarray] = []
        n_var = self.n_var

        def block(entries: list[tuple[int, np.ndarray]], height: int) -> sp.csc_matrix:
            mat = sp.lil_matrix((height, n_var))
            for col, values in entries:
                mat[:, col:col + values.shape[1]] = values
            return mat

        eye_n, eye_m = np.eye(n), np.eye(m)
        # initial state: x_b[0] = x_t
        self._init_rows = []
        offset = 0
        for b in range(self.n_branches):
            rows.append(block([(self._x(b, 0), eye_n)], n))
            self._init_rows.append(offset)
            lows.append(np.zeros(n))
            highs.append(np.zeros(n))
            offset += n
        # dynamics: x_b[j+1] - A x_b[j] - B du_b[j] = 0
        dyn = []
        for b in range(self.n_branches):
            for j in range(horizon):
                dyn.append(block([(self._x(b, j), -a_dyn), (self._u(b, j), -b_dyn),
                                  (self._x(b, j + 1), eye_n)], n))
        rows.append(sp.vstack(dyn))
        lows.append(np.zeros(len(dyn) * n))
        highs.append(np.zeros(len(dyn) * n))
        offset += len(dyn) * n
        # state boxes on steps 1..T (the region rows are these rows with tighter bounds)
        self._state_rows = offset
        r_idx, c_idx, vals = [], [], []
        row = 0
        for b in range(self.n_branches):
            slot = b - int(self.has_nominal)
            for j in range(1, horizon + 1):
                for i in range(n):
                    r_idx.append(row)
                    c_idx.append(self._x(b, j) + i)
                    vals.append(1.0)
                    if self.soft and slot >= 0:  # x - sigma+ + sigma- within the box
                        r_idx += [row, row]
                        c_idx += [self._sigma(slot) + i, self._sigma(slot) + n + i]
                        vals += [-1.0, 1.0]
                    row += 1
        rows.append(sp.csc_matrix((vals, (r_idx, c_idx)), shape=(row, n_var)))
        lows.append(np.zeros(row))
        highs.append(np.zeros(row))
        offset += row
        # input boxes
        cols = [self._u(b, j) + i for b in range(self.n_branches)
                for j in range(horizon) for i in range(m)]
        rows.append(sp.csc_matrix((np.ones(len(cols)), (np.arange(len(cols)), cols)),
                                  shape=(len(cols), n_var)))
        lows.append(np.tile(self.chain.du_lo, self.n_branches * horizon))
        highs.append(np.tile(self.chain.du_hi, self.n_branches * horizon))
        offset += len(cols)
        # first input shared with the nominal branch
        if self.has_nominal:
            for slot in range(self.n_rec):
                rows.append(block([(self._u(0, 0), eye_m),
                                   (self._u(self._slot_branch(slot), 0), -eye_m)], m))
                lows.append(np.zeros(m))
                highs.append(np.zeros(m))
                offset += m
        # recovery consensus: consecutive recovery branches share inputs 0..K'-1
        self._consensus_rows = offset
        n_cons = max(0, self.n_rec - 1) * horizon
        for slot in range(self.n_rec - 1):
            b1, b2 = self._slot_branch(slot), self._slot_branch(slot + 1)
            for j in range(horizon):
                rows.append(block([(self._u(b1, j), eye_m), (self._u(b2, j), -eye_m)], m))
        lows.append(np.zeros(n_cons * m))
        highs.append(np.zeros(n_cons * m))
        offset += n_cons * m
        # slack: sigma+ >= 0 and sigma- >= 0 per recovery branch (columns in the state rows)
        self._sigma_rows = offset
        n_sig = 2 * n * self.n_rec if self.soft else 0
        if n_sig:
            rows.append(block([(self._sigma(0), np.eye(n_sig))], n_sig))
            lows.append(np.zeros(n_sig))
            highs.append(np.full(n_sig, np.inf))
            offset += n_sig
        self._a = sp.vstack(rows, format="csc")
        self._lower = np.concatenate(lows)
        self._upper = np.concatenate(highs)
        self._build_cost()

    def _build_cost(self) -> None:
        cfg, n, horizon = self.config, self.n, self.config.horizon
        q_state, r_input = self.chain.q_state, self.chain.r_input
        diag = np.zeros(self.n_var)
        self._branch_scale = []
        for b in range(self.n_branches):
            scale = 1.0 if (b == 0) else cfg.recovery_weight
            self._branch_scale.append(scale)
            start = self._x(b, 1)
            diag[start:start + horizon * n] = np.tile(q_state, horizon) * scale
            start = self._u(b, 0)
            diag[start:start + horizon * self.m] = np.tile(r_input, horizon) * scale
        q = np.zeros(self.n_var)
        if self.soft and self.n_rec:
            start = self._sigma(0)
            diag[start:start + 2 * n * self.n_rec] = 1e-6
            q[start:start + 2 * n * self.n_rec] = cfg.slack_weight
        self._diag = diag
        # OSQP minimises 1/2 z'Pz + q'z: P = 2 diag gives sum(w * z^2)
        self._p = sp.diags(2 * diag, format="csc")
        self._q = q

    def _shift_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """Index maps that advance a solution by one step, for a shifted warm start.

        Entry ``i`` says which entry of the previous primal (dual) solution
        initializes entry ``i`` now: step ``j`` takes step ``j + 1``, and the
        last step repeats.
        """
        n, m, horizon, nb = self.n, self.m, self.config.horizon, self.n_branches
        var = np.arange(self.n_var)
        for b in range(nb):
            for j in range(horizon + 1):
                src = self._x(b, min(j + 1, horizon))
                var[self._x(b, j):self._x(b, j) + n] = np.arange(src, src + n)
            for j in range(horizon):
                src = self._u(b, min(j + 1, horizon - 1))
                var[self._u(b, j):self._u(b, j) + m] = np.arange(src, src + m)
        con = np.arange(self._a.shape[0])

        def advance(base: int, groups: int, width: int) -> None:
            idx = np.arange(groups * horizon * width).reshape(groups, horizon, width)
            src = np.concatenate([idx[:, 1:], idx[:, -1:]], axis=1)
            con[base:base + idx.size] = base + src.ravel()

        advance(nb * n, nb, n)  # dynamics rows
        advance(self._state_rows, nb, n)
        advance(self._state_rows + nb * horizon * n, nb, m)  # input rows
        advance(self._consensus_rows, max(0, self.n_rec - 1), m)
        return var, con

    # -- solve ------------------------------------------------------------------------------
    def solve(self, x0: np.ndarray, goal: np.ndarray, boxes: Sequence[Box], consensus: int,
              s: int) -> ChainSolution:
        """Solve for the chain's part of the measured state ``x0`` and of ``goal``.

        ``boxes`` fill the recovery slots in order; ``consensus`` (K') and
        ``s`` (the step from which recovery branches lie in their box) are in
        steps. The same call twice in a row returns the first answer.
        """
        cfg, n, m, horizon = self.config, self.n, self.m, self.config.horizon
        if len(boxes) != self.n_rec:
            raise ValueError(f"expected {self.n_rec} regions, got {len(boxes)}")
        key = b"".join([x0.tobytes(), goal.tobytes(), np.array([consensus, s]).tobytes(),
                        *(box.key() for box in boxes)])
        if self._memo is not None and self._memo[0] == key:
            return replace(self._memo[1], iterations=0, solve_ms=0.0)
        chain = self.chain
        lo, hi = self._lower.copy(), self._upper.copy()
        q = self._q.copy()
        for r in self._init_rows:
            lo[r:r + n] = x0
            hi[r:r + n] = x0
        # state boxes, widened early on by any excess of x0 over the tightened limits
        excess = np.maximum(np.maximum(x0 - chain.x_hi, chain.x_lo - x0), 0.0)
        taper = np.clip(1.0 - np.arange(horizon) / max(cfg.relax_steps, 1), 0.0, 1.0)
        widen = taper[:, None] * excess[None, :]  # (T, n), step j = 1..T
        box_lo = chain.x_lo[None, :] - widen
        box_hi = chain.x_hi[None, :] + widen
        targets = []
        for b in range(self.n_branches):
            b_lo, b_hi = box_lo.copy(), box_hi.copy()
            if b == 0 and self.has_nominal:
                target = goal
            else:
                box = boxes[b - int(self.has_nominal)]
                target = box.center
                b_lo[s - 1:] = np.maximum(b_lo[s - 1:], box.lo - widen[s - 1:])
                b_hi[s - 1:] = np.minimum(b_hi[s - 1:], box.hi + widen[s - 1:])
            targets.append(target)
            start = self._state_rows + b * horizon * n
            lo[start:start + horizon * n] = b_lo.ravel()
            hi[start:start + horizon * n] = b_hi.ravel()
            xs = self._x(b, 1)
            q[xs:xs + horizon * n] = -2 * self._diag[xs:xs + horizon * n] * np.tile(target, horizon)
        # consensus: active for steps < K', free afterwards
        for slot in range(self.n_rec - 1):
            start = self._consensus_rows + slot * horizon * m
            lo[start:start + horizon * m] = -np.inf
            hi[start:start + horizon * m] = np.inf
            lo[start:start + consensus * m] = 0.0
            hi[start:start + consensus * m] = 0.0
        if np.any(lo > hi):  # a region outside the state limits: nothing to solve
            solution = self._solution(None, SolveStatus.INFEASIBLE, targets, 0.0)
        else:
            solution = self._run(q, lo, hi, targets)
        self._memo = (key, solution)
        return solution

    def _run(self, q: np.ndarray, lo: np.ndarray, hi: np.ndarray, targets) -> ChainSolution:
        cfg = self.config
        infinity = osqp.constant("OSQP_INFTY")
        lo = np.where(np.isfinite(lo), lo, -infinity)
        hi = np.where(np.isfinite(hi), hi, infinity)
        start_time = time.perf_counter()
        self.solver.update(q=q, l=lo, u=hi)
        if self._previous is not None:
            z_prev, y_prev = self._previous
            self.solver.warm_start(x=z_prev[self._var_shift], y=y_prev[self._con_shift])
        warm = self._previous is not None
        if warm != self._warm:
            self.solver.update_settings(max_iter=cfg.max_iter if warm else cfg.max_iter_cold)
            self._warm = warm
        result = self.solver.solve(raise_error=False)
        solve_ms = (time.perf_counter() - start_time) * 1e3
        status = _OSQP_STATUS.get(result.info.status_val, SolveStatus.FAILED)
        if status in (SolveStatus.SOLVED, SolveStatus.INACCURATE, SolveStatus.MAX_ITER):
            self._previous = (result.x.copy(), result.y.copy())
        return self._solution(result, status, targets, solve_ms)

    def _solution(self, result, status: SolveStatus, targets, solve_ms: float) -> ChainSolution:
        n, m, horizon, nb = self.n, self.m, self.config.horizon, self.n_branches
        z = None if result is None else result.x
        iterations = 0 if result is None else int(result.info.iter)
        if status not in (SolveStatus.SOLVED, SolveStatus.INACCURATE) or z is None \
                or not np.all(np.isfinite(z)):
            return ChainSolution(status, float("inf"), None, None, float("inf"), iterations,
                                 solve_ms)
        cost = float(result.info.obj_val)
        for b, target in enumerate(targets):  # the constants OSQP leaves out
            cost += self._branch_scale[b] * horizon * float(target @ (self.chain.q_state * target))
        states = np.stack([z[self._x(b, 0):self._x(b, 0) + (horizon + 1) * n]
                           .reshape(horizon + 1, n) for b in range(nb)])
        inputs = np.stack([z[self._u(b, 0):self._u(b, 0) + horizon * m].reshape(horizon, m)
                           for b in range(nb)])
        slack = 0.0
        if self.soft and self.n_rec:
            sig = z[self._sigma(0):self._sigma(0) + 2 * n * self.n_rec]
            slack = float(np.max(np.abs(sig)))
            cost -= self.config.slack_weight * float(np.sum(sig))  # report the task cost
        return ChainSolution(status, cost, states, inputs, slack, iterations, solve_ms)


ChainCache = dict[tuple, ChainQP]


class BranchProblem:
    """Eq. 3 with a fixed shape: ``nominal`` (0 or 1) + ``n_recovery`` branches.

    ``nominal=False`` is the recovering problem ``J({y}, 0, .)``: the recovery
    branch is the one followed, with full tracking weight toward its region.
    Problems that pass the same ``cache`` share chain QPs: two subsets whose
    regions agree on a chain solve that chain once per state.
    """

    def __init__(self, model: LinearModel, x_bounds: tuple[np.ndarray, np.ndarray],
                 u_bounds: tuple[np.ndarray, np.ndarray], config: MPCConfig,
                 n_recovery: int, nominal: bool = True, soft: bool = False,
                 cache: ChainCache | None = None) -> None:
        if n_recovery < 0 or (not nominal and n_recovery != 1):
            raise ValueError("a problem without a nominal branch has exactly one recovery branch")
        self.model, self.config = model, config
        self.n_rec, self.has_nominal, self.soft = n_recovery, nominal, soft
        self.n_branches = n_recovery + int(nominal)
        self.x_lo, self.x_hi = tightened_states(x_bounds, config)
        du_lo, du_hi = tightened_inputs(model, u_bounds, config)
        q_state, r_input = config.weights.state(), config.weights.input()
        self.chains = []
        for states, inputs in decouple(model.a, model.b):
            s, i = list(states), list(inputs)
            self.chains.append(Chain(states, inputs, model.a[np.ix_(s, s)], model.b[np.ix_(s, i)],
                                     self.x_lo[s], self.x_hi[s], du_lo[i], du_hi[i],
                                     q_state[s], r_input[i]))
        self._cache: ChainCache = {} if cache is None else cache

    def _qp(self, number: int, keys: tuple[bytes, ...]) -> ChainQP:
        key = (number, self.n_rec, self.has_nominal, self.soft, self.config, keys)
        if key not in self._cache:
            self._cache[key] = ChainQP(self.chains[number], self.config, self.n_rec,
                                       self.has_nominal, self.soft)
        return self._cache[key]

    def solve(self, x0: np.ndarray, goal: np.ndarray, regions: Sequence[Region],
              consensus: int | None = None, region_step: int | None = None,
              stop_early: bool = False) -> Plan:
        """Solve for the measured state ``x0``; ``regions`` fill the recovery slots in order.

        ``consensus`` (K' steps) and ``region_step`` (s) default to the
        configured K and T; ``region_step = T + 1`` drops the region constraints
        (recovery branches only track their region's centre). ``goal`` is the
        nominal target state (12,).
        ``stop_early`` skips the remaining chains once one is infeasible
        (selection needs only the verdict then, not the least-violating plan).
        """
        cfg, horizon = self.config, self.config.horizon
        if len(regions) != self.n_rec:
            raise ValueError(f"expected {self.n_rec} regions, got {len(regions)}")
        consensus = cfg.consensus if consensus is None else consensus
        s = min(max(horizon if region_step is None else region_step, 1), horizon + 1)
        nb, n, m = self.n_branches, self.model.n, self.model.m
        states = np.zeros((nb, horizon + 1, n))
        du = np.zeros((nb, horizon, m))
        cost, slack, iterations, solve_ms = 0.0, 0.0, 0, 0.0
        status = SolveStatus.SOLVED
        planned = [planning_box(r, cfg) for r in regions]
        for number, chain in enumerate(self.chains):
            idx = list(chain.states)
            boxes = [Box(lo[idx], hi[idx], r.center[idx]) for r, (lo, hi) in zip(regions, planned,
                                                                                  strict=True)]
            order = sorted(range(len(boxes)), key=lambda i: boxes[i].key())
            qp = self._qp(number, tuple(boxes[i].key() for i in order))
            sol = qp.solve(x0[idx], goal[idx], [boxes[i] for i in order], consensus, s)
            iterations += sol.iterations
            solve_ms += sol.solve_ms
            if sol.states is None:
                status = sol.status
                break
            if status is SolveStatus.SOLVED:
                status = sol.status
            # QP branch of each region: nominal first, then the regions in key order
            branch = list(range(int(self.has_nominal))) + [
                int(self.has_nominal) + order.index(i) for i in range(len(regions))]
            states[:, :, idx] = sol.states[branch]
            du[:, :, list(chain.inputs)] = sol.du[branch]
            cost += sol.cost
            slack = max(slack, sol.slack)
            if stop_early and (not sol.status.feasible or sol.slack > cfg.slack_tolerance):
                status = SolveStatus.INFEASIBLE
                break
        if not status.feasible and status is not SolveStatus.INACCURATE:
            empty = np.zeros((horizon, m))
            return Plan(status, float("inf"), self.model.u_hover.copy(), empty, None, {}, {},
                        consensus, s, iterations, solve_ms)
        inputs = du + self.model.u_hover
        offset = int(self.has_nominal)
        recovery = {r.index: states[offset + i] for i, r in enumerate(regions)}
        recovery_inputs = {r.index: inputs[offset + i] for i, r in enumerate(regions)}
        return Plan(status, cost, inputs[0][0].copy(), inputs[0],
                    states[0] if self.has_nominal else None, recovery, recovery_inputs,
                    consensus, s, iterations, solve_ms, slack, cfg.slack_tolerance)
