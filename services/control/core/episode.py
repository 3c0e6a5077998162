"""One anomaly's life in the controller, as one immutable value and its pure transitions.

Algorithm 1's modes (:mod:`.aesop`'s docstring) are the life of one anomaly: flagged in
``nominal`` flight it becomes ``anomaly_pending`` with the regions offered to the reasoner
(``Y_tanom``) and the tick it was flagged (``t_anom``); the reasoner's answer either ends
it ("continue", ``y = 0``: back to ``nominal``) or commits a region (``recovering``), and
with no answer by ``K`` the controller commits a fallback itself. Every field of that life
is here; the :class:`~.aesop.Controller` holds one :class:`Episode` and replaces it.

Each transition returns the next episode and the line a person should read (``None``:
nothing happened). One table (``tests/unit/test_control_episode.py``) shows them all.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from shared.messages import Mode


@dataclass(frozen=True)
class Episode:
    """The pending or handled anomaly (all defaults: nominal flight, none pending)."""

    mode: Mode = Mode.NOMINAL
    t_anom: int | None = None  # tick the anomaly was flagged
    options: tuple[int, ...] = ()  # regions offered to the reasoner (Y_tanom)
    chosen: int | None = None  # region committed to (recovering)
    fallback: bool = False  # committed without a decision
    spent: int = 0  # consensus ticks a hold had already used when the anomaly came

    def k(self, t: int) -> int:
        """Ticks of the consensus budget used by tick ``t`` (a hold's included)."""
        return 0 if self.t_anom is None else t - self.t_anom + self.spent

    def due(self, t: int, consensus: int) -> bool:
        """Pending with the budget spent: the fallback must be committed now."""
        return self.mode is Mode.PENDING and self.k(t) >= consensus

    def left(self, t: int, consensus: int) -> int | None:
        """Ticks of the budget left while pending (``None`` otherwise)."""
        return consensus - self.k(t) if self.mode is Mode.PENDING else None

    def active(self, kept: tuple[int, ...]) -> tuple[int, ...]:
        """The regions this step keeps reachable: the chosen one, the offered ones, or the
        subset nominal flight keeps (``kept``)."""
        if self.mode is Mode.RECOVERING and self.chosen is not None:
            return (self.chosen,)
        return self.options if self.mode is Mode.PENDING else kept


def detect(episode: Episode, t: int, options: tuple[int, ...], spent: int,
           blind: bool = False) -> tuple[Episode, str | None]:
    """An anomaly flagged at tick ``t``: in nominal flight with regions to offer, ask the
    reasoner among ``options``; otherwise nothing changes (one anomaly at a time)."""
    if episode.mode is not Mode.NOMINAL or not options:
        return episode, None
    asked = Episode(Mode.PENDING, t_anom=t, options=options, spent=spent)
    what = "anomaly while flying blind" if blind else "anomaly"
    return asked, f"{what}: asking the reasoner among regions {options}"


def decide(episode: Episode, decision: int | None) -> tuple[Episode, str | None]:
    """The reasoner's ``decision`` for the pending anomaly (``None``: still thinking)."""
    if decision is None:
        return episode, None
    if episode.mode is Mode.RECOVERING:
        return episode, f"late decision {decision} ignored: already recovering"
    if episode.mode is not Mode.PENDING:
        return episode, None
    if decision == 0:
        return Episode(spent=episode.spent), "continue (y = 0): back to nominal"
    if decision in episode.options:
        return (replace(episode, mode=Mode.RECOVERING, chosen=decision),
                f"reasoner chose region {decision}; recovering")
    return episode, f"decision {decision} was not offered {episode.options}; ignored"


def commit(episode: Episode, choice: int) -> tuple[Episode, str]:
    """No decision by K: recover to ``choice`` without one."""
    return (replace(episode, mode=Mode.RECOVERING, chosen=choice, fallback=True),
            f"no decision by K: fallback to region {choice}")
