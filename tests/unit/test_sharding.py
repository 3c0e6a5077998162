"""Rendezvous hashing of robots over detector replicas (services/embedding/fleet/sharding.py) and
the replica set's bookkeeping (services/embedding/fleet/replicas.py)."""

from __future__ import annotations

import pytest

from services.embedding.fleet.replicas import Replicas, replica_key
from services.embedding.fleet.sharding import assignment, owner

ROBOTS = [f"robot{i}" for i in range(1000)]


def test_every_replica_computes_the_same_owner_whatever_the_order() -> None:
    for robot in ROBOTS[:50]:
        assert owner(robot, ["a", "b", "c"]) == owner(robot, ["c", "a", "b"])
    assert owner("r0", []) is None
    assert owner("r0", ["only"]) == "only"


def test_robots_spread_evenly_and_only_a_leaving_replicas_robots_move() -> None:
    four = assignment(ROBOTS, ["a", "b", "c", "d"])
    assert sorted(sum(four.values(), [])) == sorted(ROBOTS)
    assert all(200 <= len(mine) <= 300 for mine in four.values()), \
        {r: len(m) for r, m in four.items()}
    three = assignment(ROBOTS, ["a", "b", "c"])
    for replica in ("a", "b", "c"):  # d's robots went elsewhere, nobody else's moved
        assert set(four[replica]) <= set(three[replica])
    moved = set(ROBOTS) - set(four["a"]) - set(four["b"]) - set(four["c"])
    assert moved == set(four["d"])
    # a replica joining takes robots only, about a fifth of them
    five = assignment(ROBOTS, ["a", "b", "c", "d", "e"])
    assert all(set(five[r]) <= set(four[r]) for r in "abcd")
    assert 150 <= len(five["e"]) <= 250


def test_a_replica_owns_what_the_live_set_gives_it_and_counts_itself() -> None:
    changes: list[frozenset[str]] = []
    me = Replicas("a", on_change=changes.append)
    assert me.live == {"a"} and all(me.owns(r) for r in ROBOTS[:20])  # alone: every robot
    me.seen("b", True)
    me.seen("b", True)  # told twice: one change
    me.seen("a", False)  # its own token is never taken away
    assert me.live == {"a", "b"} and changes == [frozenset({"a", "b"})]
    assert [me.owns(r) for r in ROBOTS[:50]] == [owner(r, ["a", "b"]) == "a"
                                                  for r in ROBOTS[:50]]
    me.seen("b", False)
    assert me.live == {"a"} and len(changes) == 2
    assert replica_key("a") == "aesop/health/embedding/a"


@pytest.mark.parametrize("name", ["", "a/b", "a*", " a", "x$y"])
def test_a_replica_name_is_one_key_chunk(name: str) -> None:
    with pytest.raises(ValueError, match="one key chunk"):
        Replicas(name)
