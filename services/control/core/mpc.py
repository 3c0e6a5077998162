"""The AESOP multi-branch MPC, eq. 3 of the paper, on OSQP.

``J_t(Y, K, T)``: one nominal branch (index 0) and one recovery branch per
region in ``Y``, each a trajectory of the planning model (:mod:`.planning`: the
12-state hover model, or the point mass the hardware scene plans with) over
``T`` steps:

* every branch starts at the measured state ``x_t``;
* every recovery branch shares its first input with the nominal branch;
* the recovery branches share their first ``K`` inputs with each other;
* recovery branch ``i`` lies in region ``X_R^i`` from step ``s`` on (``s = T``
  in nominal operation, ``T - k`` while a decision is pending, or the
  relaxing promise of :func:`promised_step`); regions are sets of
  equilibria, so holding them to the end of the horizon changes no
  feasibility and keeps the problem's shape fixed;
* state and input boxes on every step of every branch;
* with a lagged point mass, each command within ``lag_gap`` of the acceleration the
  vehicle realizes at that step (:func:`tightened_lag_gaps`): a bound on the realized
  jerk, which for a multirotor is its tilt rate.

The cost is the nominal task cost ``C`` (quadratic tracking of the goal plus
input effort) plus a small, ``recovery_weight``-scaled cost on each recovery
branch: input effort, and (``recovery_tracking``) tracking of its region's
centre. Either makes the recovery plans unique; tracking also pulls the
shared first input toward the regions, which at 200 steps with regions far
away holds the robot back from its goal, so the hardware scene uses effort
only.

The linear model splits into chains that do not interact (for the hover
model ``(x, vx, theta, q)``, ``(y, vy, phi, p)``, ``(z, vz)``, ``(psi, r)``;
for the point mass one per axis). The weights are diagonal, the constraints
are boxes and the consensus equalities hold input by input, so eq. 3
separates *exactly* into one small QP per chain: the cost is the sum of the
chains' costs and the plan is feasible when every chain is. :func:`decouple`
finds the chains from the model's sparsity (nothing is hard-coded), and
:class:`BranchProblem` solves one :class:`ChainQP` per chain (on threads with
``workers > 1``; OSQP releases the GIL) and stitches the plan together. Many
subsets share a chain problem (both grass fields lie at the same ``x``),
which a shared cache of chain QPs turns into one solve. A chain's cost per
ADMM iteration grows linearly with ``T``.

A :class:`ChainQP` has a fixed shape (number of branches, horizon) and is
built and factorized once; each tick only vectors change (initial state,
bounds that encode ``s`` and ``K``, targets), and OSQP warm-starts from the
previous solution shifted one step. Shrinking horizons and consensus are
bound updates, not new problems.

Feasibility is decided, not guessed (``SolveStatus.decided``): a solve that
stops at its iteration cap or time limit is no evidence either way. Such a
chain goes to a referee, PIQP, an interior-point method that settles it (a
solution, or a certificate of infeasibility) in a few tens of iterations
where ADMM near the edge of feasibility can take thousands; its answer
warm-starts OSQP's next tick. What neither settles within its budget is
reported as undecided, not infeasible, and the same call again resumes from
where it stopped.

Robustness details for a plant that is not the linear model:

* constraints on velocity, tilt and rates are tightened by ``shrink`` (3 %),
  and velocity by ``velocity_margin`` more (0.25 m/s on the paper's vehicle,
  the overshoot measured when a turn-around is planned at the limit; 0.1 m/s
  for the point mass), so model errors do not violate the true limits;
* if the measured state already exceeds a tightened bound (model error), the
  bounds of the first ``relax_steps`` steps (after ``relax_lag``) are widened
  by that excess, at least by ``relax_floor`` on the symmetric limits,
  tapering linearly to zero, so the problem stays feasible while the plan
  brings the state back; and on each step by what a lag still pushing a state
  toward its bound carries it over when braking as hard as its gap allows
  (:func:`carried_excess`);
* AESOP's plans sit on the edge of feasibility (the nominal branch pulls them
  there), where a plant a hair off its plan turns the next tick infeasible.
  With ``reserve_steps = R`` the tree promises its regions ``R`` steps before
  ``T``, and the promise relaxes to ``T`` while the reasoner thinks
  (:func:`promised_step`): every tick brings ``R / K`` steps of slack.

With ``soft=True`` every recovery branch carries an L1-priced slack per
state component that shifts its state box (limits and region alike; the
shift moves the box, it does not widen it, and the nominal branch has none).
A region out of reach then costs slack instead of making the problem
infeasible; a plan is *feasible* when the solver converged and the largest
slack is below ``slack_tolerance``. The baselines need this (their
least-violating plan), and AESOP flies it only when even the hard recovery
without a deadline is shown infeasible. Caveat, measured against the CVXPY
reference: OSQP's slack estimate at ``eps = 1e-3`` runs at about ``10 eps``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np
import osqp
import piqp
import scipy.sparse as sp

from .planning import PlanningModel
from .regions import Region


class SolveStatus(StrEnum):
    SOLVED = "solved"
    INACCURATE = "solved_inaccurate"
    INFEASIBLE = "infeasible"
    MAX_ITER = "max_iter"
    TIME_LIMIT = "time_limit"
    FAILED = "failed"

    @property
    def feasible(self) -> bool:
        return self is SolveStatus.SOLVED

    @property
    def decided(self) -> bool:
        """Whether the solve settled feasibility: solved, or a certificate of infeasibility.

        A solve stopped by its iteration cap or time limit (or an inaccurate one)
        is no evidence either way: the problem may well be feasible.
        """
        return self in (SolveStatus.SOLVED, SolveStatus.INFEASIBLE)


_OSQP_STATUS = {
    osqp.SolverStatus.OSQP_SOLVED: SolveStatus.SOLVED,
    osqp.SolverStatus.OSQP_SOLVED_INACCURATE: SolveStatus.INACCURATE,
    osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE: SolveStatus.INFEASIBLE,
    # OSQP reports an inaccurate certificate only when it stopped at its cap
    osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE: SolveStatus.MAX_ITER,
    osqp.SolverStatus.OSQP_MAX_ITER_REACHED: SolveStatus.MAX_ITER,
    osqp.SolverStatus.OSQP_TIME_LIMIT_REACHED: SolveStatus.TIME_LIMIT,
}


_NO_TIME_LIMIT = 1e10  # s, OSQP's default (it refuses 0)


@dataclass(frozen=True)
class Weights:
    """Diagonal quadratic weights of the tracking cost, per kind of coordinate
    (:attr:`.planning.PlanningModel.state_groups` and ``input_groups``)."""

    position: float = 1.0  # 1/m^2
    velocity: float = 0.2  # s^2/m^2
    attitude: float = 0.5  # 1/rad^2
    rate: float = 0.1  # s^2/rad^2
    thrust: float = 0.05  # 1/N^2
    torque: float = 1.0  # 1/(N m)^2
    acceleration: float = 0.5  # s^4/m^2, on the commanded acceleration
    lag: float = 0.0  # s^4/m^2, on the realized acceleration (a lag state)

    def state(self, model: PlanningModel) -> np.ndarray:
        return np.array([getattr(self, group) for group in model.state_groups])

    def input(self, model: PlanningModel) -> np.ndarray:
        return np.array([getattr(self, group) for group in model.input_groups])


@dataclass(frozen=True)
class MPCConfig:
    horizon: int = 40  # T, steps
    consensus: int = 15  # K, steps
    weights: Weights = field(default_factory=Weights)
    recovery_weight: float = 0.01  # scale of the recovery branches' own cost
    # share of that cost that tracks the region's centre (the rest is input effort). Eq. 3
    # prices only the nominal branch; input effort alone keeps recovery plans unique. Over a
    # long horizon with regions far away, tracking them pulls the robot back from its goal.
    recovery_tracking: float = 1.0
    shrink: float = 0.03  # fraction by which symmetric state limits and input limits tighten
    position_margin: float = 0.05  # m: fence and region boxes planned this far inside
    # m/s: velocity limits planned this much further inside. On the paper's vehicle the
    # plant's horizontal acceleration is g tan(theta), not the model's g theta, and the
    # attitude chain reverses slowly: a turn-around planned at the limit overshoots ~0.2 m/s.
    velocity_margin: float = 0.25
    input_margin: float = 0.005  # least tightening of an input bound (OSQP is eps-exact)
    # share of a lag gap (the realized-jerk bound, i.e. the tilt rate) held back beyond
    # shrink: a vehicle's attitude loop, lagging the exponential its command asks for, and
    # its own velocity feedback overshoot the tilt rate that the lag alone implies
    jerk_margin: float = 0.0
    relax_steps: int = 20  # steps over which an initial-state excess is tapered out (2 s at
    # dt 0.1: the paper vehicle's attitude chain needs about 1 s to take off the margin)
    # steps before the taper starts: the excess is allowed in full up to step relax_lag. The
    # hover model cannot change velocity in one step (1); a point mass can (0), and with a
    # lag it would keep the excess forever, braking only "from the next step" every tick.
    # A count of model steps (not rescaled with the grid, unlike STEP_FIELDS in scenario.py).
    relax_lag: int = 1
    # least widening of the symmetric limits (m/s, rad, rad/s) in those first steps: a
    # state just inside its box can be carried over it by dynamics no input can stop at
    # once (a point mass's acceleration lag); this keeps such a state feasible. It spends
    # part of the margin between the planned and the true limits, so it must be smaller.
    relax_floor: float = 0.0
    # R, steps: nominal selection promises the regions R steps before T, and while the
    # reasoner thinks (or a hold lasts) the promise relaxes linearly to T at k = K. A plan
    # sits on the edge of its promise (the nominal branch pulls it there), and a plant that
    # lags its plan a little would push it over; the relaxing promise gives each tick R/K
    # steps of slack to absorb that. Theorem 1's deadline, T after the anomaly, still holds.
    reserve_steps: int = 0
    min_region_step: int = 5  # earliest step a shrinking horizon may pin a region to
    late_region_steps: int = 5  # how far an unreachable region deadline is pushed back per try
    slack_weight: float = 1000.0  # L1 price per unit of constraint violation
    slack_tolerance: float = 1e-2  # largest slack (m, m/s, rad) a feasible plan may have
    eps_abs: float = 1e-3
    eps_rel: float = 1e-3
    eps_prim_inf: float = 1e-3  # OSQP's primal-infeasibility tolerance (certificate accuracy)
    # A solve stopped by either cap has not decided feasibility (SolveStatus.decided): the
    # selector does not count it as infeasible, and the next tick resumes from its iterate.
    max_iter: int = 1000  # per warm solve
    max_iter_cold: int = 2000  # the first solve of a problem (off the loop, in warm-up)
    time_limit_s: float = 0.0  # per warm chain solve, 0: none (the tick's budget, not a verdict)
    # PIQP iterations to settle what OSQP left undecided at its cap (0: no referee)
    referee_max_iter: int = 80
    workers: int = 1  # threads solving the chains of one problem (OSQP releases the GIL)

    def __post_init__(self) -> None:
        if not 0 <= self.consensus < self.horizon:
            raise ValueError("need 0 <= consensus < horizon")
        if not 0.0 <= self.jerk_margin < 1.0 - self.shrink:
            raise ValueError("need 0 <= jerk_margin < 1 - shrink")
        if not 0.0 <= self.recovery_tracking <= 1.0:
            raise ValueError("need 0 <= recovery_tracking <= 1")
        if not 1 <= self.min_region_step <= self.horizon:
            raise ValueError("need 1 <= min_region_step <= horizon")
        if not 0 <= self.reserve_steps <= self.horizon - self.consensus:
            raise ValueError("need 0 <= reserve_steps <= horizon - consensus")
        if self.late_region_steps < 1:
            raise ValueError("need late_region_steps >= 1")
        if self.relax_steps < 1 or self.relax_lag < 0:
            raise ValueError("need relax_steps >= 1 and relax_lag >= 0")
        if self.max_iter < 1 or self.max_iter_cold < 1 or self.workers < 1:
            raise ValueError("need max_iter, max_iter_cold and workers >= 1")
        if self.time_limit_s < 0:
            raise ValueError("need time_limit_s >= 0")

    @property
    def lag_gap_share(self) -> float:
        """The share of each lag gap (``|u - a|``) an input may use: ``shrink`` and
        ``jerk_margin`` are held back."""
        return 1.0 - self.shrink - self.jerk_margin


@dataclass(frozen=True)
class Plan:
    """One solve of eq. 3. Trajectories are ``(T+1, n)`` arrays of model states."""

    status: SolveStatus
    cost: float
    u0: np.ndarray  # absolute first input
    inputs: np.ndarray  # (T, m) absolute inputs of the branch the robot follows
    nominal: np.ndarray | None
    recovery: dict[int, np.ndarray]
    recovery_inputs: dict[int, np.ndarray]  # (T, m) absolute inputs per region
    consensus: int
    region_step: int
    iterations: int
    solve_ms: float
    slack: float = 0.0  # largest constraint violation of a recovery branch
    slack_tolerance: float = 1e-2
    refereed: int = 0  # chains whose verdict came from the PIQP referee

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
    floor: np.ndarray  # least early widening per state (relax_floor on symmetric limits)
    # (lag state, its input, lo, hi), chain-local: lo <= du[k] - x[k] <= hi on every step
    lags: tuple[tuple[int, int, float, float], ...] = ()


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
    refereed: bool = False


@dataclass(frozen=True)
class _Raw:
    """What a solver returned: primal, OSQP-convention duals, objective, iterations."""

    status: SolveStatus
    x: np.ndarray
    y: np.ndarray
    objective: float
    iterations: int
    refereed: bool = False


def tightened_states(model: PlanningModel, config: MPCConfig) -> tuple[np.ndarray, np.ndarray]:
    """The state box the MPC plans in: the model's symmetric limits (velocity, tilt, rates)
    scaled by ``1 - shrink``, velocity ``velocity_margin`` further in, the position fence
    moved ``position_margin`` inward; free coordinates (yaw) untouched."""
    lo, hi = model.x_lo.copy(), model.x_hi.copy()
    sym, vel, pos = list(model.symmetric), list(model.velocity), list(model.position)
    lo[sym] *= 1.0 - config.shrink
    hi[sym] *= 1.0 - config.shrink
    lo[pos] += config.position_margin
    hi[pos] -= config.position_margin
    lo[vel] += config.velocity_margin
    hi[vel] -= config.velocity_margin
    return lo, hi


def promised_step(config: MPCConfig, k: int) -> int:
    """The step, counted from now, by which a tree promises its regions ``k`` ticks after
    the promise was made at full K and T: ``T - R`` at first, relaxing linearly to
    Algorithm 1's ``T - k`` at ``k = K`` (``R = reserve_steps``)."""
    r, big_k = config.reserve_steps, max(config.consensus, 1)
    reserve = r - (r * min(k, big_k)) // big_k
    return config.horizon - k - reserve


