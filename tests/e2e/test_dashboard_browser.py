"""The dashboard page in real headless Chromium (Debian's, driven by Playwright) while a
scripted demo flight is published over real Zenoh to a real `aesop serve dashboard`.

Screenshots go to the test's tmp directory and, when ``AESOP_SCREENSHOT_DIR`` is set,
there too (the README shows ``dashboard-demo.png`` of ``test_dashboard_demo.py``).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from playwright.sync_api import Browser, expect

from shared import topics
from shared.bus import Bus
from shared.messages import Event
from shared.process import ServiceProcess, free_port
from shared.settings import BusSettings
from tests.e2e.browser import canvas_count, screenshot
from tests.e2e.demo_flight import (
    DECISION_AT,
    REGIONS,
    REQUEST_AT,
    TICKS,
    Flight,
    regions,
    wait_following,
)
from tests.zenoh_peers import wait_until

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

ROBOT = "e2e"
OTHER = "e2e-2"  # another robot of the fleet, seen in the overview
WAIT_MS = 15_000


class Live:
    def __init__(self, proc: ServiceProcess, bus: Bus) -> None:
        self.proc, self.bus = proc, bus


@pytest.fixture
def live(tmp_path: Path) -> Iterator[Live]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    port = free_port()
    env = {"AESOP_ZENOH_LISTEN": endpoint, "AESOP_ROBOT": ROBOT}
    proc = ServiceProcess(["serve", "dashboard", "--port", str(port)], port=port, env=env,
                          log_path=tmp_path / "dashboard.log", ready_timeout_s=60,
                          unset=["AESOP_ADMIN_TOKEN"])
    with proc, Bus.open(BusSettings(zenoh_connect=[endpoint]), "control") as bus:
        wait_following(bus, ROBOT, proc.url)
        yield Live(proc, bus)


def test_the_page_draws_the_live_flight_and_shows_the_decision(
        browser: Browser, live: Live, tmp_path: Path) -> None:
    page = browser.new_page(viewport={"width": 1440, "height": 700})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("console", lambda msg: errors.append(msg.text) if msg.type == "error" else None)
    page.goto(live.proc.url)
    expect(page.locator("#status")).to_have_attribute("data-state", "connected",
                                                      timeout=WAIT_MS)
    expect(page.locator('#services [data-service="control"]')).to_have_attribute(
        "data-alive", "true", timeout=WAIT_MS)
    live.bus.publish(topics.regions(ROBOT), regions(ROBOT))  # as the control service starts
    expect(page.locator("#top")).to_have_attribute("data-regions", str(len(REGIONS)),
                                                   timeout=WAIT_MS)

    flight = Flight(live.bus, ROBOT)
    flight.fly(until=DECISION_AT)  # nominal, then the anomaly and the request to the reasoner
    page.wait_for_function(f"document.querySelector('#top').dataset.points >= {DECISION_AT}",
                           timeout=WAIT_MS)
    assert canvas_count(page, "top", "branches") == len(REGIONS)  # the recovery tree
    assert canvas_count(page, "side", "points") == DECISION_AT
    assert canvas_count(page, "score", "anomalies") == DECISION_AT - REQUEST_AT + 1
    expect(page.locator("#mode")).to_have_attribute("data-mode", "anomaly_pending")
    request = page.locator("#requests li").first
    expect(request).to_have_attribute("data-status", re.compile("pending|expired"))
    expect(request.locator(".countdown")).to_have_text(re.compile(r"K in \d+\.\d s|past K"))
    # the fleet overview: this robot waits on the reasoner; another robot raised an alarm
    live.bus.publish(topics.event(OTHER, "control"), Event(
        robot=OTHER, source="control", kind="state_stale", severity="alarm", message="late"))
    mine = page.locator(f'#fleet-rows tr[data-robot="{ROBOT}"]')
    expect(mine.locator("td").nth(3)).to_have_text(re.compile(r"K in \d+\.\d s|past K"),
                                                   timeout=WAIT_MS)
    expect(mine).to_have_attribute("data-mine", "true")
    expect(page.locator(f'#fleet-rows tr[data-robot="{OTHER}"] td').nth(5)).to_have_text(
        "1: control/state_stale", timeout=WAIT_MS)
    screenshot(page, tmp_path, "dashboard-pending.png")

    flight.fly(until=TICKS)  # the decision, then the recovery toward the rooftop
    decision = page.locator("#decisions li").first
    expect(decision).to_have_attribute("data-source", "llm", timeout=WAIT_MS)
    expect(decision).to_contain_text("y=3 rooftop")
    expect(request).to_have_attribute("data-status", "answered")
    expect(request.locator(".countdown")).to_have_text("y=3 (llm)")
    page.wait_for_function(f"document.querySelector('#top').dataset.points >= {TICKS}",
                           timeout=WAIT_MS)
    expect(page.locator("#mode")).to_have_attribute("data-mode", "recovering")
    assert canvas_count(page, "top", "branches") == 1  # committed: the chosen branch
    expect(page.locator('#events li[data-kind="mode_change"]')).to_have_count(2)
    expect(mine.locator("td").nth(4)).to_have_text("y=3 rooftop (llm)", timeout=WAIT_MS)
    expect(mine.locator("td").nth(3)).to_have_text("–")  # answered: waiting for nothing
    shot = screenshot(page, tmp_path, "dashboard.png")
    assert shot.stat().st_size > 10_000
    assert errors == []


def test_the_page_reconnects_and_redraws_from_the_snapshot(
        browser: Browser, live: Live, tmp_path: Path) -> None:
    # a quick flight, but not one burst: Zenoh drops best-effort puts past a full queue
    Flight(live.bus, ROBOT).fly(period_s=0.002)
    wait_until(lambda: len(httpx.get(f"{live.proc.url}/v1/snapshot").json()["trail"]) >= TICKS,
               "the service to hold the whole flight", WAIT_MS / 1000)
    page = browser.new_page()
    page.goto(live.proc.url)
    # a late page draws at once from the snapshot
    page.wait_for_function(f"document.querySelector('#top').dataset.points >= {TICKS}",
                           timeout=WAIT_MS)
    expect(page.locator("#decisions li")).to_have_count(1)
    live.proc.stop()
    expect(page.locator("#status")).to_have_attribute(
        "data-state", re.compile("disconnected|connecting"), timeout=WAIT_MS)
    live.proc.start()
    expect(page.locator("#status")).to_have_attribute("data-state", "connected",
                                                      timeout=WAIT_MS)
    # the new service knows nothing yet: the page redrew from its (empty) snapshot
    expect(page.locator("#top")).to_have_attribute("data-points", "0")
    screenshot(page, tmp_path, "dashboard-reconnected.png")


def test_the_page_names_detector_drift_until_it_is_cleared(
        browser: Browser, live: Live, tmp_path: Path) -> None:
    from shared.messages import Event

    page = browser.new_page(viewport={"width": 1440, "height": 700})
    page.goto(live.proc.url)
    expect(page.locator("#status")).to_have_attribute("data-state", "connected",
                                                      timeout=WAIT_MS)
    expect(page.locator("#drift")).to_be_hidden()
    key = topics.event(ROBOT, "embedding")
    live.bus.publish(key, Event(
        robot=ROBOT, source="embedding", kind="drift", severity="warning",
        message="detector drift: the detector may be seeing new wording",
        data={"flagged": 15, "seen": 15, "phrases": "one crimson carton; two skids"}))
    drift = page.locator("#drift")
    expect(drift).to_be_visible(timeout=WAIT_MS)
    expect(drift).to_contain_text("15/15 flagged · one crimson carton; two skids")
    expect(page.locator('#events li[data-kind="drift"]')).to_have_count(1)
    screenshot(page, tmp_path, "dashboard-drift.png")
    live.bus.publish(key, Event(robot=ROBOT, source="embedding", kind="drift_cleared",
                                message="detector drift cleared"))
    expect(drift).to_be_hidden(timeout=WAIT_MS)


def test_with_a_token_the_page_reads_by_a_session_of_its_port_until_logout(
        browser: Browser, tmp_path: Path) -> None:
    """Issue 43, finding 8, in a real browser: the cookie ``/?token=`` leaves names a
    server-side session after the dashboard's port, expires, and ends on logout (a copy of
    it, as another app on the host would have received, then opens nothing)."""
    token = "e2e-dashboard-session-token"
    port = free_port()
    env = {"AESOP_ZENOH_LISTEN": f"tcp/127.0.0.1:{free_port()}", "AESOP_ROBOT": ROBOT,
           "AESOP_ADMIN_TOKEN": token}
    with ServiceProcess(["serve", "dashboard", "--port", str(port)], port=port, env=env,
                        log_path=tmp_path / "dashboard.log", ready_timeout_s=60,
                        unset=["AESOP_ADMIN_TOKEN_FILE"]) as proc:
        context = browser.new_context()
        page = context.new_page()
        page.goto(f"{proc.url}/?token={token}")
        expect(page).to_have_url(f"{proc.url}/")  # the address bar lost the token
        status = page.locator("#status")
        expect(status).to_have_attribute("data-state", "connected", timeout=WAIT_MS)
        [cookie] = context.cookies()
        assert cookie["name"] == f"aesop_dashboard_{port}" and token not in cookie["value"]
        assert cookie["httpOnly"] and cookie["sameSite"] == "Strict" and cookie["path"] == "/"
        assert cookie["expires"] > 0  # not a cookie for as long as the browser runs
        copy = {"Cookie": f"{cookie['name']}={cookie['value']}"}
        assert httpx.get(f"{proc.url}/v1/snapshot", headers=copy).status_code == 200
        page.locator("#logout").click()
        # the page comes back without a session: its stream is refused (the guard's
        # refusal before the accept reaches a browser as 1006, not 1008)
        expect(status).to_have_attribute("data-state", re.compile("disconnected|unauthorized"),
                                         timeout=WAIT_MS)
        expect(page.locator("#logout")).to_be_hidden()
        assert context.cookies() == []
        assert httpx.get(f"{proc.url}/v1/snapshot", headers=copy).status_code == 401
        context.close()
