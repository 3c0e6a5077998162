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
    the tree's relaxing promise (:func:`.mpc.promised_step`), never later than
    :func:`region_step`."""
    return min(max(config.min_region_step, promised_step(config, k)),
               region_step(config, k, last))


def late(solve: Callable[[int], Plan], s: int, config: MPCConfig, last: int | None,
         what: str) -> tuple[Plan, int | None, str | None]:
    """``solve(s)``; if infeasible, ``solve`` again with the region due later. Returns the
    plan, the deadline to remember (``last`` unless the plan is feasible) and what to say.

    On the nonlinear plant the measured state drifts from the linear plan, and a region
    due in ``s`` steps can be out of reach while it is still reachable a little later
    (killing a small residual velocity takes the attitude chain about 1 s). Feasibility
    only grows with ``s``, so this pushes the deadline back in ``late_region_steps``
    increments up to ``T``, and last drops it (``s = T + 1``: the plan only heads for the
    region) so that the state and input limits stay hard for as long as they can be met.
    Said once per deadline pushed further (beyond the paper).
    """
    plan = solve(s)
    first = s
    while not plan.feasible and s <= config.horizon:
        if not plan.status.decided or s == config.horizon:
            s = config.horizon + 1  # a rung that did not decide: straight to the last one
        else:
            s = min(config.horizon, s + config.late_region_steps)
        plan = solve(s)
    if not plan.feasible:
        return plan, last, None
    said = None
    if s > first and (last is None or s > last):
        due = "with no deadline" if s > config.horizon else f"by step {s}"
        said = f"{what}: region out of reach by step {first}; heading for it {due}"
    return plan, s, said
