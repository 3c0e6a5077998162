"""One anomaly's life (services/control/core/episode.py), one row per transition, and the two
other values a tick replaces: the plan kept to fly blind (kept.py) and the regions'
deadline (deadlines.py)."""

import math
from dataclasses import replace

import numpy as np
import pytest

from services.control.core.deadlines import late, promise, region_step
from services.control.core.episode import Episode, commit, decide, detect
from services.control.core.kept import AHEAD, Kept
from services.control.core.mpc import MPCConfig, SolveStatus
from shared.messages import Mode

NOMINAL = Episode()
PENDING = Episode(Mode.PENDING, t_anom=10, options=(1, 2), spent=3)
RECOVERING = replace(PENDING, mode=Mode.RECOVERING, chosen=2)
FALLEN_BACK = replace(RECOVERING, chosen=1, fallback=True)

# (name, episode before, transition, expected after, what a person reads)
ROWS = [
    ("nominal, flagged: ask among the options",
     NOMINAL, lambda e: detect(e, 10, (1, 2), 3),
     PENDING, "anomaly: asking the reasoner among regions (1, 2)"),
    ("nominal, flagged while blind: said so",
     NOMINAL, lambda e: detect(e, 10, (1, 2), 3, blind=True),
     PENDING, "anomaly while flying blind: asking the reasoner among regions (1, 2)"),
    ("nominal, flagged with nothing to offer: nothing asked",
     NOMINAL, lambda e: detect(e, 10, (), 0), NOMINAL, None),
    ("pending, flagged again: one anomaly at a time",
     PENDING, lambda e: detect(e, 12, (3,), 0), PENDING, None),
    ("recovering, flagged again: nothing changes",
     RECOVERING, lambda e: detect(e, 12, (3,), 0), RECOVERING, None),
    ("pending, no answer yet", PENDING, lambda e: decide(e, None), PENDING, None),
    ("pending, continue: nominal again (a hold's spent ticks stay)",
     PENDING, lambda e: decide(e, 0), Episode(spent=3), "continue (y = 0): back to nominal"),
    ("pending, an offered region: recovering to it",
     PENDING, lambda e: decide(e, 2), RECOVERING, "reasoner chose region 2; recovering"),
    ("pending, a region not offered: ignored",
     PENDING, lambda e: decide(e, 7), PENDING, "decision 7 was not offered (1, 2); ignored"),
    ("recovering, a late decision: ignored, said",
     RECOVERING, lambda e: decide(e, 1), RECOVERING,
     "late decision 1 ignored: already recovering"),
    ("nominal, a decision for nothing: silent", NOMINAL, lambda e: decide(e, 1), NOMINAL, None),
    ("pending, no decision by K: the fallback",
     PENDING, lambda e: commit(e, 1), FALLEN_BACK, "no decision by K: fallback to region 1"),
]


@pytest.mark.parametrize("name,before,transition,after,said", ROWS, ids=[r[0] for r in ROWS])
def test_each_transition(name, before, transition, after, said) -> None:
    assert transition(before) == (after, said)


def test_the_budget_counts_from_the_anomaly_and_a_holds_spent_ticks() -> None:
    assert NOMINAL.k(50) == 0 and NOMINAL.left(50, 20) is None and not NOMINAL.due(50, 20)
    assert PENDING.k(10) == 3 and PENDING.left(10, 20) == 17
    assert not PENDING.due(26, 20) and PENDING.due(27, 20)
    assert not RECOVERING.due(100, 20) and RECOVERING.left(100, 20) is None


def test_the_regions_kept_reachable_follow_the_episode() -> None:
    assert NOMINAL.active((1, 2, 3)) == (1, 2, 3)
    assert PENDING.active((1, 2, 3)) == (1, 2)
    assert RECOVERING.active((1, 2, 3)) == (2,)


class FakePlan:
    """The fields of a ``Plan`` the kept plan reads."""

    def __init__(self, t: int, m: int = 2, recovery: bool = True) -> None:
        self.inputs = np.arange(t * m, dtype=float).reshape(t, m)
        self.nominal = np.zeros((t + 1, 3))
        self.u0 = self.inputs[0]
        self.recovery_inputs = {1: self.inputs + 100.0} if recovery else {}
        self.recovery = {1: np.ones((t + 1, 3))} if recovery else {}


def test_a_kept_plan_is_flown_blind_step_by_step_then_its_last_input_repeats() -> None:
    plan = FakePlan(4)
    kept, flown = Kept(ahead=np.empty((0, 2))).keep(plan, np.full(3, 7.0))
    assert flown.plan is plan and flown.blind is None
    assert np.array_equal(flown.reference, np.full(3, 7.0))
    assert np.array_equal(kept.ahead, plan.inputs[1:1 + AHEAD])  # its own next inputs
    seen = []
    for _ in range(5):
        kept, flown = kept.blind(np.zeros(2))
        seen.append((flown.u[0], flown.blind, len(kept.ahead)))
    # the recovery branch's inputs (100 + ...), steps 1, 2, 3, then 3 again: spent
    assert seen == [(102.0, 2, 2), (104.0, 1, 1), (106.0, 0, 0), (106.0, 0, 0), (106.0, 0, 0)]


