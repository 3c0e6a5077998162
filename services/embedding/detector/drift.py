"""Drift: a robot's verdicts flag more than the calibration allows (pure).

A calibrated detector promises to flag at most ``1 - alpha`` of nominal observations. A new
captioner, camera or model update breaks that promise for every frame at once, and a robot
that sees one anomaly after another cannot tell drift from danger. So, per robot, the
verdicts of its last ``window`` distinct scenes are tested against the promise: with ``k``
of ``n`` flagged, the binomial tail ``P(X >= k)`` for ``X ~ Binomial(n, 1 - alpha)``; below
``significance`` the robot is *drifting*, named in one ``drift`` event with the new phrases
its flagged scenes held most often (those the cache holds no exact match for), until the
tail rises above :data:`CLEAR_P` again (``drift_cleared``).

A scene already in the window does not count again: one anomaly that stays in view for a
minute is one flagged scene, not 600, and never reads as drift (a captioner that rewrites
every object makes one new scene after another). At the defaults (50 scenes, 1e-7) it takes
15 flagged scenes in 50 at alpha 0.95, and a switch that flags every scene is named on its
15th.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

from scipy.special import bdtrc

CLEAR_P = 0.01  # a drifting robot is cleared once its window's tail is above this
NAMED = 5  # new phrases a drift event names


@dataclass(frozen=True)
class DriftReport:
    """What a robot's window shows when its drift state changes."""

    state: Literal["drift", "cleared"]
    flagged: int
    seen: int
    expected_rate: float
    p_value: float
    phrases: tuple[str, ...]

    @property
    def message(self) -> str:
        said = (f"{self.flagged} of the last {self.seen} observations flagged where the "
                f"calibration allows {self.expected_rate:.0%} (binomial p {self.p_value:.1e})")
        if self.state == "cleared":
            return f"detector drift cleared: {said}"
        named = "; ".join(self.phrases) or "no detections named"
        return (f"detector drift: {said}; the detector may be seeing new wording, not new "
                f"objects. New phrases seen most: {named}. Accept reviewed scenes in the new "
                "wording to re-learn (docs/embedding.md)")


@dataclass
class _Robot:
    verdicts: deque[tuple[bool, tuple[str, ...], str]]  # flagged, new phrases, scene
    scenes: set[str] = field(default_factory=set)  # those in ``verdicts``
    drifting: bool = False
    flagged: int = 0  # of the verdicts kept
    phrases: Counter[str] = field(default_factory=Counter)


class DriftMonitor:
    """The drift state of each robot, from its verdicts in turn (:meth:`observe`)."""

    def __init__(self, window: int = 50, significance: float = 1e-7,
                 max_robots: int = 256) -> None:
        self.window = window
        self.significance = significance
        self.max_robots = max_robots
        self._robots: dict[str, _Robot] = {}

    def drifting(self) -> list[str]:
        return sorted(r for r, state in self._robots.items() if state.drifting)

    def current(self, robot: str) -> tuple[int, int, tuple[str, ...]] | None:
        """A drifting robot's flagged and seen verdicts in its window, and the new phrases
        its flagged observations held most; None when it is not drifting."""
        state = self._robots.get(robot)
        if state is None or not state.drifting:
            return None
        return state.flagged, len(state.verdicts), self._named(state)

    @staticmethod
    def _named(state: _Robot) -> tuple[str, ...]:
        return tuple(p for p, _ in state.phrases.most_common(NAMED))

    def observe(self, robot: str, flagged: bool, rate: float | None,
                new_phrases: Sequence[str] = (), scene: str | None = None
                ) -> DriftReport | None:
        """One verdict of ``robot`` for ``scene`` (its content's key; None: every verdict a
        scene of its own), ``new_phrases`` its detections the cache holds no exact match
        for; ``rate`` the false-positive rate the calibration allows (None: nothing
        promised, e.g. uncalibrated: not tested). A report when the robot starts or stops
        drifting; a scene already in the window changes nothing."""
        state = self._robots.get(robot)
        if state is None:
            if len(self._robots) >= self.max_robots:
                self._robots.pop(next(iter(self._robots)))
            state = self._robots[robot] = _Robot(deque(maxlen=self.window))
        if scene is not None and scene in state.scenes:
            return None
        if len(state.verdicts) == self.window:
            old_flagged, old, old_scene = state.verdicts[0]
            state.scenes.discard(old_scene)
            state.flagged -= old_flagged
            for phrase in old:
                state.phrases[phrase] -= 1
                if state.phrases[phrase] <= 0:
                    del state.phrases[phrase]
        kept = tuple(dict.fromkeys(new_phrases)) if flagged else ()
        if scene is not None:
            state.scenes.add(scene)
        state.verdicts.append((flagged, kept, "" if scene is None else scene))
        state.flagged += flagged
        state.phrases.update(kept)
        if rate is None or not 0.0 < rate < 1.0:
            return None
        seen, k = len(state.verdicts), state.flagged
        p = float(bdtrc(k - 1, seen, rate)) if k else 1.0  # P(X >= k), X ~ Bin(seen, rate)
        if not state.drifting and p < self.significance:
            state.drifting = True
            return DriftReport("drift", k, seen, rate, p, self._named(state))
        if state.drifting and p > CLEAR_P:
            state.drifting = False
            return DriftReport("cleared", k, seen, rate, p, ())
        return None
