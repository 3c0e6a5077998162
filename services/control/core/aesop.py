"""Algorithm 1 (AESOP) as a mode machine, and the two baselines of the paper.

Every controller has the same ``make_step`` shape: given the measured state,
whether the fast detector flags this tick, and the slow reasoner's decision
for the pending anomaly (``None`` while it thinks), it returns the input to
apply and what it did. A step never raises: a failed solve makes the
controller follow its last feasible plan, shifted one step, and report the
status.

Modes (``ControlState.mode``):

* ``nominal``: solve ``J_t(Y_t, K, T)`` with the cheapest feasible subset
  ``Y_t``; on an anomaly remember ``t_anom`` and ``Y_tanom`` and ask the
  reasoner to choose among ``Y_tanom``;
* ``anomaly_pending``: at ``k = t - t_anom`` solve ``J_t(Y_tanom, K - k, T - k)``
  (shrinking consensus and horizon). If no decision has come when ``k = K``,
  commit to the programmatic fallback (beyond the paper: default, the cheapest
  feasible recovery in ``Y_tanom``) and say so;
* ``recovering``: solve ``J_t({y}, 0, T - k)`` and follow the recovery branch.

The horizon to the region never shrinks below ``MPCConfig.min_region_step``
so that the nonlinear plant's small model errors never pin a region to the
very next step (documented deviation from ``max(0, T - k)``). While
recovering, a region out of reach by that step is planned to be reached
later (``Controller._late``): the nonlinear truth arrives a little after
Theorem 1's ``t_anom + T`` rather than not at all.

Holding (beyond the paper). In nominal operation nothing guarantees that
some subset is feasible at the *full* ``K`` and ``T`` on the next tick: the
previous tree, shifted, shares only ``K - 1`` recovery inputs. When no
subset is, the controller keeps the last feasible subset ``Y`` and solves
``J_t(Y, K - h, T - h)`` for the ``h`` ticks since it was feasible, which
Theorem 1 keeps feasible: the robot flies the shared recovery prefix and
slows down until a full tree is feasible again. An anomaly during a hold
has ``K - h`` ticks left, not ``K``: the consensus budget is already spent.
A subset whose solve stopped at its iteration cap or time limit has not been
shown infeasible (``SolveStatus.decided``): it is not used, but nothing is
discarded for it either; the hold continues and the next tick resumes the
solve from where it stopped.

The measured state is the plant's 12-state ``x``; the controller plans in
its model's coordinates (:mod:`.planning`). A non-finite measurement never
reaches a solver and a non-finite input never leaves a step: the step flies
the last feasible plan's recovery branch (or hovers) and says so.

The three methods are one :class:`Controller` configured by a :class:`Policy`
(:data:`AESOP`, :data:`FSMPC`, :data:`NAIVE`): what each keeps while flying nominally,
what it flies while the reasoner thinks, and whether it commits a fallback at K.

The nominal task is a :class:`Route`: the approach waypoint above the goal,
then the goal (the paper's hardware: "toward a waypoint a foot above the
landing zone. Upon reaching the waypoint, it descends and lands.").
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from shared.messages import Mode

from .dynamics import N_STATE
from .mpc import BranchProblem, MPCConfig, Plan, SolveStatus, promised_step, tightened_inputs
from .planning import PlanningModel
from .regions import Region
from .selection import SubsetSelector

SENT_KEPT = 64  # inputs remembered for delay compensation (3.2 s at 20 Hz)
AHEAD = 16  # the plan's next inputs an output carries (the set-point sends some of them)


def carry_forward(model: PlanningModel, x: np.ndarray, age: float,
                  sent: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Delay compensation: ``x``, measured ``age`` seconds (model time) before this step,
    carried forward under the inputs ``sent`` since ((input, lag states before it), newest
    last): the step it was measured in for the rest of that step, then each later one (as
    far back as ``sent`` reaches)."""
    dt = model.dt
    back = min(math.ceil(age / dt - 1e-9), len(sent))
    if back <= 0:
        return x
    first_s = min(age - (back - 1) * dt, dt)  # of the oldest step, what the state missed
    u_first, lag_first = sent[-back]
    lag = model.advance_by(lag_first, u_first, dt - first_s) if model.n_lag else lag_first
    inputs = [u for u, _ in list(sent)[len(sent) - back:]]
    return model.predict(x, lag, inputs, first_s)


