"""While the reasoner thinks, a tree whose regions fall out of reach by the promise is
still flown closed-loop: its deadline is pushed back as little as makes it feasible, then
comes a step nearer a tick (issue 46).

The tree's promise tightens by a step a tick (``T - k`` less a relaxing reserve). On a real
airframe the vehicle realizes the trunk's deceleration a little late, so in the hardware
scene, turning back at the red box with the far regions binding, the tree at the promise
was infeasible on about one pending tick in two (found on the second airframe, at 50 Hz
with 50 ms added, beside two CPU hogs). Each such tick flew the kept plan blind, open
loop, and in one flight for 1.2 s in a row: the body rate went over its limit. The same
tree with its regions due by T was feasible every time. The push is
:func:`~services.control.core.deadlines.late`'s, the earliest rung that is feasible, so
that the trunk still turns back; and it needs the box widened by what the lag carries
(``test_control_carry.py``): without it the recovery chosen later, riding its speed cap,
went infeasible and the least-violating plan flew the airframe 0.2 m/s over its limit.
"""

from __future__ import annotations

import numpy as np

from services.control.core.aesop import Controller
from services.control.core.controllers import make_controller
from services.control.core.deadlines import promise
from services.control.core.episode import Mode
from services.control.core.scenario import load_scenario

SCENARIO = load_scenario("hardware")

# a tick of such a flight: 12 ticks after the anomaly, 0.5 m short of the red box, still
# flying away from the regions at 0.63 m/s and decelerating at only 0.38 m/s^2 (the
# trunk's plan: 0.97); recorded from the second airframe's flight
LAGGING = np.array([2.3153, 0.0001, 0.4006, 0.6347, 0.0, 0.0001, 0, 0, 0, 0, 0, 0])
REALIZED = np.array([-0.378, -0.0002, 0.0])


def pending(ticks: int) -> Controller:
    """The hardware scene's loop flying in at 0.85 m/s, an anomaly 1.6 m short of the red
    box, then ``ticks - 1`` pending ticks on its own model."""
    ctrl = make_controller("aesop", SCENARIO)
    model, x = ctrl.model, np.zeros(12)
    x[:3], x[3] = (1.2, 0.0, 0.4), 0.85
    for t in range(3 + ticks - 1):
        out = ctrl.make_step(x.copy(), anomaly=t == 3)
        assert out.plan is not None and out.blind is None
        x = model.predict(x, ctrl.lag, [out.u], model.dt)
    assert ctrl.mode is Mode.PENDING
    return ctrl


def test_a_tree_out_of_reach_by_its_promise_is_flown_with_its_deadline_pushed_back_least() -> None:
    ctrl = pending(12)
    k = ctrl.episode.k(ctrl.t)
    s = promise(ctrl.config, k, ctrl.region_step)
    xm = ctrl.model.measure(LAGGING, np.asarray(REALIZED)[list(ctrl.model.lag_inputs)])
    options = ctrl.episode.options
    tight = ctrl.selector.solve(options, xm, ctrl.goal, ctrl.config.consensus - k, s)
    assert not tight.feasible and tight.status.decided  # the situation: out of reach by s

    out = ctrl.make_step(LAGGING, anomaly=False, realized=REALIZED)
    assert out.blind is None and out.plan is not None, "flew the kept plan blind"
    pushed = out.plan.region_step
    assert out.plan.feasible and s < pushed <= s + 2 * ctrl.config.late_region_steps
    assert out.plan.consensus == ctrl.config.consensus - k  # K' as Algorithm 1's
    assert any("out of reach" in e for e in out.events), out.events

    # the deadline stays pushed back and comes a step nearer a tick (Algorithm 1's T - k
    # from there): the next ticks are one solve each
    x = ctrl.model.predict(LAGGING, ctrl.lag, [out.u], ctrl.model.dt)
    out = ctrl.make_step(x, anomaly=False)
    assert out.plan is not None and out.plan.feasible
    assert out.plan.region_step == pushed - 1
    assert not any("out of reach" in e for e in out.events)
    x = ctrl.model.predict(x, ctrl.lag, [out.u], ctrl.model.dt)
    out = ctrl.make_step(x, anomaly=False)
    assert out.plan is not None and out.plan.region_step == pushed - 2


def test_the_deadline_pushed_back_while_pending_holds_into_recovery() -> None:
    """The region the reasoner picks is due no earlier than the tree promised it."""
    ctrl = pending(12)
    out = ctrl.make_step(LAGGING, anomaly=False, realized=REALIZED)
    assert out.plan is not None
    pushed = out.plan.region_step
    x = ctrl.model.predict(LAGGING, ctrl.lag, [out.u], ctrl.model.dt)
    out = ctrl.make_step(x, anomaly=False, decision=ctrl.episode.options[0])
    assert ctrl.mode is Mode.RECOVERING
    assert out.plan is not None and out.plan.feasible
    assert out.plan.region_step >= pushed - 1
