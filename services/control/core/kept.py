"""What the controller flies when a step has no usable plan: the last one it kept.

A step that solves flies its plan's first input and keeps the plan (its recovery branch
when it has one: the shared prefix that keeps every region of the subset reachable, the
safest thing to fly blind, ending at rest in its region). A step that does not solve,
or has no usable state, flies the kept plan one input further on (``blind``). Either way
the step says what it flew as a :class:`Flown`: the input, the model state the plan
expects now (the set-point's reference) and the plan's next inputs (``ahead``), which
the vehicle flies through ticks the loop misses. A lagged input the step sends, and each
one ahead, starts within the lag gap the MPC plans with of the lag state it meets
(:meth:`Kept.within_reach`): the recovery branch flown blind after late ticks, the trunk's
inputs ahead having been flown meanwhile, would otherwise step the vehicle's tilt.

Pure and immutable: :class:`Kept` values are replaced, never changed.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .mpc import MPCConfig, Plan
from .planning import PlanningModel

AHEAD = 16  # the plan's next inputs an output carries (the set-point sends some of them)


@dataclass(frozen=True)
class Flown:
    """One step's input and what the vehicle is told beside it."""

    u: np.ndarray
    plan: Plan | None  # this step's own plan; None when it flew the kept one
    reference: np.ndarray | None = None  # the model state the plan expects now
    blind: int | None = None  # the kept plan's steps left after this one (None: own plan)


def _empty() -> np.ndarray:
    return np.empty((0, 0))


@dataclass(frozen=True)
class Kept:
    """The last usable plan's inputs ``(T, m)`` and the states they fly ``(T+1, n)``, the
    steps flown since it was kept, and the inputs after this step's (``ahead``)."""

    inputs: np.ndarray | None = None
    states: np.ndarray | None = None
    age: int = 0
    ahead: np.ndarray = field(default_factory=_empty)

    def keep(self, plan: Plan, measured: np.ndarray) -> tuple[Kept, Flown]:
        """Fly ``plan`` (its inputs finite) from the model state ``measured``, and keep it."""
        kept = Kept(inputs=next(iter(plan.recovery_inputs.values()), plan.inputs),
                    states=next(iter(plan.recovery.values()), plan.nominal),
                    ahead=plan.inputs[1:1 + AHEAD])
        return kept, Flown(plan.u0, plan, reference=measured)

    def blind(self, hover: np.ndarray) -> tuple[Kept, Flown]:
        """The kept plan's next input (its last repeated once spent), or ``hover``."""
        if self.inputs is None:
            return replace(self, ahead=self.ahead[:0]), Flown(hover.copy(), None, blind=0)
        age = self.age + 1
        step = min(age, len(self.inputs) - 1)
        reference = None if self.states is None else self.states[step]
        kept = replace(self, age=age, ahead=self.inputs[step + 1:step + 1 + AHEAD])
        return kept, Flown(self.inputs[step].copy(), None, reference,
                           blind=len(self.inputs) - 1 - step)

    def within_reach(self, model: PlanningModel, lag: np.ndarray, u: np.ndarray,
                     config: MPCConfig) -> tuple[Kept, np.ndarray]:
        """``u`` (meeting the lag states ``lag``) and the inputs ahead, each moved within
        the share of its lag gap the MPC plans with (:meth:`.PlanningModel.within_reach`);
        a solved plan's inputs are already there."""
        rows = np.vstack([u, self.ahead.reshape(-1, len(u))])
        rows = model.within_reach(lag, rows, config.lag_gap_share)
        return replace(self, ahead=rows[1:]), rows[0]

    def skipped(self, ticks: int) -> Kept:
        """``ticks`` ticks passed unstepped (the vehicle flew what was sent ahead)."""
        return replace(self, age=self.age + ticks * (self.inputs is not None),
                       ahead=self.ahead[ticks:])

    def forget(self) -> Kept:
        """Nothing kept is flyable (a non-finite input): hover from now on."""
        return Kept(ahead=self.ahead[:0])

    def finite_ahead(self) -> Kept:
        return self if np.all(np.isfinite(self.ahead)) else replace(self, ahead=self.ahead[:0])