def sendable(model: PlanningModel, x: np.ndarray, u: np.ndarray, thrust_hi: float
             ) -> np.ndarray:
    """What the plant is sent for the planned input ``u`` (or rows of inputs) at the
    12-state ``x`` (as is when ``x`` is not finite). For the hover model, the collective
    thrust scaled by ``1 / (cos phi cos theta)``: the model assumes all thrust is vertical,
    and a tilted vehicle loses that fraction of it and sinks below the plan (saturated at
    ``thrust_hi``, the thrust box the MPC plans in). An acceleration command goes as is."""
    if model.name != "quadrotor" or not np.all(np.isfinite(x)):
        return u
    u = u.copy()
    u[..., 0] = np.minimum(u[..., 0] / max(np.cos(x[6]) * np.cos(x[7]), 0.5), thrust_hi)
    return u


@dataclass(frozen=True)
class Policy:
    """How a method flies: Algorithm 1 and the paper's two baselines differ only here."""

    name: str
    keeps_tree: bool  # nominal flight keeps recovery plans for a subset of the regions
    shares_k: bool  # and their first K inputs are shared (eq. 3); else K = 0 (FS-MPC)
    waits_on_tree: bool  # while the reasoner thinks, fly J(Y, K - k, T - k); else fly on
    commits_at_k: bool  # no decision by K: commit to the fallback region
    soft_recovery: bool  # accept a least-violating recovery plan


AESOP = Policy("aesop", keeps_tree=True, shares_k=True, waits_on_tree=True, commits_at_k=True,
               soft_recovery=False)
FSMPC = Policy("fsmpc", keeps_tree=True, shares_k=False, waits_on_tree=False,
               commits_at_k=False, soft_recovery=True)  # recovery plans kept, flies on
NAIVE = Policy("naive", keeps_tree=False, shares_k=False, waits_on_tree=False,
               commits_at_k=False, soft_recovery=True)  # plans a recovery once told
POLICIES = {p.name: p for p in (NAIVE, FSMPC, AESOP)}


class Route:
    """The nominal task's targets in order (model rest states); the next one takes over
    once the robot is within ``reach`` (m) of the current one and slower than
    ``settle`` (m/s). The last one is the goal."""

    def __init__(self, stops: Sequence[np.ndarray], reach: float = 0.1,
                 settle: float = 0.2) -> None:
        if not stops:
            raise ValueError("a route needs at least one stop")
        self.stops = tuple(np.asarray(s, dtype=float) for s in stops)
        self.reach, self.settle = reach, settle
        self.index = 0

    @property
    def goal(self) -> np.ndarray:
        return self.stops[-1]

    def target(self, x: np.ndarray, model: PlanningModel) -> np.ndarray:
        """The current target for the model state ``x`` (advances the route)."""
        pos, vel = list(model.position), list(model.velocity)
        while self.index < len(self.stops) - 1:
            here = self.stops[self.index]
            if (np.linalg.norm(x[pos] - here[pos]) > self.reach
                    or np.linalg.norm(x[vel]) > self.settle):
                break
            self.index += 1
        return self.stops[self.index]


@dataclass(frozen=True)
class ControlOutput:
    u: np.ndarray  # absolute input to apply, in the model's input units
    mode: Mode
    status: SolveStatus
    plan: Plan | None  # None when the step fell back to the last plan
    active_regions: tuple[int, ...]
    t_anom: int | None  # tick of the pending/handled anomaly
    chosen: int | None  # region being recovered to
    request: tuple[int, ...] | None = None  # options for the reasoner, on the detection tick
    events: tuple[str, ...] = ()
    fallback: bool = False  # the recovery was committed without a decision
    consensus_left: int | None = None  # ticks until the fallback at K, while one is pending
    alarms: tuple[str, ...] = ()  # what went wrong in this step (non-finite state or input)
    # the model state the plan expects at this instant (the set-point's position and
    # velocity); None when the step hovers without a plan
    reference: np.ndarray | None = None
    # flying blind on the kept branch: its steps left after this one (0: spent, its last
    # input repeated); None when the input comes from this step's own plan
    blind: int | None = None
    # the plan's next inputs after ``u``, one per tick, as ``u`` is sent (``(j, m)``; empty
    # without a plan): what the vehicle flies through ticks the loop misses
    ahead: np.ndarray = field(default_factory=lambda: np.empty((0, 0)))


