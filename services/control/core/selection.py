"""Recovery-set selection: the cheapest feasible ``J_t(Y, K, T)`` over subsets ``Y``.

The paper solves eq. 3 for every combination of at least two recovery sets
and keeps the cheapest feasible one. Two facts make most of that work
unnecessary, and both are exact:

* adding a region to ``Y`` only adds constraints, so ``J(Y) <= J(Y')`` for
  ``Y subset Y'``: the cheapest feasible subset is always one of the smallest
  allowed size (``min_size``, 2 in the paper), and a larger one can only tie;
* a region that is infeasible alone is infeasible in every subset holding it.

So the selector solves the subsets of size ``min_size`` only, each with its
own warm solver (:class:`~.mpc.BranchProblem`), and, when ``screen`` is on,
first solves the cheaper single-region problems to skip subsets that contain
an infeasible region. ``aesop bench mpc`` measures what each of these buys.

A subset whose solve stopped at its cap is neither chosen nor counted as
infeasible: :attr:`Selection.decided` says whether every candidate was
settled, so the controller can say why it holds.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .mpc import BranchProblem, ChainCache, MPCConfig, Plan, SolveStatus, promised_step
from .planning import PlanningModel
from .regions import Region


@dataclass(frozen=True)
class Selection:
    """The chosen subset (region indices) and its plan; ``subset=()`` if none is feasible."""

    subset: tuple[int, ...]
    plan: Plan | None
    candidates: dict[tuple[int, ...], Plan]
    solve_ms: float  # wall time of the whole selection

    @property
    def feasible(self) -> bool:
        return self.plan is not None

    @property
    def decided(self) -> bool:
        """Every candidate either solved or was shown infeasible (none stopped at a cap)."""
        return all(p.status.decided for p in self.candidates.values())

    @property
    def status(self) -> SolveStatus:
        """The chosen plan's status, else ``INFEASIBLE`` if every candidate was shown
        infeasible, else the status of one that did not decide."""
        if self.plan is not None:
            return self.plan.status
        undecided = [p.status for p in self.candidates.values() if not p.status.decided]
        return undecided[0] if undecided else SolveStatus.INFEASIBLE


class SubsetSelector:
    """Chooses ``Y_t``. ``workers`` > 1 solves the candidate subsets in threads; the
    config's ``workers`` solve the chains of each problem in threads."""

    def __init__(self, model: PlanningModel, config: MPCConfig, regions: Sequence[Region],
                 min_size: int = 2, screen: bool = False, workers: int = 1,
                 soft: bool = False) -> None:
        self.model, self.config = model, config
        self.regions = {r.index: r for r in regions}
        self.size = max(1, min(min_size, len(self.regions)))
        self.screen = screen and self.size > 1
        self.subsets = list(itertools.combinations(sorted(self.regions), self.size))
        self.soft = soft
        self._problems: dict[tuple[int, ...], BranchProblem] = {}
        self._cache: ChainCache = {}  # chain QPs shared by subsets that agree on a chain
        self._pool = ThreadPoolExecutor(workers) if workers > 1 else None
        self._chains = ThreadPoolExecutor(config.workers) if config.workers > 1 else None
        self.last: Selection | None = None  # the newest select()'s answer

    def problem(self, subset: tuple[int, ...]) -> BranchProblem:
        """The warm solver kept for ``subset`` (built on first use)."""
        if subset not in self._problems:
            self._problems[subset] = BranchProblem(self.model, self.config, len(subset),
                                                   soft=self.soft, cache=self._cache,
                                                   executor=self._chains)
        return self._problems[subset]

    def solve(self, subset: tuple[int, ...], x0: np.ndarray, goal: np.ndarray,
              consensus: int | None = None, region_step: int | None = None) -> Plan:
        """``J(subset, K', s)``, by default at K and the full promise (``T`` less the
        reserve, :func:`~.mpc.promised_step`)."""
        if region_step is None:
            region_step = promised_step(self.config, 0)
        return self.problem(subset).solve(x0, goal, [self.regions[i] for i in subset],
                                          consensus, region_step, stop_early=True)

    def select(self, x0: np.ndarray, goal: np.ndarray) -> Selection:
        """Solve every candidate subset at full K and promise; keep the cheapest feasible."""
        start = time.perf_counter()
        subsets = self.subsets
        if self.screen:
            singles = self._map([(i,) for i in sorted(self.regions)], x0, goal)
            bad = {s[0] for s, plan in singles.items() if not plan.feasible}
            subsets = [s for s in subsets if not bad.intersection(s)]
        plans = self._map(subsets, x0, goal)
        feasible = {s: p for s, p in plans.items() if p.feasible}
        best = min(feasible, key=lambda s: feasible[s].cost, default=())
        self.last = Selection(best, feasible.get(best), plans,
                              (time.perf_counter() - start) * 1e3)
        return self.last

    def _map(self, subsets: list[tuple[int, ...]], x0: np.ndarray, goal: np.ndarray
             ) -> dict[tuple[int, ...], Plan]:
        if self._pool is None:
            return {s: self.solve(s, x0, goal) for s in subsets}
        for s in subsets:
            self.problem(s)  # build serially: setup is not thread-safe to interleave
        futures = {s: self._pool.submit(self.solve, s, x0, goal) for s in subsets}
        return {s: f.result() for s, f in futures.items()}

    def close(self) -> None:
        for pool in (self._pool, self._chains):
            if pool is not None:
                pool.shutdown(wait=True)
