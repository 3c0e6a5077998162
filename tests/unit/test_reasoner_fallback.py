"""fallback_choice: the programmatic answer when the LLM gives none."""

from __future__ import annotations

import pytest

from services.reasoner.deciding import FallbackPolicy, fallback_choice
from shared.messages import Option

OPTIONS = (
    Option(index=0, label="continue"),
    Option(index=1, label="alternative landing site"),
    Option(index=2, label="Holding Zone"),
)
RANKS = FallbackPolicy(kind="rank", ranks={"holding zone": 0, "alternative landing site": 5})


def test_first_recovery_is_lowest_recovery_index() -> None:
    assert fallback_choice(OPTIONS, FallbackPolicy()) == 1


def test_first_recovery_ignores_order_and_gaps() -> None:
    opts = (Option(index=7, label="b"), Option(index=0, label="c"), Option(index=3, label="a"))
    assert fallback_choice(opts, FallbackPolicy()) == 3


@pytest.mark.parametrize("policy", [FallbackPolicy(), RANKS])
def test_only_continue_offered_gives_zero(policy: FallbackPolicy) -> None:
    assert fallback_choice((Option(index=0, label="continue"),), policy) == 0


@pytest.mark.parametrize("policy", [FallbackPolicy(), RANKS])
def test_empty_options_give_zero(policy: FallbackPolicy) -> None:
    assert fallback_choice((), policy) == 0


def test_rank_prefers_lowest_rank_case_insensitive() -> None:
    assert fallback_choice(OPTIONS, RANKS) == 2


def test_rank_matches_label_with_whitespace_and_case() -> None:
    policy = FallbackPolicy(kind="rank", ranks={"  ALTERNATIVE Landing Site ": -1})
    assert fallback_choice(OPTIONS, policy) == 1


def test_rank_unranked_options_come_last() -> None:
    policy = FallbackPolicy(kind="rank", ranks={"alternative landing site": 9})
    assert fallback_choice(OPTIONS, policy) == 1


def test_rank_nothing_ranked_falls_to_lowest_recovery_index() -> None:
    policy = FallbackPolicy(kind="rank", ranks={"unrelated": 0})
    assert fallback_choice(OPTIONS, policy) == 1


def test_rank_ties_go_to_lower_index() -> None:
    opts = (*OPTIONS, Option(index=3, label="holding zone"))
    assert fallback_choice(opts, RANKS) == 2


def test_rank_never_picks_continue_even_if_ranked_best() -> None:
    policy = FallbackPolicy(kind="rank", ranks={"continue": -100, "holding zone": 3})
    assert fallback_choice(OPTIONS, policy) == 2


def test_policy_is_frozen_and_copies_ranks() -> None:
    ranks = {"Holding Zone": 0}
    policy = FallbackPolicy(kind="rank", ranks=ranks)
    ranks["alternative landing site"] = -5
    assert fallback_choice(OPTIONS, policy) == 2
    with pytest.raises(TypeError):
        policy.ranks["x"] = 1  # type: ignore[index]


@pytest.mark.parametrize("kwargs", [{"kind": "random"}, {"kind": "rank", "ranks": {"a": 1.5}},
                                    {"kind": "rank", "ranks": {"a": True}}])
def test_policy_rejects_bad_values(kwargs: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        FallbackPolicy(**kwargs)  # type: ignore[arg-type]
