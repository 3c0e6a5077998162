"""The detector's per-robot inbox (services/embedding/fairness.py): one robot's flood
neither delays nor drops another robot's observations, and every refusal is counted."""

from __future__ import annotations

import pytest

from services.embedding.fairness import OTHER, FairInbox


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def offer(inbox: FairInbox[int], robot: str, item: int) -> bool:
    return inbox.admit(robot) is None and inbox.put(robot, item)


def test_a_flooding_robot_waits_its_turn_behind_a_quiet_one() -> None:
    inbox: FairInbox[int] = FairInbox(rate_hz=1000, max_robots=8, depth=32, per_robot=2,
                                      clock=Clock())
    for i in range(30):  # robot1 floods first
        offer(inbox, "robot1", i)
    offer(inbox, "robot0", 100)
    first = [inbox.take() for _ in range(3)]
    # robot1's first, then robot0's at once (not after robot1's 29 others), then robot1's
    assert first == [("robot1", 0), ("robot0", 100), ("robot1", 1)]
    assert inbox.take() is None  # robot1 has its 2 slots, robot0 nothing waiting
    inbox.done("robot1")
    assert inbox.take() == ("robot1", 2)


def test_by_default_a_flooding_robot_has_one_observation_in_any_batch() -> None:
    """Issue 43, finding 10: the observations being scored at once are the embedding
    batch; 4 of a robot's at once put 4 of a flood's distinct texts beside (and in the
    batch before) another robot's one, which waited for all of them. By default a robot
    has one being scored: whatever batch another robot's observation waits for, or is
    in, holds at most one of the flood's."""
    inbox: FairInbox[str] = FairInbox(rate_hz=10_000, max_robots=8, clock=Clock())
    for i in range(1000):  # robot A floods distinct texts (its queue keeps the newest)
        offer(inbox, "A", f"A's text {i}")
    offer(inbox, "B", "B's text")
    scoring = []
    while (nxt := inbox.take()) is not None:  # all that may be scored at once
        scoring.append(nxt)
    assert scoring == [("A", "A's text 968"), ("B", "B's text")]
    inbox.done("A")
    assert inbox.take() == ("A", "A's text 969")  # A's next, once its one was scored
    assert inbox.take() is None


def test_a_full_queue_drops_its_own_oldest_and_counts_it() -> None:
    inbox: FairInbox[int] = FairInbox(rate_hz=1000, max_robots=8, depth=4, per_robot=1,
                                      clock=Clock())
    offer(inbox, "robot0", 0)
    kept = [offer(inbox, "robot1", i) for i in range(6)]
    assert kept == [True] * 4 + [False] * 2
    got = [inbox.take(), inbox.take()]
    assert got == [("robot0", 0), ("robot1", 2)]  # robot1's two oldest went
    assert inbox.counts() == {("robot1", "full"): 2}


def test_the_rate_is_per_robot_with_a_second_of_burst() -> None:
    clock = Clock()
    inbox: FairInbox[int] = FairInbox(rate_hz=10, max_robots=8, clock=clock)
    admitted = sum(inbox.admit("robot1") is None for _ in range(50))
    assert admitted == 10  # a burst of one second's worth
    assert inbox.admit("robot0") is None  # the other robot's own bucket is full
    clock.t = 0.5
    assert sum(inbox.admit("robot1") is None for _ in range(50)) == 5  # refilled at 10 Hz
    assert inbox.counts() == {("robot1", "rate"): 85}


def test_robots_past_the_limit_replace_idle_ones_or_are_refused() -> None:
    inbox: FairInbox[int] = FairInbox(rate_hz=1000, max_robots=2, per_robot=1, clock=Clock())
    offer(inbox, "a", 1)
    offer(inbox, "b", 2)
    assert inbox.admit("c") == "robots"  # a and b both have work waiting
    assert inbox.take() == ("a", 1)
    inbox.done("a")  # a is idle now: c takes its place
    assert inbox.admit("c") is None and inbox.put("c", 3)
    for i in range(100):  # made-up robot ids cannot grow the counters
        inbox.admit(f"x{i}")
    assert inbox.counts() == {(OTHER, "robots"): 101}


def test_bad_limits_are_refused() -> None:
    with pytest.raises(ValueError, match="positive"):
        FairInbox(rate_hz=0, max_robots=1)


def test_refusals_are_reported_once_per_robot_per_window() -> None:
    from services.embedding.fairness import DropReports

    reports = DropReports(every_s=10.0)
    assert reports.due({("r1", "rate"): 5}, now=0.0) == {"r1": {"rate": 5}}
    assert reports.due({("r1", "rate"): 9, ("r2", "full"): 1}, now=3.0) == {"r2": {"full": 1}}
    assert reports.due({("r1", "rate"): 9, ("r2", "full"): 1}, now=5.0) == {}
    # r1's window ended: what came since its report, in one
    assert reports.due({("r1", "rate"): 12, ("r2", "full"): 1}, now=10.5) == {"r1": {"rate": 7}}
    assert reports.due({}, now=30.0) == {}  # forgotten robots leave nothing behind