CARRY_STEPS = 40  # the braking flight simulated at most (2 s on the hardware grid)


def carried_excess(chain: Chain, x0: np.ndarray, config: MPCConfig) -> np.ndarray:
    """``(T, n)``: how far over its tightened box each state of ``chain`` is carried on steps
    ``k = 1..T`` when every lagged input brakes as hard as its lag gap allows from ``x0``.

    A lag state still pushing a velocity toward its cap carries it over before any command
    can stop it (the gap bounds how fast the command may turn). Nothing would then be
    feasible, not even with no deadline, and the least-violating plan's slack shifts the
    whole velocity box: on the second airframe it flew 1.24 m/s against the 1 m/s limit
    (issue 46). The braking flight is feasible by construction, so the box is widened by
    what it is carried over, on the steps it is. Simulated until every state the lags
    drive turns back inside its box (a step or two in nominal flight)."""
    out = np.zeros((config.horizon, len(chain.states)))
    if not chain.lags:
        return out
    x = np.asarray(x0, dtype=float)
    lags = [(state, channel, gap_lo, gap_hi, _driven(chain, state))
            for state, channel, gap_lo, gap_hi in chain.lags]
    driven_states = [lag[4] for lag in lags]
    u = np.zeros(len(chain.inputs))
    for k in range(min(config.horizon, CARRY_STEPS)):
        before = np.abs(x[driven_states])
        for state, channel, gap_lo, gap_hi, driven in lags:
            stop = -x[driven] / (chain.a[driven, state] or 1.0)  # stops it in a step, at most
            toward = min(max(stop, chain.du_lo[channel]), chain.du_hi[channel])
            u[channel] = min(max(toward, x[state] + gap_lo), x[state] + gap_hi)
        x = chain.a @ x + chain.b @ u
        out[k] = np.maximum(np.maximum(x - chain.x_hi, chain.x_lo - x), 0.0)
        if not out[k].any() and np.all(np.abs(x[driven_states]) <= before):
            break  # inside, and braking: nothing more to carry
    return out


