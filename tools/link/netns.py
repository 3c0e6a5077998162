"""Two hosts on one machine: a network namespace for the robot, joined to ours by a veth pair.

This namespace is the server's, so what the robot and the server say to each other crosses a real
network interface between real addresses, not loopback.

The robot's namespace has its own loopback (its router is open there, as on a robot's own
computer) and one interface, ``<name>r`` at ``10.<a>.<b>.2``; this namespace gets
``<name>s`` at ``10.<a>.<b>.1``. Processes run in the robot's namespace through
``ip netns exec`` (:meth:`Link.run`). Needs ``ip`` (iproute2) and root (CAP_NET_ADMIN);
these kernels have no ``tc netem``, so faults come from :mod:`.proxy` on the link.

    with robot_namespace("aesop41") as link:
        subprocess.run(link.run(["ping", "-c1", link.server_ip]))
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass


@dataclass(frozen=True)
class Link:
    """The robot's namespace and the two ends of its link."""

    namespace: str
    server_ip: str  # this namespace's end
    robot_ip: str  # the robot's end

    def run(self, argv: Sequence[str]) -> list[str]:
        """``argv`` run in the robot's namespace."""
        return ["ip", "netns", "exec", self.namespace, *argv]


def missing() -> str | None:
    """Why no namespace can be made here (None: one can)."""
    if shutil.which("ip") is None:
        return "no `ip` command (Debian's iproute2)"
    if os.geteuid() != 0:
        return "not root: a network namespace and a veth pair need CAP_NET_ADMIN"
    return None


def subnet_of(name: str) -> tuple[int, int]:
    """The ``10.<a>.<b>.0/24`` of a link, from its name (two links of two runs at once get
    two subnets unless their names collide)."""
    digest = sum((i + 1) * ord(c) for i, c in enumerate(name))
    return 200 + digest % 50, digest // 50 % 250 + 1


@contextmanager
def robot_namespace(name: str) -> Iterator[Link]:
    """The robot's namespace ``name`` (at most 14 characters: it names the interfaces too)
    and its link to this one, up; everything removed on exit, and first if a crashed run
    left it behind."""
    if len(name) > 14:
        raise ValueError(f"namespace name {name!r}: at most 14 characters")
    why = missing()
    if why is not None:
        raise RuntimeError(f"cannot make the robot's network namespace: {why}")
    a, b = subnet_of(name)
    link = Link(name, f"10.{a}.{b}.1", f"10.{a}.{b}.2")
    server_end, robot_end = f"{name}s", f"{name}r"
    _remove(name, server_end)
    try:
        for argv in (["ip", "netns", "add", name],
                     ["ip", "link", "add", server_end, "type", "veth", "peer", "name", robot_end],
                     ["ip", "link", "set", robot_end, "netns", name],
                     ["ip", "addr", "add", f"{link.server_ip}/24", "dev", server_end],
                     ["ip", "link", "set", server_end, "up"],
                     ["ip", "-n", name, "addr", "add", f"{link.robot_ip}/24", "dev", robot_end],
                     ["ip", "-n", name, "link", "set", robot_end, "up"],
                     ["ip", "-n", name, "link", "set", "lo", "up"]):
            _ip(argv)
        yield link
    finally:
        _remove(name, server_end)


def _ip(argv: Sequence[str]) -> None:
    done = subprocess.run(argv, capture_output=True, text=True, timeout=30,
                          stdin=subprocess.DEVNULL)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: {done.stderr.strip()}")


def _remove(name: str, server_end: str) -> None:
    """The namespace (its end of the veth pair goes with it) and this end, if there."""
    for argv in (["ip", "netns", "del", name], ["ip", "link", "del", server_end]):
        subprocess.run(argv, capture_output=True, timeout=30, stdin=subprocess.DEVNULL)