def test_nothing_kept_hovers_and_forgetting_drops_what_was_kept() -> None:
    kept, flown = Kept(ahead=np.empty((0, 2))).blind(np.array([9.0, 9.0]))
    assert flown.u.tolist() == [9.0, 9.0] and flown.reference is None and flown.blind == 0
    kept, _ = kept.keep(FakePlan(3, recovery=False), np.zeros(3))
    assert kept.forget().inputs is None and kept.forget().ahead.shape == (0, 2)
    assert kept.skipped(1).age == 1 and len(kept.skipped(1).ahead) == 1
    bad = replace(kept, ahead=np.full((2, 2), np.nan))
    assert bad.finite_ahead().ahead.shape == (0, 2)


CONFIG = MPCConfig(horizon=20, consensus=8, min_region_step=4, late_region_steps=3)


@pytest.mark.parametrize("k,last,expected", [
    (0, None, 20), (5, None, 15), (18, None, 4),  # s = T - k, at least min_region_step
    (5, 17, 16),  # a deadline pushed back stays pushed back (one step earlier per tick)
    (5, 30, 20),  # never past T
])
def test_the_regions_are_due_by_t_minus_k(k, last, expected) -> None:
    assert region_step(CONFIG, k, last) == expected
    assert promise(CONFIG, k, last) <= expected


class Status:
    def __init__(self, decided: bool) -> None:
        self.decided = decided


class Ladder:
    """A solve feasible from step ``reach`` on; ``decided`` False: it stops at its cap."""

    def __init__(self, reach: int, decided: bool = True) -> None:
        self.reach, self.decided, self.asked = reach, decided, []

    def __call__(self, s: int):
        self.asked.append(s)
        ok = s >= self.reach
        return type("P", (), {"feasible": ok, "status": SolveStatus.SOLVED if ok
                              else Status(self.decided)})()


def test_a_late_region_is_pushed_back_to_the_earliest_rung_and_said_once() -> None:
    solve = Ladder(reach=15)
    plan, last, said = late(solve, 10, CONFIG, None, "recovering")
    assert plan.feasible and last == 16  # the rungs are 13, 16, 19, T = 20, then T + 1
    assert solve.asked == [10, 21, 13, 19, 16]  # no deadline, then galloping, halving
    assert said == "recovering: region out of reach by step 10; heading for it by step 16"
    _, last, said = late(Ladder(reach=15), 10, CONFIG, 16, "recovering")
    assert last == 16 and said is None  # no further than before: nothing new to say


def test_a_rung_that_did_not_decide_drops_the_deadline_and_infeasible_keeps_the_last() -> None:
    solve = Ladder(reach=21, decided=False)
    plan, last, said = late(solve, 10, CONFIG, None, "recovering")
    assert solve.asked == [10, 21] and last == 21 and said.endswith("with no deadline")
    plan, last, said = late(Ladder(reach=99), 10, CONFIG, 12, "recovering")
    assert not plan.feasible and last == 12 and said is None


HARDWARE = MPCConfig(horizon=200, consensus=86, min_region_step=10)  # the paper's grid: T = 10 s


def test_a_region_out_of_reach_at_every_deadline_costs_two_solves_not_one_per_rung() -> None:
    """Issue 46: one tick solved all 38 rungs of the hardware grid (5 steps apart) before it
    flew the least-violating plan, 0.4-0.65 s beside two CPU hogs, and the vehicle held."""
    solve = Ladder(reach=999)
    plan, last, said = late(solve, 10, HARDWARE, None, "recovering")
    assert not plan.feasible and last is None and said is None
    assert solve.asked == [10, 201]  # the deadline, then none: feasibility only grows with s


@pytest.mark.parametrize("reach", [11, 14, 15, 16, 99, 137, 196, 199, 200, 201])
def test_the_earliest_reachable_rung_is_found_by_galloping_and_halving(reach: int) -> None:
    solve = Ladder(reach=reach)
    plan, last, _ = late(solve, 10, HARDWARE, None, "recovering")
    rungs = [*range(15, 200, 5), 200, 201]  # s pushed back 5 steps at a time, T, then none
    assert plan.feasible and last == min(r for r in rungs if r >= reach)
    assert len(solve.asked) <= 2 + 2 * math.ceil(math.log2(len(rungs)))  # 14, not up to 40
    if reach <= 15:  # one rung late: the deadline, none, the rung
        assert solve.asked == [10, 201, 15]


def test_a_pushed_pending_deadline_comes_a_step_nearer_a_tick_until_the_promise_is_later() -> None:
    """Issue 46: while the reasoner thinks, a tree out of reach by its promise is pushed back
    as a late region is (:func:`late`); then the deadline comes a step nearer each tick and
    the promise, which relaxes by less, takes over again."""
    config = replace(HARDWARE, reserve_steps=20)  # the scene's: 1 s, relaxing over K
    s = promise(config, 12, None)
    solve = Ladder(reach=s + 1)
    plan, last, said = late(solve, s, config, None, "while the reasoner thinks")
    assert plan.feasible and last == s + 5 and solve.asked == [s, 201, s + 5]
    ticks = [promise(config, 12 + i, last + 1 - i) for i in range(1, 40)]
    assert ticks[:5] == [s + 4, s + 3, s + 2, s + 1, s]  # last - 1, a step a tick
    assert ticks[-1] == promise(config, 51, None)  # then the promise again
    assert all(0 <= a - b <= 1 for a, b in zip(ticks, ticks[1:], strict=False))

