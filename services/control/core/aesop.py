"""Algorithm 1 (AESOP) as a mode machine, and the two baselines of the paper.

Every controller has the same ``make_step`` shape: given the measured state,
whether the fast detector flags this tick, and the slow reasoner's decision
for the pending anomaly (``None`` while it thinks), it returns the input to
apply and what it did. A step never raises: a failed solve makes the
controller follow its last feasible plan, shifted one step, and report the
status.

Modes (``ControlState.mode``; one anomaly's life is an :class:`.episode.Episode`):

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
later (:func:`.deadlines.late`): the nonlinear truth arrives a little after
Theorem 1's ``t_anom + T`` rather than not at all. So is the tree while the
reasoner thinks, from its promise: the robot flies a solved tree rather than the last
one blind.

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
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from shared.messages import Mode

from .deadlines import late, promise, region_step
from .dynamics import N_STATE
from .episode import Episode, commit, decide, detect
from .kept import AHEAD, Flown, Kept
from .mpc import BranchProblem, MPCConfig, Plan, SolveStatus, tightened_inputs
from .planning import PlanningModel
from .regions import Region
from .selection import SubsetSelector

SENT_KEPT = 64  # inputs remembered for delay compensation (3.2 s at 20 Hz)


def _missed(dt: float, age: float, sent: Sequence[tuple[np.ndarray, np.ndarray]]
            ) -> tuple[int, float]:
    """Of a state ``age`` seconds old, how many of the steps ``sent`` it has not seen, and
    how much of the oldest of them it missed (s)."""
    back = min(math.ceil(age / dt - 1e-9), len(sent))
    return back, (min(age - (back - 1) * dt, dt) if back > 0 else 0.0)


def carry_forward(model: PlanningModel, x: np.ndarray, age: float,
                  sent: Sequence[tuple[np.ndarray, np.ndarray]],
                  lag: np.ndarray | None = None) -> np.ndarray:
    """Delay compensation: ``x``, measured ``age`` seconds (model time) before this step,
    carried forward under the inputs ``sent`` since ((input, lag states before it), newest
    last): the step it was measured in for the rest of that step, then each later one (as
    far back as ``sent`` reaches). The lag states at ``x``'s instant are ``lag`` where the
    vehicle reported them, else predicted from the steps sent."""
    back, first_s = _missed(model.dt, age, sent)
    if back <= 0:
        return x
    u_first, lag_first = sent[-back]
    if lag is None:
        lag = (model.advance_by(lag_first, u_first, model.dt - first_s) if model.n_lag
               else lag_first)
    inputs = [u for u, _ in list(sent)[len(sent) - back:]]
    return model.predict(x, lag, inputs, first_s)


def carried_lag(model: PlanningModel, lag: np.ndarray, age: float,
                sent: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """The lag states ``lag``, measured ``age`` seconds before this step, carried to it
    under the inputs ``sent`` since (as :func:`carry_forward` carries the state)."""
    back, first_s = _missed(model.dt, age, sent)
    if back <= 0:
        return np.asarray(lag, dtype=float)
    inputs = [u for u, _ in list(sent)[len(sent) - back:]]
    lag = model.advance_by(lag, inputs[0], first_s)
    for u in inputs[1:]:
        lag = model.advance(lag, u)
    return lag


def measured_lag(model: PlanningModel, realized: np.ndarray | None) -> np.ndarray | None:
    """The model's lag states as the vehicle reports them (the acceleration it realizes, on
    the lagged axes), within the inputs a command may take; None where the model has none or
    the report is missing or not finite (the prediction from the commands sent stands)."""
    if realized is None or not model.n_lag:
        return None
    axes = list(model.lag_inputs)
    lag = np.asarray(realized, dtype=float)[axes]
    if not np.all(np.isfinite(lag)):
        return None
    clipped: np.ndarray = np.clip(lag, np.asarray(model.u_lo)[axes],
                                  np.asarray(model.u_hi)[axes])
    return clipped


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


class Problems:
    """What a :class:`Controller` solves, as its :class:`Policy` says: the tree of the
    cheapest feasible subset (``selector``) or, without one, the nominal branch alone; and
    the recovering problem toward one region, hard and least-violating (built when first
    needed)."""

    def __init__(self, model: PlanningModel, config: MPCConfig, regions: Sequence[Region],
                 policy: Policy, min_size: int = 2, selector: SubsetSelector | None = None
                 ) -> None:
        self.model, self.config, self.policy = model, config, policy
        self.regions = tuple(regions)
        self.selector: SubsetSelector | None = None
        self.nominal: BranchProblem | None = None  # without a tree: the nominal branch
        if policy.keeps_tree:
            tree = config if policy.shares_k else replace(config, consensus=0)
            self.selector = selector or SubsetSelector(model, tree, regions, min_size=min_size)
        else:
            self.nominal = BranchProblem(model, config, 0)
        self._recover: dict[bool, BranchProblem] = {}

    def recovery(self, soft: bool) -> BranchProblem:
        if soft not in self._recover:
            self._recover[soft] = BranchProblem(self.model, self.config, 1, nominal=False,
                                                soft=soft)
        return self._recover[soft]

    def warm_up(self, x: np.ndarray, goal: np.ndarray) -> None:
        """Cold-solve a first tick's problems at the model state ``x``: the nominal ones,
        and the recovering ones (the hard one and the least-violating one it falls back to)
        toward each region, so that the first recovering tick starts warm too."""
        if self.selector is not None:
            self.selector.select(x, goal)
        elif self.nominal is not None:
            self.nominal.solve(x, goal, [])
        for soft in (True,) if self.policy.soft_recovery else (False, True):
            for region in self.regions:
                self.recovery(soft).solve(x, goal, [region], 0, self.config.horizon)


class Controller:
    """Algorithm 1's loop body, one ``make_step`` per tick, as its :class:`Policy` says.

    What a tick changes is three values, each replaced as a whole: the anomaly's life
    (:class:`.episode.Episode`), the plan kept to fly blind (:class:`.kept.Kept`) and the
    nominal flight's hold (``held``, ``region_step``); the rest is the flight's fixed
    configuration, its solvers and the commands sent (delay compensation)."""

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
        self.problems = Problems(model, config, regions, policy, min_size, selector)
        self.selector = self.problems.selector
        self.episode = Episode()
        self.kept = Kept(ahead=np.empty((0, model.m)))
        self.t = 0  # ticks flown (K is counted in them)
        self._active: tuple[int, ...] = ()  # the subset whose recovery plans are kept
        self.held = 0  # ticks since a subset was feasible at full K and T (holding if > 0)
        self.region_step: int | None = None  # the step the last plan reached its regions by
        self.degraded = False  # recovering on the least-violating plan
        self._said: list[str] = []  # events of this step
        self._alarms: list[str] = []  # what went wrong in this step
        self._x = np.zeros(N_STATE)  # the measured plant state of this step
        self._lag = np.zeros(model.n_lag)  # the model's lag states, from the commands sent
        self._thrust_hi = model.linear.u_hover[0] + tightened_inputs(model, config)[1][0]
        self.goal = route.goal  # this step's nominal target (model state)
        self.measured = model.rest_state(np.zeros(3))  # the model state of the last step
        # (input, lag states before it) of the steps sent, newest last: what a state that
        # arrives late has not yet seen (make_step's ``age``)
        self._sent: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=SENT_KEPT)

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
        self.kept = replace(self.kept, ahead=other.kept.ahead.copy())

    @property
    def mode(self) -> Mode:
        return self.episode.mode

    def _follow(self, plan: Plan | None, accept: bool) -> Flown:
        """Fly ``plan`` if usable (and keep it), else the kept plan one step further on."""
        if plan is not None and accept:
            if np.all(np.isfinite(plan.u0)) and np.all(np.isfinite(plan.inputs)):
                self.kept, flown = self.kept.keep(plan, self.measured)
                return flown
            self._alarms.append("non-finite plan from the solver: flying the last plan's "
                                "recovery branch")
        return self._blind()

    def _blind(self) -> Flown:
        self.kept, flown = self.kept.blind(self.model.linear.u_hover)
        return flown

    def skip(self, ticks: int, ahead: int = AHEAD) -> None:
        """``ticks`` ticks passed unstepped (a late loop); the vehicle flew the first ``ahead``
        inputs sent ahead, then held (hover). They count as stepped: K is the vehicle's time."""
        flown = self.kept.ahead[:min(max(ahead, 0), ticks)]
        for i in range(ticks):
            u = flown[i] if i < len(flown) else self.model.linear.u_hover
            self._sent.append((np.array(u, dtype=float), self._lag))
            self._lag = self.model.advance(self._lag, self._sendable(u))
        self.t += ticks
        self.held += ticks * (self.held > 0)
        self.kept = self.kept.skipped(ticks)

    def _select(self, selector: SubsetSelector, x: np.ndarray) -> tuple[Flown, SolveStatus]:
        """One selection tick: keep the cheapest feasible subset active and follow its plan.

        With no subset shown feasible, hold the last one with the consensus and horizon
        shrunk by the ticks since it was (module docstring)."""
        selection = selector.select(x, self.goal)
        if selection.feasible or not self._active:
            if selection.feasible:
                self._active = selection.subset
                if self.held:
                    self._said.append(f"full tree feasible again with regions {self._active}")
                self.held, self.region_step = 0, None
            status = selection.plan.status if selection.plan else selection.status
            return self._follow(selection.plan, selection.feasible), status
        self.held += 1
        if self.held == 1:
            why = ("no subset feasible" if selection.decided else
                   "no subset shown feasible yet (a solve stopped at its cap)")
            self._said.append(f"{why} at full K and T: holding regions {self._active}")
        plan = selector.solve(self._active, x, self.goal,
                              max(0, selector.config.consensus - self.held),
                              promise(self.config, self.held, self.region_step))
        return self._follow(plan, plan.feasible), plan.status

    def _recovering(self, x: np.ndarray) -> tuple[Flown, SolveStatus]:
        """Fly toward the chosen region: ``J({y}, 0, T - k)``.

        If the hard problem is infeasible even with no deadline (the nonlinear
        plant has drifted from the linear plan), fly the least-violating plan
        rather than blind: it is still closed-loop. If it did not decide within
        its budget, fly the last verified plan. The status reported is the hard
        problem's.
        """
        chosen = self.episode.chosen
        if chosen is None:  # RECOVERING is always entered with a region chosen
            raise RuntimeError("recovering with no region chosen")
        region, s = [self.regions[chosen]], self._due()
        if self.policy.soft_recovery:
            plan = self.problems.recovery(True).solve(x, self.goal, region, 0, s)
        else:
            plan, self.region_step, said = late(lambda s: self.problems.recovery(False).solve(
                x, self.goal, region, 0, s), s, self.config, self.region_step, "recovering")
            self._said.extend([said] if said else [])
        status = plan.status
        if not plan.feasible and not self.policy.soft_recovery:
            if not status.decided:  # no verdict within the budget: the last verified plan
                return self._follow(None, False), status
            plan = self.problems.recovery(True).solve(x, self.goal, region, 0, self.config.horizon)
            if not self.degraded:
                self._said.append(f"recovery to region {chosen} infeasible ({status}): "
                                  "flying the least-violating plan")
        self.degraded = not status.feasible
        return self._follow(plan, plan.status in (SolveStatus.SOLVED, SolveStatus.INACCURATE)), \
            status

    def _due(self) -> int:
        """The step this tick's plan must reach its region by (:func:`.deadlines.region_step`)."""
        return region_step(self.config, self.episode.k(self.t), self.region_step)

    def warm_up(self, x: np.ndarray) -> None:
        """Build and cold-solve the problems of a first tick at the 12-state ``x``, off the
        loop.

        The first solve of a problem has no warm start (up to ``max_iter_cold``
        iterations, a few hundred ms); after this the first tick at ``x`` is
        answered by each chain's memo and later ones start warm; the recovering problems
        (the hard one and the least-violating one it falls back to) are cold-solved toward
        each region. The flight has not begun: nothing else changes (the route moves on
        only if ``x`` is already at its waypoint, as the first tick would).
        """
        xm = self.model.measure(x, self._lag)
        self.problems.warm_up(xm, self.route.target(xm, self.model))

    def make_step(self, x: np.ndarray | None, anomaly: bool, decision: int | None = None,
                  age: float = 0.0, realized: np.ndarray | None = None) -> ControlOutput:
        """One tick: the vehicle's 12-state ``x`` measured ``age`` seconds ago (model time),
        ``anomaly`` from the detector, the reasoner's ``decision`` for the pending anomaly
        (``None`` while it thinks). ``x`` is carried forward to now with the planning model
        and the inputs sent since (delay compensation). ``realized``: the acceleration the
        vehicle reported with ``x`` (world frame), the model's lag states measured rather
        than predicted (:func:`measured_lag`). ``x`` None: no usable state (the caller
        raised the alarm); the step flies blind as for a non-finite one, silently."""
        if x is None:
            return self._measurement_lost(decision, anomaly, alarm=False)
        self._x = np.asarray(x, dtype=float)
        if not np.all(np.isfinite(self._x)):
            return self._measurement_lost(decision, anomaly)
        lag = measured_lag(self.model, realized)
        if lag is not None:
            self._lag = carried_lag(self.model, lag, age, self._sent)
        if age > 0.0:
            self._x = carry_forward(self.model, self._x, age, self._sent, lag)
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
        self._decide(decision, None)
        if alarm:
            self._alarms.append("non-finite state measured: flying the last plan's recovery "
                                "branch")
        request = None
        if anomaly:
            request = self._detect(self._active or tuple(sorted(self.regions)), self.held,
                                   blind=True)
        return self._output(self._blind(), SolveStatus.FAILED,
                            self.episode.active(self._active), request)

    def _step(self, x: np.ndarray, anomaly: bool, decision: int | None) -> ControlOutput:
        ep, policy = self._decide(decision, x), self.policy
        if ep.mode is Mode.RECOVERING:
            flown, status = self._recovering(x)
            return self._output(flown, status, ep.active(()))
        if ep.mode is Mode.PENDING and policy.waits_on_tree:
            assert self.selector is not None
            k, solve, what = ep.k(self.t), self.selector.solve, "while the reasoner thinks"
            plan, self.region_step, said = late(lambda s: solve(
                ep.options, x, self.goal, self.config.consensus - k, s),
                promise(self.config, k, self.region_step), self.config, self.region_step, what)
            self._said.extend([said] if said else [])
            return self._output(self._follow(plan, plan.feasible), plan.status, ep.options)
        if self.selector is not None:
            flown, status = self._select(self.selector, x)
            active = self._active
        else:
            assert self.problems.nominal is not None
            nominal = self.problems.nominal.solve(x, self.goal, [])
            flown, status, active = self._follow(nominal, nominal.feasible), nominal.status, ()
        request = None
        if anomaly:
            # AESOP asks among the subset its tree keeps (none kept: it cannot offer any);
            # a baseline among every region when it keeps none; a hold's ticks come off
            # AESOP's consensus budget
            waits = policy.waits_on_tree
            request = self._detect(active if waits else (active or tuple(sorted(self.regions))),
                                   self.held if waits else ep.spent)
        return self._output(flown, status, active, request)

    def _detect(self, options: tuple[int, ...], spent: int, blind: bool = False
                ) -> tuple[int, ...] | None:
        """An anomaly this tick: the options asked, or None when none is asked."""
        before = self.episode
        self.episode, said = detect(before, self.t, options, spent, blind)
        self._said.extend([said] if said else [])
        return self.episode.options if self.episode is not before else None

    def _decide(self, decision: int | None, x: np.ndarray | None) -> Episode:
        """Take the reasoner's decision; pending with the budget spent (and the policy
        commits at K), commit the fallback chosen from ``x``. The episode after both."""
        self.episode, said = decide(self.episode, decision)
        if said is not None and self.episode.mode is Mode.NOMINAL:
            self.region_step = None  # "continue": the hold's deadline no longer stands
        self._said.extend([said] if said else [])
        if self.policy.commits_at_k and self.episode.due(self.t, self.config.consensus):
            self.episode, said = commit(self.episode, self._fallback_region(x))
            self._said.append(said)
        return self.episode

    def _fallback_region(self, x: np.ndarray | None) -> int:
        """The configured fallback region, or the cheapest feasible recovery from ``x`` (the
        first offered when ``x`` is unknown or none is)."""
        options = self.episode.options
        if isinstance(self.fallback, int):
            return self.fallback
        if self.fallback == "first" or x is None:
            return options[0]
        costs = {}
        for y in options:
            plan = self.problems.recovery(False).solve(x, self.goal, [self.regions[y]], 0,
                                                       self._due())
            if plan.feasible:
                costs[y] = plan.cost
        return min(costs, key=costs.__getitem__) if costs else options[0]

    def _sendable(self, u: np.ndarray) -> np.ndarray:
        return sendable(self.model, self._x, np.asarray(u, dtype=float), self._thrust_hi)

    def _output(self, flown: Flown, status: SolveStatus, active: tuple[int, ...],
                request: tuple[int, ...] | None = None) -> ControlOutput:
        alarms, self._alarms = tuple(self._alarms), []
        planned = np.asarray(flown.u, dtype=float)
        u = self._sendable(planned)
        if alarms or not np.all(np.isfinite(u)):
            status = SolveStatus.FAILED
        if not np.all(np.isfinite(u)):
            flown = self._blind()
            if not np.all(np.isfinite(flown.u)):
                self.kept = self.kept.forget()
                flown = replace(flown, u=self.model.linear.u_hover.copy())
            alarms += ("non-finite input from the solver: flying the last plan's recovery "
                       "branch",)
            planned = u = np.asarray(flown.u, dtype=float)
        self.kept = self.kept.finite_ahead()
        if self.model.n_lag:  # acceleration commands, sent as planned: each within reach
            self.kept, u = self.kept.within_reach(self.model, self._lag, planned, self.config)
            planned = u
        ahead = self._sendable(self.kept.ahead)  # every row at once: this runs each tick
        self._sent.append((planned.copy(), self._lag))
        self._lag = self.model.advance(self._lag, u)
        ep, events, self._said = self.episode, tuple(self._said), []
        out = ControlOutput(u=u, mode=ep.mode, status=status, plan=flown.plan,
                            active_regions=active, t_anom=ep.t_anom, chosen=ep.chosen,
                            request=request, events=events, fallback=ep.fallback,
                            consensus_left=ep.left(self.t, self.config.consensus),
                            alarms=alarms, reference=flown.reference, blind=flown.blind,
                            ahead=ahead)
        self.t += 1
        return out
