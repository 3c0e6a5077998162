"""The dashboard page in real headless Chromium (Debian's, driven by Playwright) while the
real stack flies one of `aesop demo`'s scenarios.

The stack is the one `aesop demo --random-ports` brings up (:mod:`tools.stack.up`: a
Zenoh hub, the fake LLM, the vector cache, the reasoner, the control loop and the
dashboard, as processes); the cache is built and calibrated and scenario 2a (another
quadrotor on the red box) is flown by the demo's own code
(:func:`tools.demo.flights.fly_scenarios`) while the page watches. The page must stay
connected, draw the flown trajectory and show the reasoner's decision: the LLM's choice
of the alternative landing site, beside the detection the detector named. Then scenario 3
(a keyboard on the ground) is flown: the LLM answers "continue" and the keyboard's scene
shows as a proposal to the cache, pending review.

The screenshot (after both) goes to the test's tmp directory and, when ``AESOP_SCREENSHOT_DIR`` is
set, there too (``dashboard-demo.png``).
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from playwright.sync_api import Browser, Page, expect

from tests.demo_stack import demo_stack
from tests.e2e.browser import canvas_count, screenshot
from tools.demo.flights import demo_scenario, fly_scenarios
from tools.stack.up import StackPlan

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(540)]

SCENARIO = "2a"  # another quadrotor on the red box: land on the blue box instead
KEYBOARD = "3"  # an unseen keyboard on the ground: continue
WAIT_MS = 30_000
FLIGHT_TIMEOUT_S = 300  # the cache (385 texts, a CPU embedder), calibration, a 12 s flight


TOKEN = secrets.token_urlsafe(24)  # the stack's admin token


@pytest.fixture
def stack(tmp_path: Path) -> Iterator[StackPlan]:
    with demo_stack(tmp_path, TOKEN) as plan:
        yield plan


def fly(page: Page, stack: StackPlan, scenario: str
        ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The demo's own code flies the scenario, in a thread: meanwhile Playwright keeps
    taking the page's events (and a failure of the flight ends the wait at once)."""
    with ThreadPoolExecutor(1) as pool:
        flying = pool.submit(fly_scenarios, stack, [scenario])
        deadline = time.monotonic() + FLIGHT_TIMEOUT_S
        while not flying.done() and time.monotonic() < deadline:
            page.wait_for_timeout(500)
        return flying.result(timeout=1)


def test_the_page_follows_a_real_demo_scenario(browser: Browser, stack: StackPlan,
                                               tmp_path: Path) -> None:
    demo = demo_scenario(SCENARIO)
    url = stack.url("dashboard")
    assert url is not None
    page = browser.new_page(viewport={"width": 1440, "height": 700})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("console", lambda msg: errors.append(msg.text) if msg.type == "error" else None)
    page.goto(f"{url}/?token={TOKEN}")  # as `aesop up` says: the token becomes a cookie
    assert page.url == f"{url}/"  # and leaves the address bar
    expect(page.locator("#status")).to_have_attribute("data-state", "connected",
                                                      timeout=WAIT_MS)
    expect(page.locator('#services [data-service="control"]')).to_have_attribute(
        "data-alive", "true", timeout=WAIT_MS)
    expect(page.locator("#top")).to_have_attribute("data-regions", "2", timeout=WAIT_MS)

    result, flights = fly(page, stack, SCENARIO)

    [row] = result["scenarios"]
    assert row["outcome"] == "ok", row  # landed on the blue box, no constraint violated
    assert (row["decision"], row["decision_source"]) == ("alternative landing site", "llm")
    expect(page.locator("#status")).to_have_attribute("data-state", "connected")
    # the flight's request (the control loop may have asked before, while the cache was
    # being built and no verdict came: the stale-detector fail-safe) and its answer
    [seen] = demo.anomalies
    request = page.locator("#requests li").filter(has_text=seen).first
    expect(request).to_have_attribute("data-status", "answered", timeout=WAIT_MS)
    expect(request.locator(".countdown")).to_have_text("y=1 (llm)")
    # the detector named the odd detection, beside its nearest nominal one
    expect(request.locator(".unusual")).to_contain_text(
        f"{seen} — nearest nominal: a quadrotor on the ground")
    decision = page.locator('#decisions li[data-source="llm"][data-choice="1"]').first
    expect(decision.locator(".choice")).to_have_text("y=1 alternative landing site")
    flown = len(flights[demo.name])
    assert flown >= 50  # 12 s at 5 Hz
    page.wait_for_function(  # the whole flight is drawn (the dashboard saw its reset)
        f"document.querySelector('#top').dataset.points >= {flown - 2}", timeout=WAIT_MS)
    assert canvas_count(page, "side", "points") >= flown - 2
    assert canvas_count(page, "score", "anomalies") >= 1
    # the keyboard: the LLM lets it pass, and the scene is proposed to the cache
    keyboard, _ = fly(page, stack, KEYBOARD)
    [row] = keyboard["scenarios"]
    assert row["outcome"] == "ok" and row["decision"] == "continue", row
    proposal = page.locator("#proposals li").first
    expect(proposal).to_have_attribute("data-state", "pending", timeout=WAIT_MS)
    expect(proposal).to_contain_text("a keyboard on the ground")
    # (not necessarily the newest request: once the flight is over the camera is quiet,
    # and the loop may already have asked about the silence)
    named = page.locator("#requests li .unusual").filter(has_text="a keyboard on the ground")
    expect(named.first).to_contain_text("a keyboard on the ground — nearest nominal:")
    # reviewed on the page: selected and accepted (the page asks for the admin token; the
    # dashboard forwards the batch to the embedding service, whose event comes back)
    ident = proposal.get_attribute("data-id")
    page.on("dialog", lambda dialog: dialog.accept(TOKEN))
    proposal.locator("input[type=checkbox]").check()
    page.locator("#accept-selected").click()
    expect(page.locator("#review-status")).to_contain_text("1 accepted on", timeout=WAIT_MS)
    expect(page.locator(f'#proposals li[data-id="{ident}"]')).to_have_attribute(
        "data-state", "accepted", timeout=WAIT_MS)
    expect(page.locator("#accept-selected")).to_be_disabled()
    shot = screenshot(page, tmp_path, "dashboard-demo.png")
    assert shot.stat().st_size > 10_000
    assert errors == []