def _driven(chain: Chain, state: int) -> int:
    """The chain state the lag ``state`` drives most (a point mass's velocity)."""
    pushed = np.abs(chain.a[:, state]).copy()
    pushed[state] = 0.0
    return int(np.argmax(pushed))


def relax_taper(config: MPCConfig) -> np.ndarray:
    """``(T,)``: the share of an initial-state excess over the tightened box that the bounds
    of steps ``k = 1..T`` allow: 1 up to step ``relax_lag``, then falling linearly to 0
    over ``relax_steps`` steps."""
    steps = np.arange(1, config.horizon + 1)
    return np.clip(1.0 - (steps - config.relax_lag) / config.relax_steps, 0.0, 1.0)


def planning_box(model: PlanningModel, region: Region, config: MPCConfig
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A region's ``(lo, hi)`` in model coordinates as the MPC aims for it: its position
    box shrunk by ``position_margin`` (at most to a quarter of its width), so that the
    plant, a little off the linear plan, still lands inside."""
    lo, hi = model.region_box(region)
    pos = list(model.position)
    margin = np.minimum(config.position_margin, (hi[pos] - lo[pos]) / 4)
    lo[pos] += margin
    hi[pos] -= margin
    return lo, hi


def tightened_inputs(model: PlanningModel, config: MPCConfig) -> tuple[np.ndarray, np.ndarray]:
    """The input box the MPC plans in, relative to hover: each bound moved inward by
    ``shrink`` of its distance from hover, and at least ``input_margin``, so that a
    solution accurate to OSQP's tolerance still respects the true limits."""
    u_hover = model.linear.u_hover
    du_lo, du_hi = model.u_lo - u_hover, model.u_hi - u_hover
    hi = du_hi - np.maximum(config.shrink * np.abs(du_hi), config.input_margin)
    lo = du_lo + np.maximum(config.shrink * np.abs(du_lo), config.input_margin)
    if np.any(lo >= hi):
        raise ValueError("input bounds too narrow for the configured margins")
    return lo, hi


def tightened_lag_gaps(model: PlanningModel, config: MPCConfig
                       ) -> list[tuple[int, int, float, float]]:
    """``(state, input, lo, hi)`` per lag state with a finite ``lag_gap``: the bounds on
    ``du[k] - a[k]`` (input relative to hover, minus the lag state at the same step) that
    keep ``|u - a|`` within the gap tightened by ``shrink + jerk_margin``. The first step
    is always feasible: ``u_0 = a_0``, a filter of past commands inside the input box."""
    first = model.n - model.n_lag
    out = []
    for j, (channel, gap) in enumerate(zip(model.lag_inputs, model.lag_gap, strict=False)):
        if np.isfinite(gap):
            width = gap * config.lag_gap_share
            hover = float(model.linear.u_hover[channel])
            out.append((first + j, channel, -width - hover, width - hover))
    return out


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

    Variables, branch after branch: ``x_b[0..T]`` then ``du_b[0..T-1]``; then,
    when ``soft``, ``sigma+`` and ``sigma-`` (``n`` each) per recovery slot.
    Rows: initial states, dynamics, state boxes on steps ``1..T`` (region rows
    are these rows with tighter bounds), input boxes, the lag gaps (each command
    against its lag state at the same step), the first input shared
    with the nominal branch, consecutive recovery branches' consensus on every
    step (free from ``K'`` on), and the slacks' signs.
    """

    def __init__(self, chain: Chain, config: MPCConfig, n_recovery: int,
                 nominal: bool = True, soft: bool = False) -> None:
        self.chain, self.config = chain, config
        self.n, self.m = chain.a.shape[0], chain.b.shape[1]
        self.n_rec, self.has_nominal, self.soft = n_recovery, nominal, soft
        self.n_branches = n_recovery + int(nominal)
        horizon = config.horizon
        self.branch_size = (horizon + 1) * self.n + horizon * self.m
        self._n_sigma = 2 * self.n * n_recovery if soft else 0
        self.n_var = self.n_branches * self.branch_size + self._n_sigma
        self._build()
        self._var_shift, self._con_shift = self._shift_maps()
        self._previous: tuple[np.ndarray, np.ndarray] | None = None
        self._memo: tuple[bytes, ChainSolution] | None = None
        self._pending_key: bytes | None = None  # the last call, if it did not decide
        self._warm = False
        self.solver = osqp.OSQP()
        self.solver.setup(self._p, self._q.copy(), self._a, self._lower.copy(), self._upper.copy(),
                          eps_abs=config.eps_abs, eps_rel=config.eps_rel,
                          eps_prim_inf=config.eps_prim_inf, max_iter=config.max_iter_cold,
                          verbose=False, warm_starting=True, polishing=False,
                          check_termination=5)

    # -- layout -----------------------------------------------------------------------------
    def _x_index(self) -> np.ndarray:
        """Variable index of ``x_b[k][i]``, shape ``(branches, T+1, n)``."""
        nb, horizon, n = self.n_branches, self.config.horizon, self.n
        base = np.arange(nb)[:, None, None] * self.branch_size
        index: np.ndarray = base + np.arange((horizon + 1) * n).reshape(1, horizon + 1, n)
        return index

    def _u_index(self) -> np.ndarray:
        """Variable index of ``du_b[k][j]``, shape ``(branches, T, m)``."""
        nb, horizon, n, m = self.n_branches, self.config.horizon, self.n, self.m
        base = np.arange(nb)[:, None, None] * self.branch_size + (horizon + 1) * n
        index: np.ndarray = base + np.arange(horizon * m).reshape(1, horizon, m)
        return index

    def _sigma(self, slot: int) -> int:
        """First of ``2 n`` slack variables (sigma+, then sigma-) of recovery slot ``slot``."""
        return int(self.n_branches * self.branch_size + 2 * slot * self.n)

    def _build(self) -> None:
        n, m, horizon, nb = self.n, self.m, self.config.horizon, self.n_branches
        a_dyn, b_dyn = self.chain.a, self.chain.b
        xi, ui = self._x_index(), self._u_index()
        self._xi, self._ui = xi, ui
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        vals: list[np.ndarray] = []
        bounds: list[tuple[np.ndarray, np.ndarray]] = []
        count = 0

        def add(r: np.ndarray, c: np.ndarray, v: np.ndarray | float, height: int,
                lo: np.ndarray | float = 0.0, hi: np.ndarray | float = 0.0) -> int:
            """Append ``height`` rows (local row numbers ``r``); returns their first row."""
            nonlocal count
            rows.append(count + np.asarray(r).ravel())
            cols.append(np.asarray(c).ravel())
            vals.append(np.broadcast_to(v, np.shape(c)).ravel())
            bounds.append((np.broadcast_to(lo, height).copy(), np.broadcast_to(hi, height).copy()))
            first, count = count, count + height
            return first

        # initial state: x_b[0] = x_t (bounds set per solve)
        init = np.arange(nb * n).reshape(nb, n)
        self._init_rows = add(init, xi[:, 0, :], 1.0, nb * n)
        # dynamics: x_b[k+1] - A x_b[k] - B du_b[k] = 0, row (b, k, i)
        dyn = np.arange(nb * horizon * n).reshape(nb, horizon, n)
        ai, aj = np.nonzero(a_dyn)
        bi, bj = np.nonzero(b_dyn)
        r = [dyn, dyn[..., ai], dyn[..., bi]]
        c = [xi[:, 1:, :], xi[:, :-1, aj], ui[:, :, bj]]
        v = [np.ones(dyn.shape), np.broadcast_to(-a_dyn[ai, aj], dyn[..., ai].shape),
             np.broadcast_to(-b_dyn[bi, bj], dyn[..., bi].shape)]
        add(np.concatenate([x.ravel() for x in r]), np.concatenate([x.ravel() for x in c]),
            np.concatenate([x.ravel() for x in v]), nb * horizon * n)
        # state boxes on steps 1..T, row (b, k-1, i); soft recovery rows: x - sigma+ + sigma-
        box = np.arange(nb * horizon * n).reshape(nb, horizon, n)
        r, c, v = [box], [xi[:, 1:, :]], [np.ones(box.shape)]
        if self.soft and self.n_rec:
            rec = box[int(self.has_nominal):]  # (n_rec, T, n)
            sig = np.array([self._sigma(s) for s in range(self.n_rec)])[:, None, None] \
                + np.arange(n)[None, None, :]
            sig = np.broadcast_to(sig, rec.shape)
            r += [rec, rec]
            c += [sig, sig + n]
            v += [np.full(rec.shape, -1.0), np.ones(rec.shape)]
        self._state_rows = add(np.concatenate([x.ravel() for x in r]),
                               np.concatenate([x.ravel() for x in c]),
                               np.concatenate([x.ravel() for x in v]), nb * horizon * n)
        # input boxes, row (b, k, j)
        self._input_rows = add(np.arange(nb * horizon * m), ui, 1.0, nb * horizon * m,
                               np.tile(self.chain.du_lo, nb * horizon),
                               np.tile(self.chain.du_hi, nb * horizon))
        # commands within the lag gap of the realized acceleration, row (b, k, l)
        lags = self.chain.lags
        n_lag = len(lags)
        gap = np.arange(nb * horizon * n_lag).reshape(nb, horizon, n_lag)
        lag_x = xi[:, :-1, [state for state, _, _, _ in lags]]
        lag_u = ui[:, :, [channel for _, channel, _, _ in lags]]
        self._lag_rows = add(np.concatenate([gap.ravel(), gap.ravel()]),
                             np.concatenate([lag_u.ravel(), lag_x.ravel()]),
                             np.concatenate([np.ones(gap.size), -np.ones(gap.size)]), gap.size,
                             np.tile([lo for _, _, lo, _ in lags], nb * horizon),
                             np.tile([hi for _, _, _, hi in lags], nb * horizon))
        # the first input shared with the nominal branch
        if self.has_nominal and self.n_rec:
            share = np.arange(self.n_rec * m).reshape(self.n_rec, m)
            add(np.concatenate([share.ravel(), share.ravel()]),
                np.concatenate([np.broadcast_to(ui[0, 0], share.shape).ravel(),
                                ui[1:, 0, :].ravel()]),
                np.concatenate([np.ones(share.size), -np.ones(share.size)]), share.size)
        # recovery consensus: consecutive recovery branches share inputs 0..K'-1
        first = int(self.has_nominal)
        n_pairs = max(0, self.n_rec - 1)
        cons = np.arange(n_pairs * horizon * m).reshape(n_pairs, horizon, m)
        left = ui[first:first + n_pairs]
        right = ui[first + 1:first + 1 + n_pairs]
        self._consensus_rows = add(np.concatenate([cons.ravel(), cons.ravel()]),
                                   np.concatenate([left.ravel(), right.ravel()]),
                                   np.concatenate([np.ones(cons.size), -np.ones(cons.size)]),
                                   cons.size)
        # slack: sigma+ >= 0 and sigma- >= 0
        n_sig = self._n_sigma
        self._sigma_rows = add(np.arange(n_sig), self._sigma(0) + np.arange(n_sig), 1.0, n_sig,
                               0.0, np.inf)
        self._a = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                        np.concatenate(cols))),
                                shape=(count, self.n_var))
        self._lower = np.concatenate([lo for lo, _ in bounds])
        self._upper = np.concatenate([hi for _, hi in bounds])
        # rows that bound one variable (state, input and slack boxes): PIQP's variable bounds
        self._rows = self._a.tocsr()
        single = np.diff(self._rows.indptr) == 1
        single[self._init_rows:self._init_rows + nb * n] = False
        entry = self._rows.indptr[:-1].clip(max=max(self._rows.nnz - 1, 0))
        self._bound_rows = single & (self._rows.data[entry] == 1.0)
        self._bound_vars = self._rows.indices[entry[self._bound_rows]]
        self._build_cost()

    def _build_cost(self) -> None:
        cfg, nb = self.config, self.n_branches
        scale = np.array([1.0 if (b == 0) else cfg.recovery_weight for b in range(nb)])
        tracking = scale * np.array([1.0 if (b == 0) else cfg.recovery_tracking
                                     for b in range(nb)])
        self._branch_scale = tracking  # of the state cost, for the constant OSQP leaves out
        diag = np.zeros(self.n_var)
        diag[self._xi[:, 1:, :]] = tracking[:, None, None] * self.chain.q_state
        diag[self._ui] = scale[:, None, None] * self.chain.r_input
        q = np.zeros(self.n_var)
        if self._n_sigma:
            sig = slice(self._sigma(0), self._sigma(0) + self._n_sigma)
            diag[sig] = 1e-6
            q[sig] = cfg.slack_weight
        self._diag = diag
        self._q_target = diag[self._xi[:, 1:, :]]  # (branches, T, n): sum w (x - t)^2
        # OSQP minimises 1/2 z'Pz + q'z: P = 2 diag gives sum(w * z^2)
        self._p = sp.diags(2 * diag, format="csc")
        self._q = q

    def _shift_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """Index maps that advance a solution by one step, for a shifted warm start.

        Entry ``i`` says which entry of the previous primal (dual) solution
        initializes entry ``i`` now: step ``k`` takes step ``k + 1``, and the
        last step repeats.
        """
        horizon = self.config.horizon
        var = np.arange(self.n_var)
        xi, ui = self._xi, self._ui
        var[xi] = xi[:, np.minimum(np.arange(horizon + 1) + 1, horizon), :]
        var[ui] = ui[:, np.minimum(np.arange(horizon) + 1, horizon - 1), :]
        con = np.arange(self._a.shape[0])

        def advance(base: int, groups: int, width: int) -> None:
            idx = np.arange(groups * horizon * width).reshape(groups, horizon, width)
            src = np.concatenate([idx[:, 1:], idx[:, -1:]], axis=1)
            con[base:base + idx.size] = base + src.ravel()

        nb = self.n_branches
        advance(self._init_rows + nb * self.n, nb, self.n)  # dynamics rows
        advance(self._state_rows, nb, self.n)
        advance(self._input_rows, nb, self.m)
        advance(self._lag_rows, nb, len(self.chain.lags))
        advance(self._consensus_rows, max(0, self.n_rec - 1), self.m)
        return var, con

    # -- solve ------------------------------------------------------------------------------
    def solve(self, x0: np.ndarray, goal: np.ndarray, boxes: Sequence[Box], consensus: int,
              s: int) -> ChainSolution:
        """Solve for the chain's part of the measured state ``x0`` and of ``goal``.

        ``boxes`` fill the recovery slots in order; ``consensus`` (K') and
        ``s`` (the step from which recovery branches lie in their box) are in
        steps. The same decided call twice in a row returns the first answer;
        an undecided one resumes from where it stopped. A non-finite ``x0`` or
        ``goal`` is refused (``FAILED``) without a solve.
        """
        cfg, n, m, horizon, nb = self.config, self.n, self.m, self.config.horizon, self.n_branches
        if len(boxes) != self.n_rec:
            raise ValueError(f"expected {self.n_rec} regions, got {len(boxes)}")
        if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(goal))):
            return ChainSolution(SolveStatus.FAILED, float("inf"), None, None, float("inf"), 0,
                                 0.0)
        key = b"".join([x0.tobytes(), goal.tobytes(), np.array([consensus, s]).tobytes(),
                        *(box.key() for box in boxes)])
        if self._memo is not None and self._memo[0] == key:
            return replace(self._memo[1], iterations=0, solve_ms=0.0)
        chain = self.chain
        lo, hi = self._lower.copy(), self._upper.copy()
        init = slice(self._init_rows, self._init_rows + nb * n)
        lo[init] = hi[init] = np.tile(x0, nb)
        # state boxes, widened early on by any excess of x0 over the tightened limits
        excess = np.maximum(np.maximum(x0 - chain.x_hi, chain.x_lo - x0), chain.floor)
        widen = np.maximum(relax_taper(cfg)[:, None] * excess[None, :],  # (T, n), k = 1..T
                           carried_excess(chain, x0, cfg))
        box_lo = np.repeat((chain.x_lo - widen)[None], nb, axis=0)
        box_hi = np.repeat((chain.x_hi + widen)[None], nb, axis=0)
        targets = np.empty((nb, n))
        if self.has_nominal:
            targets[0] = goal
        for slot, box in enumerate(boxes):
            b = slot + int(self.has_nominal)
            targets[b] = box.center
            box_lo[b, s - 1:] = np.maximum(box_lo[b, s - 1:], box.lo - widen[s - 1:])
            box_hi[b, s - 1:] = np.minimum(box_hi[b, s - 1:], box.hi + widen[s - 1:])
        rows = slice(self._state_rows, self._state_rows + nb * horizon * n)
        lo[rows], hi[rows] = box_lo.ravel(), box_hi.ravel()
        q = self._q.copy()
        q[self._xi[:, 1:, :]] = -2 * self._q_target * targets[:, None, :]
        # consensus: active for steps < K', free afterwards
        n_pairs = max(0, self.n_rec - 1)
        cons = slice(self._consensus_rows, self._consensus_rows + n_pairs * horizon * m)
        free = np.full((n_pairs, horizon, m), np.inf)
        free[:, :consensus] = 0.0
        lo[cons], hi[cons] = -free.ravel(), free.ravel()
        if np.any(lo > hi):  # a region outside the state limits: nothing to solve
            solution = self._solution(None, targets, 0.0)
        else:
            resume = self._pending_key == key
            solution = self._run(q, lo, hi, targets, shift=not resume)
        # an undecided answer is not remembered: the same call again resumes the solve
        # from its iterate as it stands (not shifted: no tick has passed)
        decided = solution.status.decided
        self._memo = (key, solution) if decided else None
        self._pending_key = None if decided else key
        return solution

    def _run(self, q: np.ndarray, lo: np.ndarray, hi: np.ndarray,
             targets: np.ndarray, shift: bool = True) -> ChainSolution:
        """OSQP, warm-started from the last iterate (``shift``: advanced one step); if it
        stops at its iteration cap without deciding, PIQP referees."""
        cfg = self.config
        infinity = osqp.constant("OSQP_INFTY")
        start_time = time.perf_counter()
        self.solver.update(q=q, l=np.where(np.isfinite(lo), lo, -infinity),
                           u=np.where(np.isfinite(hi), hi, infinity))
        if self._previous is not None:
            z_prev, y_prev = self._previous
            if shift:
                z_prev, y_prev = z_prev[self._var_shift], y_prev[self._con_shift]
            self.solver.warm_start(x=z_prev, y=y_prev)
        warm = self._previous is not None
        if warm != self._warm:
            limit = cfg.time_limit_s if warm and cfg.time_limit_s > 0 else _NO_TIME_LIMIT
            self.solver.update_settings(max_iter=cfg.max_iter if warm else cfg.max_iter_cold,
                                        time_limit=limit)
            self._warm = warm
        result = self.solver.solve(raise_error=False)
        raw = _Raw(_OSQP_STATUS.get(result.info.status_val, SolveStatus.FAILED), result.x,
                   result.y, float(result.info.obj_val), int(result.info.iter))
        # stopped at its iteration cap: referee; at its time limit the tick's budget is spent
        out_of_time = raw.status is SolveStatus.TIME_LIMIT or (
            warm and cfg.time_limit_s > 0
            and time.perf_counter() - start_time >= cfg.time_limit_s)
        if not raw.status.decided and not out_of_time and cfg.referee_max_iter > 0:
            judged = self._referee(q, lo, hi)
            raw = replace(judged, iterations=raw.iterations + judged.iterations, refereed=True)
        solve_ms = (time.perf_counter() - start_time) * 1e3
        if raw.status is not SolveStatus.FAILED and raw.status is not SolveStatus.INFEASIBLE \
                and np.all(np.isfinite(raw.x)) and np.all(np.isfinite(raw.y)):
            # a capped iterate is kept too: the next tick resumes from it, shifted
            self._previous = (raw.x.copy(), raw.y.copy())
        return self._solution(raw, targets, solve_ms)

    def _referee(self, q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> _Raw:
        """The same QP by PIQP, an interior-point method that settles feasibility (a
        solution or a certificate) in a few tens of iterations where ADMM can take
        thousands. Single-variable box rows become variable bounds; its duals are mapped
        to OSQP's (``y = z_u - z_l``) so that its answer warm-starts the next tick.

        One that stops at its cap is run once more with every KKT solve refined: whether
        PIQP certifies an infeasible chain depends on the CPU's floating point (one that
        CI certified within the cap stalled past 1,000 iterations on an AMD EPYC without
        AVX-512, its step lengths at 0; refined, it is certified in 35)."""
        raw = self._piqp(q, lo, hi, refine=False)
        if raw.status is not SolveStatus.MAX_ITER:
            return raw
        again = self._piqp(q, lo, hi, refine=True)
        return replace(again, iterations=raw.iterations + again.iterations)

    def _piqp(self, q: np.ndarray, lo: np.ndarray, hi: np.ndarray, *, refine: bool) -> _Raw:
        cfg = self.config
        bound = self._bound_rows
        eq = (lo == hi) & ~bound
        ineq = ~eq & ~bound & (np.isfinite(lo) | np.isfinite(hi))
        x_lo = np.full(self.n_var, -np.inf)
        x_hi = np.full(self.n_var, np.inf)
        x_lo[self._bound_vars] = lo[bound]
        x_hi[self._bound_vars] = hi[bound]
        solver = piqp.SparseSolver()
        settings = solver.settings
        settings.verbose = False
        settings.max_iter = cfg.referee_max_iter
        settings.eps_abs, settings.eps_rel = cfg.eps_abs / 10, cfg.eps_rel / 10
        settings.iterative_refinement_always_enabled = refine
        a = self._rows
        solver.setup(self._p, q, a[eq].tocsc(), lo[eq], a[ineq].tocsc(), lo[ineq], hi[ineq],
                     x_lo, x_hi)
        code = solver.solve()
        out = solver.result
        status = {piqp.PIQP_SOLVED: SolveStatus.SOLVED,
                  piqp.PIQP_PRIMAL_INFEASIBLE: SolveStatus.INFEASIBLE,
                  piqp.PIQP_MAX_ITER_REACHED: SolveStatus.MAX_ITER}.get(code, SolveStatus.FAILED)
        y = np.zeros(len(lo))
        y[eq] = out.y
        y[ineq] = out.z_u - out.z_l
        y[bound] = (out.z_bu - out.z_bl)[self._bound_vars]
        return _Raw(status, np.asarray(out.x), y, float(out.info.primal_obj),
                    int(out.info.iter))

    def _solution(self, raw: _Raw | None, targets: np.ndarray, solve_ms: float
                  ) -> ChainSolution:
        horizon = self.config.horizon
        status = SolveStatus.INFEASIBLE if raw is None else raw.status
        z = None if raw is None else raw.x
        iterations = 0 if raw is None else raw.iterations
        refereed = raw is not None and raw.refereed
        if status not in (SolveStatus.SOLVED, SolveStatus.INACCURATE) or z is None \
                or not np.all(np.isfinite(z)):
            if status in (SolveStatus.SOLVED, SolveStatus.INACCURATE):
                status = SolveStatus.FAILED  # "solved" with a non-finite answer
            return ChainSolution(status, float("inf"), None, None, float("inf"), iterations,
                                 solve_ms, refereed)
        assert raw is not None  # a solved status comes from a solver's answer
        cost = raw.objective
        # the constants OSQP leaves out: sum over branches of w_b * T * t_b' Q t_b
        cost += float(np.sum(self._branch_scale * horizon
                             * np.einsum("bi,i,bi->b", targets, self.chain.q_state, targets)))
        states = z[self._xi]
        inputs = z[self._ui]
        slack = 0.0
        if self._n_sigma:
            sig = z[self._sigma(0):self._sigma(0) + self._n_sigma]
            slack = float(np.max(np.abs(sig)))
            cost -= self.config.slack_weight * float(np.sum(sig))  # report the task cost
        return ChainSolution(status, cost, states, inputs, slack, iterations, solve_ms, refereed)


# key: (chain, recovery branches, nominal?, soft?, config, the regions' chain boxes)
ChainCache = dict[tuple[int, int, bool, bool, MPCConfig, tuple[bytes, ...]], ChainQP]


class BranchProblem:
    """Eq. 3 with a fixed shape: ``nominal`` (0 or 1) + ``n_recovery`` branches.

    ``nominal=False`` is the recovering problem ``J({y}, 0, .)``: the recovery
    branch is the one followed, with full tracking weight toward its region.
    Problems that pass the same ``cache`` share chain QPs: two subsets whose
    regions agree on a chain solve that chain once per state. With an
    ``executor``, the chains of one solve run in its threads (OSQP releases
    the GIL while it iterates).
    """

    def __init__(self, model: PlanningModel, config: MPCConfig, n_recovery: int,
                 nominal: bool = True, soft: bool = False, cache: ChainCache | None = None,
                 executor: Executor | None = None) -> None:
        if n_recovery < 0 or (not nominal and n_recovery != 1):
            raise ValueError("a problem without a nominal branch has exactly one recovery branch")
        self.model, self.config = model, config
        self.n_rec, self.has_nominal, self.soft = n_recovery, nominal, soft
        self.n_branches = n_recovery + int(nominal)
        self.x_lo, self.x_hi = tightened_states(model, config)
        du_lo, du_hi = tightened_inputs(model, config)
        q_state, r_input = config.weights.state(model), config.weights.input(model)
        a, b = model.linear.a, model.linear.b
        floor = np.zeros(model.n)
        floor[list(model.symmetric)] = config.relax_floor
        gaps = tightened_lag_gaps(model, config)
        self.chains = []
        for states, inputs in decouple(a, b):
            s, i = list(states), list(inputs)
            lags = tuple((s.index(state), i.index(channel), lo, hi)
                         for state, channel, lo, hi in gaps if state in s)
            self.chains.append(Chain(states, inputs, a[np.ix_(s, s)], b[np.ix_(s, i)],
                                     self.x_lo[s], self.x_hi[s], du_lo[i], du_hi[i],
                                     q_state[s], r_input[i], floor[s], lags))
        self._cache: ChainCache = {} if cache is None else cache
        self._executor = executor

    def _qp(self, number: int, keys: tuple[bytes, ...]) -> ChainQP:
        key = (number, self.n_rec, self.has_nominal, self.soft, self.config, keys)
        if key not in self._cache:
            self._cache[key] = ChainQP(self.chains[number], self.config, self.n_rec,
                                       self.has_nominal, self.soft)
        return self._cache[key]

    def solve(self, x0: np.ndarray, goal: np.ndarray, regions: Sequence[Region],
              consensus: int | None = None, region_step: int | None = None,
              stop_early: bool = False) -> Plan:
        """Solve for the measured model state ``x0``; ``regions`` fill the recovery slots.

        ``consensus`` (K' steps) and ``region_step`` (s) default to the
        configured K and T; ``region_step = T + 1`` drops the region constraints
        (recovery branches only track their region's centre). ``goal`` is the
        nominal target (a model state). ``stop_early`` stops at the first chain
        that is not feasible (selection needs only the verdict then, not the
        least-violating plan); with an executor all chains run anyway.
        """
        cfg, horizon, model = self.config, self.config.horizon, self.model
        if len(regions) != self.n_rec:
            raise ValueError(f"expected {self.n_rec} regions, got {len(regions)}")
        consensus = cfg.consensus if consensus is None else consensus
        s = min(max(horizon if region_step is None else region_step, 1), horizon + 1)
        nb, n, m = self.n_branches, model.n, model.m
        if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(goal))):  # nothing to solve
            return Plan(SolveStatus.FAILED, float("inf"), model.linear.u_hover.copy(),
                        np.zeros((horizon, m)), None, {}, {}, consensus, s, 0, 0.0)
        planned = [planning_box(model, r, cfg) for r in regions]
        centers = [model.region_center(r) for r in regions]
        jobs = []
        for number, chain in enumerate(self.chains):
            idx = list(chain.states)
            boxes = [Box(lo[idx], hi[idx], c[idx]) for (lo, hi), c in zip(planned, centers,
                                                                           strict=True)]
            order = sorted(range(len(boxes)), key=lambda i: boxes[i].key())
            qp = self._qp(number, tuple(boxes[i].key() for i in order))
            jobs.append((chain, order, qp, (x0[idx], goal[idx], [boxes[i] for i in order],
                                            consensus, s)))
        if self._executor is not None and len(jobs) > 1:
            futures = [self._executor.submit(qp.solve, *args) for _, _, qp, args in jobs]
            solutions = [f.result() for f in futures]
        else:
            solutions = []
            for _, _, qp, args in jobs:
                solutions.append(qp.solve(*args))
                last = solutions[-1]
                if stop_early and (not last.status.feasible or last.slack > cfg.slack_tolerance):
                    break
        states = np.zeros((nb, horizon + 1, n))
        du = np.zeros((nb, horizon, m))
        cost, slack, iterations, solve_ms, refereed = 0.0, 0.0, 0, 0.0, 0
        status = SolveStatus.SOLVED
        for (chain, order, _, _), sol in zip(jobs, solutions, strict=False):
            iterations += sol.iterations
            solve_ms += sol.solve_ms
            refereed += int(sol.refereed)
            if sol.states is None:
                status = _worse(status, sol.status)
                continue
            assert sol.du is not None  # a chain solution has both trajectories or neither
            if status is SolveStatus.SOLVED:
                status = sol.status
            # QP branch of each region: nominal first, then the regions in key order
            branch = list(range(int(self.has_nominal))) + [
                int(self.has_nominal) + order.index(i) for i in range(len(regions))]
            states[:, :, list(chain.states)] = sol.states[branch]
            du[:, :, list(chain.inputs)] = sol.du[branch]
            cost += sol.cost
            slack = max(slack, sol.slack)
        if len(solutions) < len(jobs) and status.feasible:
            status = SolveStatus.INFEASIBLE  # stopped early on a slack-violating chain
        if not status.feasible and status is not SolveStatus.INACCURATE:
            empty = np.zeros((horizon, m))
            return Plan(status, float("inf"), model.linear.u_hover.copy(), empty, None, {}, {},
                        consensus, s, iterations, solve_ms, refereed=refereed)
        inputs = du + model.linear.u_hover
        offset = int(self.has_nominal)
        recovery = {r.index: states[offset + i] for i, r in enumerate(regions)}
        recovery_inputs = {r.index: inputs[offset + i] for i, r in enumerate(regions)}
        return Plan(status, cost, inputs[0][0].copy(), inputs[0],
                    states[0] if self.has_nominal else None, recovery, recovery_inputs,
                    consensus, s, iterations, solve_ms, slack, cfg.slack_tolerance, refereed)


_SEVERITY = {SolveStatus.SOLVED: 0, SolveStatus.INACCURATE: 1, SolveStatus.MAX_ITER: 2,
             SolveStatus.TIME_LIMIT: 2, SolveStatus.INFEASIBLE: 3, SolveStatus.FAILED: 4}


def _worse(a: SolveStatus, b: SolveStatus) -> SolveStatus:
    """The plan's status from its chains': one infeasible chain makes it infeasible; a
    chain that has not decided makes it undecided (unless another proved infeasibility)."""
    return a if _SEVERITY[a] >= _SEVERITY[b] else b
