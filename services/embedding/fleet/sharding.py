"""Which detector replica scores which robot (pure): rendezvous hashing.

Every replica announces itself (a liveliness token, :mod:`.replicas`) and sees the others'.
Each robot belongs to the live replica with the highest weight ``hash(replica, robot)``
(highest random weight, Thaler and Ravishankar 1998): every replica computes the same owner
from the same set, no coordination, and when a replica leaves only its robots move, each to
the replica that comes second for it; when one joins it takes about 1/n of the robots.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable


def weight(replica: str, robot: str) -> int:
    """The robot's weight on the replica: 64 bits of BLAKE2b of both names."""
    digest = hashlib.blake2b(f"{replica}\0{robot}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big")


def owner(robot: str, replicas: Iterable[str]) -> str | None:
    """The replica that scores ``robot`` (None without any replica); ties, which 64 bits
    make all but impossible, go to the smaller name."""
    best: tuple[int, str] | None = None
    for replica in replicas:
        key = (weight(replica, robot), replica)
        if best is None or key[0] > best[0] or (key[0] == best[0] and replica < best[1]):
            best = key
    return None if best is None else best[1]


def assignment(robots: Iterable[str], replicas: Iterable[str]) -> dict[str, list[str]]:
    """Each live replica's robots (sorted), every replica listed."""
    live = sorted(set(replicas))
    out: dict[str, list[str]] = {r: [] for r in live}
    for robot in sorted(set(robots)):
        found = owner(robot, live)
        if found is not None:
            out[found].append(robot)
    return out
