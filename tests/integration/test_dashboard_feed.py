"""The dashboard's feed survives what others declare on the bus (issue 14: one liveliness
token with a name the topics refuse ended the feed for good, while /readyz stayed 200)."""

from __future__ import annotations

import asyncio

import pytest

from services.dashboard.feed import Update, follow
from shared.bus import Bus
from tests.zenoh_peers import async_wait_until

pytestmark = pytest.mark.timeout(60)


async def test_a_bad_liveliness_name_is_dropped_and_the_feed_goes_on(
        listener: Bus, connector: Bus) -> None:
    seen: list[Update] = []
    feed = asyncio.create_task(follow(listener.session, "robot0", seen.append))
    bad = connector.session.liveliness().declare_token("aesop/health/bad name!")
    good = connector.session.liveliness().declare_token("aesop/health/late-service")
    try:
        await async_wait_until(
            lambda: any(u.kind == "health" and u.message["service"] == "late-service"
                        for u in seen), "the good token")
        assert not feed.done(), feed
        assert not [u for u in seen if "bad" in u.topic]
    finally:
        bad.undeclare()
        good.undeclare()
        feed.cancel()
        await asyncio.gather(feed, return_exceptions=True)
