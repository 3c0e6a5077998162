"""The ROS 2 bridge's queues (services/ros2/lanes.py): each lane bounded in items and in
bytes, the oldest dropped and handed back to be counted, one larger than its lane
refused; taken by priority (the set-points first) or in turn (the ROS topics)."""

from __future__ import annotations

import threading

import pytest

from services.ros2.lanes import Lanes, Limit


def test_a_lane_drops_its_oldest_past_its_items():
    lanes = Lanes({"a": Limit(3)}, in_turn=True)
    assert [lanes.put("a", i) for i in range(5)] == [[], [], [], [0], [1]]
    assert [lanes.take(0.0) for _ in range(4)] == [("a", 2), ("a", 3), ("a", 4), None]
    assert lanes.status()["a"]["dropped"] == 2


def test_a_lane_never_holds_more_than_its_bytes():
    lanes = Lanes({"a": Limit(100, bytes=1000)}, in_turn=True)
    dropped = [lanes.put("a", i, 300) for i in range(10)]
    status = lanes.status()["a"]
    assert status["items"] == 3 and status["bytes"] == 900 and status["peak_bytes"] == 900
    assert sum(len(d) for d in dropped) == 7 == status["dropped"]
    assert lanes.put("a", "large", 1001) == ["large"]  # larger than the lane: refused
    assert lanes.status()["a"]["items"] == 3 and lanes.bytes() == 900
    lanes.take(0.0)
    assert lanes.bytes() == 600


def test_priority_takes_the_first_lane_with_something_in_it():
    lanes = Lanes({"setpoint": Limit(8), "stack": Limit(8)}, in_turn=False)
    for i in range(3):
        lanes.put("stack", f"s{i}")
    lanes.put("setpoint", "p0")
    assert lanes.take(0.0) == ("setpoint", "p0")
    lanes.put("setpoint", "p1")
    assert [lanes.take(0.0) for _ in range(3)] == [("setpoint", "p1"), ("stack", "s0"),
                                                   ("stack", "s1")]


def test_in_turn_a_flooded_lane_waits_behind_the_others():
    lanes = Lanes({"odometry": Limit(64), "detections": Limit(64)}, in_turn=True)
    for i in range(50):
        lanes.put("detections", f"d{i}")
    lanes.put("odometry", "o0")
    lanes.put("odometry", "o1")
    taken = [lanes.take(0.0) for _ in range(5)]
    assert [name for name, _ in taken if name == "odometry"] == ["odometry"] * 2
    assert taken[:4] == [("odometry", "o0"), ("detections", "d0"), ("odometry", "o1"),
                         ("detections", "d1")]


def test_take_waits_for_an_item_and_close_wakes_it_for_good():
    lanes = Lanes({"a": Limit(2)}, in_turn=True)
    got: list[object] = []
    waiter = threading.Thread(target=lambda: got.append(lanes.take(30.0)))
    waiter.start()
    lanes.put("a", "x")
    waiter.join(30.0)
    assert got == [("a", "x")]
    closer = threading.Thread(target=lambda: got.append(lanes.take(30.0)))
    closer.start()
    lanes.close()
    closer.join(30.0)
    assert got[-1] is None and not closer.is_alive()
    lanes.put("a", "y")
    assert lanes.take(0.0) is None


@pytest.mark.parametrize("limit", [Limit(0), Limit(1, bytes=0)])
def test_a_lane_holds_at_least_one_item_and_one_byte(limit: Limit):
    with pytest.raises(ValueError):
        Lanes({"a": limit}, in_turn=True)
