"""Recovery regions: labelled polytopes ``H x <= h`` over the 12-state.

A region is a position box with the vehicle at rest and level: velocity,
roll, pitch and body rates pinned to zero, yaw free within the state limits.
Every state in it is an equilibrium of the hover model under the hover input,
so the region is control invariant by construction (the paper's assumption on
``X_R^i``, used by Theorem 1). A landing region puts the box just above the
surface; a holding zone puts it in the air.

The MPC consumes the box form ``lo <= x <= hi``; :attr:`Region.polytope`
gives the same set as ``H x <= h`` for anyone who wants the general form.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from .dynamics import N_STATE, POS, RATE, VEL

RegionKind = Literal["landing", "hover"]
LABELS = ("grassy field", "rooftop", "parking lot", "alternative landing site", "holding zone")


@dataclass(frozen=True)
class Tolerance:
    """How far the nonlinear truth may sit outside a region and still be in it."""

    position: float = 0.05  # m beyond the box
    velocity: float = 0.1  # m/s
    tilt: float = 0.05  # rad, roll and pitch
    rate: float = 0.1  # rad/s

    def widen(self) -> np.ndarray:
        out = np.zeros(N_STATE)
        out[POS] = self.position
        out[VEL] = self.velocity
        out[6:8] = self.tilt
        out[RATE] = self.rate
        return out


@dataclass(frozen=True)
class Region:
    """One recovery region ``X_R^index`` (``index`` >= 1; 0 means "continue")."""

    index: int
    name: str
    label: str
    kind: RegionKind
    position_lo: tuple[float, float, float]  # m
    position_hi: tuple[float, float, float]  # m

    def __post_init__(self) -> None:
        if self.index < 1:
            raise ValueError(f"region {self.name!r}: index must be >= 1 (0 means continue)")
        if self.kind not in ("landing", "hover"):
            raise ValueError(f"region {self.name!r}: kind must be 'landing' or 'hover'")
        if not self.name:
            raise ValueError("region name must not be empty")
        lo, hi = np.asarray(self.position_lo), np.asarray(self.position_hi)
        if lo.shape != (3,) or hi.shape != (3,):
            raise ValueError(f"region {self.name!r}: position bounds need 3 values each")
        if not np.all(np.isfinite(lo)) or not np.all(np.isfinite(hi)) or np.any(lo > hi):
            raise ValueError(f"region {self.name!r}: need finite position_lo <= position_hi")

    @property
    def lo(self) -> np.ndarray:
        """Lower state bound (12,); yaw is ``-inf`` (left to the state limits)."""
        out = np.zeros(N_STATE)
        out[POS] = self.position_lo
        out[8] = -np.inf
        return out

    @property
    def hi(self) -> np.ndarray:
        out = np.zeros(N_STATE)
        out[POS] = self.position_hi
        out[8] = np.inf
        return out

    @property
    def center(self) -> np.ndarray:
        """The rest state at the middle of the box (12,)."""
        out = np.zeros(N_STATE)
        out[POS] = (np.asarray(self.position_lo) + np.asarray(self.position_hi)) / 2
        return out

    @property
    def polytope(self) -> tuple[np.ndarray, np.ndarray]:
        """``(H, h)`` with ``H x <= h`` (yaw rows omitted: yaw is free)."""
        rows = [i for i in range(N_STATE) if i != 8]
        eye = np.eye(N_STATE)[rows]
        return np.vstack([eye, -eye]), np.concatenate([self.hi[rows], -self.lo[rows]])

    def contains(self, x: np.ndarray, tolerance: Tolerance | None = None) -> bool:
        """Whether ``x`` lies in the region, widened by ``tolerance``."""
        widen = (tolerance or Tolerance(0, 0, 0, 0)).widen()
        return bool(np.all(x >= self.lo - widen) and np.all(x <= self.hi + widen))

    def to_dict(self) -> dict[str, Any]:
        return {"index": self.index, "name": self.name, "label": self.label, "kind": self.kind,
                "position_lo": list(self.position_lo), "position_hi": list(self.position_hi)}


def check_regions(regions: tuple[Region, ...]) -> None:
    """Indices must be 1..d without gaps and names unique."""
    indices = sorted(r.index for r in regions)
    if indices != list(range(1, len(regions) + 1)):
        raise ValueError(f"region indices must be 1..{len(regions)}, got {indices}")
    names = [r.name for r in regions]
    if len(set(names)) != len(names):
        raise ValueError("region names must be unique")

