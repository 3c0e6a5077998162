"""When a plan must reach its regions: Algorithm 1's ``s = T - k``, and how it moves.

``k`` ticks into the consensus budget the regions are due by step ``s = T - k`` (at least
``MPCConfig.min_region_step``: the nonlinear plant's small model errors never pin a region
to the very next step, a documented deviation). A deadline pushed back stays pushed back:
never earlier than one step before the last plan's (``last``). Pure functions of the
configuration and the last plan's deadline; the controller keeps ``last``.
"""

from __future__ import annotations

from collections.abc import Callable

from .mpc import MPCConfig, Plan, promised_step


def region_step(config: MPCConfig, k: int, last: int | None) -> int:
    """``s = T - k``, at least ``min_region_step``, no earlier than ``last - 1``."""
    s = max(config.min_region_step, config.horizon - k)
    return s if last is None else min(max(s, last - 1), config.horizon)


def promise(config: MPCConfig, k: int, last: int | None) -> int:
    """While the reasoner thinks (or a hold lasts), ``k`` ticks into the consensus budget:
    the tree's relaxing promise (:func:`.mpc.promised_step`), at least ``min_region_step``;
    a deadline pushed back :func:`late` comes a step nearer a tick (``last - 1``, never
    past ``T``) until the promise is later again (it relaxes: less than a step a tick)."""
    s = max(config.min_region_step, promised_step(config, k))
    return s if last is None else max(s, min(last - 1, config.horizon))


def late(solve: Callable[[int], Plan], s: int, config: MPCConfig, last: int | None,
         what: str) -> tuple[Plan, int | None, str | None]:
    """``solve(s)``; if infeasible, ``solve`` again with the region due later. Returns the
    plan, the deadline to remember (``last`` unless the plan is feasible) and what to say.

    On the nonlinear plant the measured state drifts from the linear plan, and a region
    due in ``s`` steps can be out of reach while it is still reachable a little later
    (killing a small residual velocity takes the attitude chain about 1 s). The deadline
    is pushed back to the earliest of the rungs ``s + late_region_steps``, ``s + 2
    late_region_steps``, ... , ``T`` where the plan is feasible, else dropped (``s = T +
    1``: the plan only heads for the region), so that the state and input limits stay hard
    for as long as they can be met. Feasibility only grows with ``s``, so one solve without
    a deadline comes first, and then the rungs are searched by galloping and halving: a
    region out of reach at every deadline costs two solves, not one per rung (one tick
    solved the hardware grid's 38 rungs in 0.4-0.65 s beside two CPU hogs, and the vehicle
    held: issue 46), a region one rung late three, the farthest rung about ``2 log2`` of
    their number. A solve that does not decide (it stopped at its cap) ends the search
    with the latest feasible plan found. Said once per deadline pushed further (beyond the
    paper).
    """
    plan = solve(s)
    if plan.feasible:
        return plan, s, None
    first, decided = s, plan.status.decided
    s = config.horizon + 1
    plan = solve(s)
    if not plan.feasible:
        return plan, last, None
    if decided:  # a solve at its cap: no time for more of them this tick
        step = config.late_region_steps
        rungs = [r for r in (*range(first + step, config.horizon, step), config.horizon)
                 if r > first]
        s, plan = _earliest(solve, rungs, s, plan)
    said = None
    if last is None or s > last:
        due = "with no deadline" if s > config.horizon else f"by step {s}"
        said = f"{what}: region out of reach by step {first}; heading for it {due}"
    return plan, s, said


def _earliest(solve: Callable[[int], Plan], rungs: list[int], s: int, plan: Plan
              ) -> tuple[int, Plan]:
    """The earliest of ``rungs`` (ascending; feasibility grows along them) whose plan is
    feasible, and its plan; ``(s, plan)``, a feasible plan past the last rung, where none is
    or a solve does not decide. Galloping (rungs 1, 2, 4, 8, ... on), then halving the gap
    the first feasible one closes: a region a rung or two late costs a solve or two."""
    below, above = -1, len(rungs)  # rungs[below] infeasible, rungs[above] feasible
    reach = 1  # the gallop's next stride; 0 once a feasible rung bounds the search
    while above - below > 1:
        middle = min(below + reach, above - 1) if reach else (below + above) // 2
        tried = solve(rungs[middle])
        if tried.feasible:
            above, s, plan, reach = middle, rungs[middle], tried, 0
        elif not tried.status.decided:
            break
        else:
            below, reach = middle, 2 * reach
    return s, plan
