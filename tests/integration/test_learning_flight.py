"""The cache learns from the slow reasoner, end to end over Zenoh and REST: the demo's
keyboard scenario flown twice by the whole stack (router, embedding, reasoner with the
fake LLM server, control) with the detector cache's proposal policy ``auto``. The first
flight flags the keyboard, the LLM answers "continue", the scene becomes a nominal
experience; the second flight flies past it without a flag."""

from __future__ import annotations

import asyncio
import secrets
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.embedding.client import EmbeddingClient
from tests.demo_stack import demo_stack
from tools.demo.flights import fly_scenarios
from tools.stack.up import DETECTOR_CACHE, StackPlan

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(600)]

TOKEN = secrets.token_urlsafe(24)
KEYBOARD = "3-keyboard-on-ground"


@pytest.fixture
def stack(tmp_path: Path) -> Iterator[StackPlan]:
    with demo_stack(tmp_path, TOKEN) as plan:
        yield plan


async def learn_automatically(url: str) -> None:
    async with EmbeddingClient(url, token=TOKEN) as client:
        info = await client.create_cache(DETECTOR_CACHE, k=1, proposals="auto")
        assert info.proposals == "auto" and info.size == 0


async def proposals(url: str) -> list[tuple[str, str, str]]:
    async with EmbeddingClient(url, token=TOKEN) as client:
        return [(p.id, p.state, p.text) for p in (await client.proposals(DETECTOR_CACHE)).proposals]


def test_the_keyboard_is_flagged_the_first_time_and_nominal_the_second(
        stack: StackPlan) -> None:
    url = stack.url("embedding")
    assert url is not None
    asyncio.run(learn_automatically(url))

    first, _ = fly_scenarios(stack, [KEYBOARD])
    [row] = first["scenarios"]
    assert row["outcome"] == "ok", row  # flagged, the LLM said continue, landed on the red box
    assert (row["decision"], row["decision_source"]) == ("continue", "llm")
    assert row["anomalous_verdicts"] >= 1
    [(ident, state, text)] = asyncio.run(proposals(url))
    assert state == "accepted" and "a keyboard on the ground" in text.splitlines()

    second, _ = fly_scenarios(stack, [KEYBOARD])  # the same cache, recalibrated
    [again] = second["scenarios"]
    assert again["anomalous_verdicts"] == 0 and again["reasoner_requests"] == 0, again
    assert again["ended_in"] == "red-box" and again["constraint_violations"] == 0
    assert [i for i, _, _ in asyncio.run(proposals(url))] == [ident]