@dataclass
class _Memory:
    mode: Mode = Mode.NOMINAL
    t: int = 0
    t_anom: int | None = None
    options: tuple[int, ...] = ()
    chosen: int | None = None
    fallback: bool = False
    inputs: np.ndarray | None = None  # last feasible plan's inputs (T, m)
    states: np.ndarray | None = None  # and its states (T+1, n), the branch those inputs fly
    age: int = 0  # ticks since that plan
    held: int = 0  # ticks since a subset was feasible at full K and T (holding if > 0)
    degraded: bool = False  # recovering on the least-violating plan
    spent: int = 0  # consensus ticks already used by a hold when the anomaly came
    region_step: int | None = None  # the step the last plan reached its regions by (s)
    events: list[str] = field(default_factory=list)


class Controller:
    """Algorithm 1's loop body, one ``make_step`` per tick, as its :class:`Policy` says."""

    def __init__(self, model: PlanningModel, config: MPCConfig, regions: Sequence[Region],
                 route: Route, policy: Policy = AESOP, fallback: str | int = "cheapest",
                 min_size: int = 2, selector: SubsetSelector | None = None) -> None:
        self.model, self.config, self.route, self.policy = model, config, route, policy
        self.name = policy.name
        self.regions = {r.index: r for r in regions}
        if not (fallback in ("cheapest", "first") or (isinstance(fallback, int)
                                                      and fallback in self.regions)):
            raise ValueError("fallback must be 'cheapest', 'first' or a region index")
        self.fallback = fallback
        self.selector: SubsetSelector | None = None
        self._nominal: BranchProblem | None = None  # without a tree: the nominal branch
        if policy.keeps_tree:
            tree = config if policy.shares_k else replace(config, consensus=0)
            self.selector = selector or SubsetSelector(model, tree, regions, min_size=min_size)
        else:
            self._nominal = BranchProblem(model, config, 0)
        self._recover: dict[bool, BranchProblem] = {}  # the recovering problem, hard/soft
        self._active: tuple[int, ...] = ()  # the subset whose recovery plans are kept
        self.memory = _Memory()
        self._x = np.zeros(N_STATE)  # the measured plant state of this step
        self._lag = np.zeros(model.n_lag)  # the model's lag states, from the commands sent
        self._thrust_hi = model.linear.u_hover[0] + tightened_inputs(model, config)[1][0]
        self.goal = route.goal  # this step's nominal target (model state)
        self.measured = model.rest_state(np.zeros(3))  # the model state of the last step
        self._alarms: list[str] = []  # what went wrong in this step
        # (input, lag states before it) of the steps sent, newest last: what a state that
        # arrives late has not yet seen (make_step's ``age``)
        self._sent: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=SENT_KEPT)
        self._reference: np.ndarray | None = None  # this step's, for ControlOutput
        self._blind_left: int | None = None
        # the plan's inputs after this step's (model units), flown through missed ticks
        self._ahead = np.empty((0, model.m))

    @property
    def state(self) -> np.ndarray:
        """The 12-state the last step planned from (carried forward to its time)."""
        return self._x.copy()

    @property
    def lag(self) -> np.ndarray:
        """The model's lag states: what the vehicle has yet to realize of the commands sent."""
        return self._lag

    def carry_on(self, other: Controller) -> None:
        """Take over the flight ``other`` was flying (same route, new regions): where it is
        on the route and the lag states of the commands it sent."""
        self.route.index = other.route.index
        self._lag = other.lag.copy()
        self._sent = deque(other._sent, maxlen=SENT_KEPT)
        self._ahead = other._ahead.copy()

    @property
    def mode(self) -> Mode:
        return self.memory.mode

    def _region_step(self, k: int) -> int:
        """Algorithm 1's ``s = T - k``, at least ``min_region_step``, and never earlier than
        one step before the last plan's (a deadline pushed back stays pushed back)."""
        s = max(self.config.min_region_step, self.config.horizon - k)
        last = self.memory.region_step
        return s if last is None else min(max(s, last - 1), self.config.horizon)

    def _promise(self, k: int) -> int:
        """While the reasoner thinks (or a hold lasts), ``k`` ticks into the consensus
        budget: the tree's relaxing promise (:func:`.mpc.promised_step`), never later than
        :meth:`_region_step`."""
        return min(max(self.config.min_region_step, promised_step(self.config, k)),
                   self._region_step(k))

    def _late(self, solve: Callable[[int], Plan], s: int, what: str) -> Plan:
        """``solve(s)``; if infeasible, ``solve`` again with the region due later.

        On the nonlinear plant the measured state drifts from the linear
        plan, and a region due in ``s`` steps can be out of reach while it is
        still reachable a little later (killing a small residual velocity
        takes the attitude chain about 1 s). Feasibility only grows with
        ``s``, so this pushes the deadline back in ``late_region_steps``
        increments up to ``T``, and last drops it (``s = T + 1``: the plan
        only heads for the region) so that the state and input limits stay
        hard for as long as they can be met. Reported once (beyond the paper).
        """
        mem, cfg = self.memory, self.config
        plan = solve(s)
        first = s
        while not plan.feasible and s <= cfg.horizon:
            if not plan.status.decided or s == cfg.horizon:
                s = cfg.horizon + 1  # a rung that did not decide: straight to the last one
            else:
                s = min(cfg.horizon, s + cfg.late_region_steps)
            plan = solve(s)
        if plan.feasible:
            if s > first and (mem.region_step is None or s > mem.region_step):
                due = "with no deadline" if s > cfg.horizon else f"by step {s}"
                mem.events.append(f"{what}: region out of reach by step {first}; "
                                  f"heading for it {due}")
            mem.region_step = s
        return plan

    def _recovery_problem(self, soft: bool) -> BranchProblem:
        if soft not in self._recover:
            self._recover[soft] = BranchProblem(self.model, self.config, 1, nominal=False,
                                                soft=soft)
        return self._recover[soft]

    def _follow(self, plan: Plan | None, accept: bool) -> tuple[np.ndarray, Plan | None]:
        """Apply ``plan`` if usable, else the last plan shifted by one more step.

        What is kept for later is a recovery branch when the plan has one:
        its first inputs are the shared prefix that keeps every region of
        the subset reachable, the safest thing to fly blind.
        """
        mem = self.memory
        if plan is not None and accept:
            if np.all(np.isfinite(plan.u0)) and np.all(np.isfinite(plan.inputs)):
                mem.inputs = next(iter(plan.recovery_inputs.values()), plan.inputs)
                mem.states = next(iter(plan.recovery.values()), plan.nominal)
                mem.age = 0
                self._reference, self._blind_left = self.measured, None
                self._ahead = plan.inputs[1:1 + AHEAD]
                return plan.u0, plan
            self._alarms.append("non-finite plan from the solver: flying the last plan's "
                                "recovery branch")
        return self._blind(), None

    def _blind(self) -> np.ndarray:
        """The last kept plan's next input (it ends at rest in its region), or hover."""
        mem = self.memory
        if mem.inputs is None:
            self._reference, self._blind_left = None, 0
            self._ahead = self._ahead[:0]
            return self.model.linear.u_hover.copy()
        mem.age += 1
        step = min(mem.age, len(mem.inputs) - 1)
        self._blind_left = len(mem.inputs) - 1 - step
        self._reference = None if mem.states is None else mem.states[step]
        self._ahead = mem.inputs[step + 1:step + 1 + AHEAD]
        return mem.inputs[step].copy()

    def skip(self, ticks: int, ahead: int = AHEAD) -> None:
        """``ticks`` ticks passed unstepped (a late loop); the vehicle flew the first ``ahead``
        inputs sent ahead, then held (hover). They count as stepped: K is the vehicle's time."""
        mem = self.memory
        flown = self._ahead[:min(max(ahead, 0), ticks)]
        for i in range(ticks):
            u = flown[i] if i < len(flown) else self.model.linear.u_hover
            self._sent.append((np.array(u, dtype=float), self._lag))
            self._lag = self.model.advance(self._lag, self._sendable(u))
            mem.t += 1
            mem.age += mem.inputs is not None
            mem.held += mem.held > 0
        self._ahead = self._ahead[ticks:]

    def _select(self, selector: SubsetSelector, x: np.ndarray
                ) -> tuple[np.ndarray, Plan | None, SolveStatus]:
        """One selection tick: keep the cheapest feasible subset active and follow its plan.

        With no subset shown feasible, hold the last one with the consensus
        and horizon shrunk by the ticks since it was (module docstring).
        """
        mem = self.memory
        selection = selector.select(x, self.goal)
        if selection.feasible or not self._active:
            if selection.feasible:
                self._active = selection.subset
                if mem.held:
                    mem.events.append(f"full tree feasible again with regions {self._active}")
                mem.held, mem.region_step = 0, None
            status = selection.plan.status if selection.plan else selection.status
            u, used = self._follow(selection.plan, selection.feasible)
            return u, used, status
        mem.held += 1
        if mem.held == 1:
            why = ("no subset feasible" if selection.decided else
                   "no subset shown feasible yet (a solve stopped at its cap)")
            mem.events.append(f"{why} at full K and T: holding regions {self._active}")
        plan = selector.solve(self._active, x, self.goal,
                              max(0, selector.config.consensus - mem.held),
                              self._promise(mem.held))
        u, used = self._follow(plan, plan.feasible)
        return u, used, plan.status

    def _recovering(self, x: np.ndarray) -> tuple[np.ndarray, Plan | None, SolveStatus]:
        """Fly toward the chosen region: ``J({y}, 0, T - k)``.

        If the hard problem is infeasible even with no deadline (the nonlinear
        plant has drifted from the linear plan), fly the least-violating plan
        rather than blind: it is still closed-loop. If it did not decide within
        its budget, fly the last verified plan. The status reported is the hard
        problem's.
        """
        mem = self.memory
        k = mem.t - (mem.t_anom or 0) + mem.spent
        if mem.chosen is None:  # RECOVERING is always entered with a region chosen
            raise RuntimeError("recovering with no region chosen")
        region = [self.regions[mem.chosen]]
        if self.policy.soft_recovery:
            plan = self._recovery_problem(True).solve(x, self.goal, region, 0,
                                                      self._region_step(k))
        else:
            plan = self._late(lambda s: self._recovery_problem(False).solve(
                x, self.goal, region, 0, s), self._region_step(k), "recovering")
        status = plan.status
        if not plan.feasible and not self.policy.soft_recovery:
            if not status.decided:  # no verdict within the budget: the last verified plan
                u, used = self._follow(None, False)
                return u, used, status
            plan = self._recovery_problem(True).solve(x, self.goal, region, 0, self.config.horizon)
            if not mem.degraded:
                mem.events.append(f"recovery to region {mem.chosen} infeasible ({status}): "
                                  "flying the least-violating plan")
        mem.degraded = not status.feasible
        u, used = self._follow(plan, plan.status in (SolveStatus.SOLVED, SolveStatus.INACCURATE))
        return u, used, status

    def warm_up(self, x: np.ndarray) -> None:
        """Build and cold-solve the problems of a first tick at the 12-state ``x``, off the
        loop.

        The first solve of a problem has no warm start (up to ``max_iter_cold``
        iterations, a few hundred ms); after this the first tick at ``x`` is
        answered by each chain's memo and later ones start warm. The flight has
        not begun: nothing else changes (the route moves on only if ``x`` is already at
        its waypoint, as the first tick would).
        """
        xm = self.model.measure(x, self._lag)
        goal = self.route.target(xm, self.model)
        if self.selector is not None:
            self.selector.select(xm, goal)
        elif self._nominal is not None:
            self._nominal.solve(xm, goal, [])
        self._warm_recovery(xm, goal)

    def _warm_recovery(self, x: np.ndarray, goal: np.ndarray) -> None:
        """Cold-solve the recovering problems (the hard one, and the least-violating one it
        falls back to) toward each region from ``x``, so that the first recovering tick
        starts warm: a cold solve at 200 steps is a few hundred ms."""
        kinds = (True,) if self.policy.soft_recovery else (False, True)
        for soft in kinds:
            for region in self.regions.values():
                self._recovery_problem(soft).solve(x, goal, [region], 0, self.config.horizon)

    def make_step(self, x: np.ndarray | None, anomaly: bool, decision: int | None = None,
                  age: float = 0.0) -> ControlOutput:
        """One tick: the vehicle's 12-state ``x`` measured ``age`` seconds ago (model time),
        ``anomaly`` from the detector, the reasoner's ``decision`` for the pending anomaly
        (``None`` while it thinks). ``x`` is carried forward to now with the planning model
        and the inputs sent since (delay compensation). ``x`` None: no usable state (the
        caller raised the alarm); the step flies blind as for a non-finite one, silently."""
        if x is None:
            return self._measurement_lost(decision, anomaly, alarm=False)
        self._x = np.asarray(x, dtype=float)
        if not np.all(np.isfinite(self._x)):
            return self._measurement_lost(decision, anomaly)
        if age > 0.0:
            self._x = carry_forward(self.model, self._x, age, self._sent)
        xm = self.model.measure(self._x, self._lag)
        self.measured = xm
        self.goal = self.route.target(xm, self.model)
        return self._step(xm, anomaly, decision)

    def _measurement_lost(self, decision: int | None, anomaly: bool = False, *,
                          alarm: bool = True) -> ControlOutput:
        """No usable state: no solver sees one. Fly the kept recovery branch (or hover),
        take the decision, and on an anomaly in nominal flight ask the reasoner among the
        regions the kept tree holds (as a solved step would); a non-finite state raises an
        alarm (``alarm``). The next usable state resumes the loop."""
        self._take_decision(decision)
        mem = self.memory
        if self.policy.commits_at_k and mem.mode is Mode.PENDING \
                and self._k() >= self.config.consensus:
            self._commit_fallback(None)
        if alarm:
            self._alarms.append("non-finite state measured: flying the last plan's recovery "
                                "branch")
        request = None
        if anomaly and mem.mode is Mode.NOMINAL:
            options = self._active or tuple(sorted(self.regions))
            mem.mode, mem.t_anom, mem.options = Mode.PENDING, mem.t, options
            mem.chosen, mem.fallback, mem.spent = None, False, mem.held
            mem.events.append(f"anomaly while flying blind: asking the reasoner among regions "
                              f"{options}")
            request = options
        active = {Mode.RECOVERING: (mem.chosen,), Mode.PENDING: mem.options}.get(
            mem.mode, self._active)
        return self._output(self._blind(), SolveStatus.FAILED, None, active, request)

    def _k(self) -> int:
        """Ticks of the consensus budget used since the anomaly (a hold's included)."""
        mem = self.memory
        return 0 if mem.t_anom is None else mem.t - mem.t_anom + mem.spent

    def _step(self, x: np.ndarray, anomaly: bool, decision: int | None) -> ControlOutput:
        mem, policy = self.memory, self.policy
        self._take_decision(decision)
        if policy.commits_at_k and mem.mode is Mode.PENDING \
                and self._k() >= self.config.consensus:
            self._commit_fallback(x)
        if mem.mode is Mode.RECOVERING:
            u, plan, status = self._recovering(x)
            return self._output(u, status, plan, (mem.chosen,))
        if mem.mode is Mode.PENDING and policy.waits_on_tree:
            assert self.selector is not None
            k = self._k()
            plan = self.selector.solve(mem.options, x, self.goal, self.config.consensus - k,
                                       self._promise(k))
            u, used = self._follow(plan, plan.feasible)
            return self._output(u, plan.status, used, mem.options)
        if self.selector is not None:
            u, used, status = self._select(self.selector, x)
            active = self._active
        else:
            assert self._nominal is not None
            nominal = self._nominal.solve(x, self.goal, [])
            (u, used), status, active = self._follow(nominal, nominal.feasible), \
                nominal.status, ()
        request = None
        # AESOP asks among the subset its tree keeps (none kept: it cannot offer any);
        # a baseline among every region when it keeps none
        options = active if policy.waits_on_tree else (active or tuple(sorted(self.regions)))
        if anomaly and mem.mode is Mode.NOMINAL and options:
            mem.mode, mem.t_anom, mem.options = Mode.PENDING, mem.t, options
            mem.chosen, mem.fallback = None, False
            if policy.waits_on_tree:
                mem.spent = mem.held  # a hold's ticks come off the consensus budget
            mem.events.append(f"anomaly: asking the reasoner among regions {options}")
            request = options
        return self._output(u, status, used, active, request)

    def _commit_fallback(self, x: np.ndarray | None) -> None:
        """Commit to the fallback region: the configured one, or the cheapest feasible
        recovery from ``x`` (the first offered when ``x`` is unknown or none is)."""
        mem = self.memory
        choice = self.fallback if isinstance(self.fallback, int) else mem.options[0]
        if self.fallback == "cheapest" and x is not None:
            k = self._k()
            costs = {}
            for y in mem.options:
                plan = self._recovery_problem(False).solve(x, self.goal, [self.regions[y]], 0,
                                                           self._region_step(k))
                if plan.feasible:
                    costs[y] = plan.cost
            choice = min(costs, key=costs.__getitem__) if costs else mem.options[0]
        mem.mode, mem.chosen, mem.fallback = Mode.RECOVERING, choice, True
        mem.events.append(f"no decision by K: fallback to region {choice}")

    def _sendable(self, u: np.ndarray) -> np.ndarray:
        return sendable(self.model, self._x, np.asarray(u, dtype=float), self._thrust_hi)

    def _output(self, u, status, plan, active, request=None) -> ControlOutput:
        mem = self.memory
        alarms, self._alarms = tuple(self._alarms), []
        if alarms:
            status = SolveStatus.FAILED
        u = np.asarray(u, dtype=float)
        planned = u
        u = self._sendable(u)
        if not np.all(np.isfinite(u)):
            u, plan, status = self._blind(), None, SolveStatus.FAILED
            if not np.all(np.isfinite(u)):
                mem.inputs, u = None, self.model.linear.u_hover.copy()
                self._ahead = self._ahead[:0]
            alarms += ("non-finite input from the solver: flying the last plan's recovery "
                       "branch",)
            planned = u
        if not np.all(np.isfinite(self._ahead)):
            self._ahead = self._ahead[:0]
        ahead = self._sendable(self._ahead)  # every row at once: this runs each tick
        self._sent.append((np.asarray(planned, dtype=float).copy(), self._lag))
        self._lag = self.model.advance(self._lag, u)
        left = self.config.consensus - self._k() if mem.mode is Mode.PENDING else None
        out = ControlOutput(u=u, mode=mem.mode, status=status, plan=plan, active_regions=active,
                            t_anom=mem.t_anom, chosen=mem.chosen, request=request,
                            events=tuple(mem.events), fallback=mem.fallback,
                            consensus_left=left, alarms=alarms, reference=self._reference,
                            blind=self._blind_left, ahead=ahead)
        self._reference, self._blind_left = None, None
        mem.events.clear()
        mem.t += 1
        return out

    def _take_decision(self, decision: int | None) -> None:
        """Apply the reasoner's decision to a pending anomaly."""
        mem = self.memory
        if decision is None or mem.mode is not Mode.PENDING:
            if decision is not None and mem.mode is Mode.RECOVERING:
                mem.events.append(f"late decision {decision} ignored: already recovering")
            return
        if decision == 0:
            mem.events.append("continue (y = 0): back to nominal")
            mem.mode, mem.t_anom, mem.options = Mode.NOMINAL, None, ()
            mem.region_step = None
        elif decision in mem.options:
            mem.mode, mem.chosen = Mode.RECOVERING, decision
            mem.events.append(f"reasoner chose region {decision}; recovering")
        else:
            mem.events.append(f"decision {decision} was not offered {mem.options}; ignored")
