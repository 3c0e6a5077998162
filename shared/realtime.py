"""Asking the OS to run a deadline thread ahead of the rest of the machine.

A thread that must act at a deadline (the reasoner's fallback at K) loses it when the
cores are busy with other processes: the scheduler shares them fairly, and a thread
that wakes at its deadline may wait its turn (tens of ms measured with two busy
processes on two cores, ``aesop bench reasoner --cpu-hog 2``). :func:`urgent` asks,
for the calling thread, for the real-time FIFO class at its lowest priority (it then runs
before every ordinary thread of the machine the moment it wakes), else for a higher
nice value, else leaves it as it is; it never raises. A real-time thread must sleep
most of the time: give it only short work.

A nice value ranks a process's threads against the other threads of its *autogroup*
only. Where the kernel groups processes by session (``/proc/sys/kernel/sched_autogroup_enabled``,
on by default in most distributions), each session shares the cores as one nice-0 task, and
``aesop up`` starts every service in a session of its own: control at nice -10 beside two CPU
hogs got no larger share than any of them, and its MPC solves ran up to 200 times slower than
alone (30 OSQP iterations in 650 ms), so its set-points stopped for up to 2.8 s (issue 46).
:func:`favoured` therefore also gives the session's autogroup the same nice value, where the
process leads its session (as under ``aesop up``); a process started from a shell leaves its
shell's session as it is.

Either needs the ``CAP_SYS_NICE`` capability (root has it; in a container,
``cap_add: [SYS_NICE]``); without it the thread runs as any other and says so once.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from typing import Literal

log = logging.getLogger(__name__)

Priority = Literal["realtime", "nice", "normal"]
NICE = -10


def favoured() -> bool:
    """Give the calling thread, and the threads it starts from now on, a higher nice
    value (a larger share of a busy machine's cores), if allowed; whether it was. For a
    process whose deadline thread needs the GIL from its other threads: they must not
    wait behind other processes to hand it over."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), NICE)
    except (OSError, AttributeError):
        return False
    _favour_autogroup()
    return True


AUTOGROUP = "/proc/self/autogroup"


def _favour_autogroup() -> None:
    """Give this process's session, where it leads it, the nice value :data:`NICE` among the
    machine's sessions (the autogroup scheduler's share). Elsewhere (no autogroups, another
    process's session, not allowed) nothing changes."""
    if os.getsid(0) != os.getpid():
        return
    with contextlib.suppress(OSError), open(AUTOGROUP, "w") as f:
        f.write(str(NICE))


def urgent(above: int = 0) -> Priority:
    """Raise the calling thread's scheduling priority as far as allowed; what it got.
    ``above``: how many real-time levels over the lowest (a thread that must preempt
    other real-time threads of its own process asks for 1)."""
    try:
        policy = os.SCHED_FIFO
        level = os.sched_get_priority_min(policy) + above
        os.sched_setscheduler(0, policy, os.sched_param(level))
        return "realtime"
    except (OSError, AttributeError):
        pass
    if favoured():
        return "nice"
    log.warning("the %s thread runs at normal priority (no CAP_SYS_NICE): on a busy "
                "machine it may act late", threading.current_thread().name)
    return "normal"
