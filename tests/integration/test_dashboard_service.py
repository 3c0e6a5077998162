"""`aesop serve dashboard` as a real process on a real Zenoh link: what is published on the
robot's topics comes back on /ws and in /v1/snapshot, with the regions from the control
service, the services' liveliness, and the ops routes."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from websockets.sync.client import ClientConnection, connect

from services.dashboard.api import STATIC
from shared import topics
from shared.bus import Bus
from shared.messages import Event
from shared.process import ServiceProcess, free_port
from shared.settings import BusSettings
from tests.e2e.demo_flight import GOAL, REGIONS, TICKS, fly, wait_following
from tests.zenoh_peers import wait_until

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

ROBOT = "dash1"
RECV_S = 10.0
# a whole scripted flight: 60 ticks of several messages each, published 5 ms apart and
# awaited for longer than one message: published in one burst, beside CI's other worker, it
# was not whole within 10 s once (2026-11-29; whether messages were dropped or late, not found)
FLIGHT_PERIOD_S, FLIGHT_S = 0.005, 30.0


class Dashboard:
    def __init__(self, proc: ServiceProcess, bus: Bus, endpoint: str) -> None:
        self.proc, self.bus, self.endpoint = proc, bus, endpoint
        self.http = httpx.Client(base_url=proc.url, timeout=10)

    def ws(self) -> ClientConnection:
        return connect(f"ws://127.0.0.1:{self.proc.port}/ws", open_timeout=10)

    def snapshot(self) -> dict[str, Any]:
        return self.http.get("/v1/snapshot").json()


@pytest.fixture(scope="module")
def dashboard(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Dashboard]:
    tmp = tmp_path_factory.mktemp("dashboard")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    port = free_port()
    env = {"AESOP_ZENOH_LISTEN": endpoint, "AESOP_ROBOT": ROBOT,
           "AESOP_DASHBOARD_LIMITS__CLIENT_QUEUE": "1000",
           # nothing listens there: a review cannot reach the embedding service
           "AESOP_DASHBOARD_EMBEDDING_URL": f"http://127.0.0.1:{free_port()}"}
    proc = ServiceProcess(["serve", "dashboard", "--port", str(port)], port=port, env=env,
                          log_path=tmp / "dashboard.log", ready_timeout_s=60,
                          unset=["AESOP_ADMIN_TOKEN"])
    with proc, Bus.open(BusSettings(zenoh_connect=[endpoint]), "tester") as bus:
        wait_following(bus, ROBOT, proc.url)
        dashboard = Dashboard(proc, bus, endpoint)
        try:
            yield dashboard
        finally:
            dashboard.http.close()


def read_until(ws: ClientConnection, wanted: set[str]) -> dict[str, dict[str, Any]]:
    """Items off the socket until one of each wanted kind has come; the last of each kind."""
    got: dict[str, dict[str, Any]] = {}
    while not wanted <= got.keys():
        item = json.loads(ws.recv(timeout=RECV_S))
        got[item["kind"]] = item
    return got


def test_a_page_gets_a_snapshot_then_every_kind_of_message(dashboard: Dashboard) -> None:
    with dashboard.ws() as ws:
        first = json.loads(ws.recv(timeout=RECV_S))
        assert first["kind"] == "snapshot" and first["message"]["robot"] == ROBOT
        assert first["message"]["services"]["dashboard"] is True
        # a tick apart, as a real flight is: keys arrive on separate subscriptions, and a
        # decision that overtook its request would have no label to show
        fly(dashboard.bus, ROBOT, period_s=0.01)
        got = read_until(ws, {"state", "plan", "anomaly", "request", "decision", "event"})
    assert got["state"]["topic"] == topics.state(ROBOT)
    state = got["state"]["message"]
    assert state["robot"] == ROBOT and len(state["x"]) == 12 and len(state["u"]) == 4
    plan = got["plan"]["message"]
    assert got["plan"]["topic"] == topics.plan(ROBOT) and (plan["nominal"] or plan["recovery"])
    assert got["anomaly"]["message"]["threshold"] == -0.7
    assert got["request"]["message"]["deadline_s"] == 1.5
    decision = got["decision"]
    assert decision["topic"] == topics.reasoner_decision(ROBOT)
    assert decision["message"]["source"] == "llm" and decision["message"]["choice"] == 3
    assert decision["label"] == "rooftop"
    assert got["event"]["message"]["kind"] == "mode_change"
    assert all(isinstance(item["received"], float) for item in got.values())


def test_the_snapshot_aggregates_the_flight_regions_and_services(dashboard: Dashboard) -> None:
    # the dashboard may still show an earlier test's flight, and each key has its own
    # subscription (a decision may be in while the states after it are on their way):
    # wait until every message of this flight has been counted, not for its middle
    before = dashboard.snapshot()["counts"]
    fly(dashboard.bus, ROBOT, period_s=FLIGHT_PERIOD_S)

    def arrived() -> bool:
        counts = dashboard.snapshot()["counts"]
        return all(counts.get(kind, 0) - before.get(kind, 0) >= n for kind, n in
                   (("state", TICKS), ("regions", TICKS // 10), ("decision", 1)))

    wait_until(arrived, "the whole flight and its regions", FLIGHT_S)
    snap = dashboard.snapshot()
    assert snap["trail"] and snap["trail"][-1][4] == "recovering"
    assert snap["state"]["chosen"] == 3
    assert snap["plan"]["status"] == "solved"
    assert any(s["is_anomaly"] for s in snap["scores"])
    assert any(not s["is_anomaly"] for s in snap["scores"])
    assert snap["decisions"][-1]["label"] == "rooftop"
    assert snap["requests"][-1]["request_id"] == snap["decisions"][-1]["request_id"]
    assert snap["goal"] == list(GOAL) and snap["regions"] == REGIONS
    assert snap["services"]["tester"] is True and snap["services"]["dashboard"] is True


def test_every_page_sees_services_come_and_go(dashboard: Dashboard) -> None:
    with dashboard.ws() as one, dashboard.ws() as two:
        for ws in (one, two):
            assert json.loads(ws.recv(timeout=RECV_S))["kind"] == "snapshot"
        with Bus.open(BusSettings(zenoh_connect=[dashboard.endpoint]), "visitor"):
            for ws in (one, two):
                assert health_of(ws, "visitor") is True
        for ws in (one, two):
            assert health_of(ws, "visitor") is False
    assert dashboard.snapshot()["services"]["visitor"] is False


def health_of(ws: ClientConnection, service: str) -> bool:
    while True:
        item = json.loads(ws.recv(timeout=RECV_S))
        if item["kind"] == "health" and item["message"]["service"] == service:
            assert item["topic"] == topics.health(service)
            return bool(item["message"]["alive"])


def test_page_static_files_and_ops_routes(dashboard: Dashboard) -> None:
    http = dashboard.http
    page = http.get("/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    for asset in ("/static/app.js", "/static/style.css"):
        assert asset in page.text
        assert http.get(asset).status_code == 200
    # nothing from the network: these machines are offline
    for path in Path(STATIC).iterdir():
        assert not re.search(r"(https?:)?//[a-z0-9.-]+\.[a-z]{2,}", path.read_text()), path.name
    assert http.get("/healthz").json() == {"status": "ok"}
    assert http.get("/readyz").json() == {"status": "ready"}
    metrics = http.get("/metrics").text
    assert 'aesop_dashboard_updates_total{kind="state"}' in metrics
    assert "aesop_dashboard_clients" in metrics



def drift_event(kind: str = "drift") -> Event:
    """What the embedding worker publishes when the robot's verdicts drift (or stop)."""
    return Event(robot=ROBOT, source="embedding", kind=kind,
                 severity="warning" if kind == "drift" else "info",
                 message="detector drift: 15 of the last 15 observations flagged where the "
                         "calibration allows 5%; the detector may be seeing new wording",
                 data={"cache": "default", "flagged": 15, "seen": 15, "expected_rate": 0.05,
                       "p_value": 3e-20, "phrases": "one crimson carton; two skids"})


def test_a_drift_event_is_shown_until_it_is_cleared(dashboard: Dashboard) -> None:
    key = topics.event(ROBOT, "embedding")
    dashboard.bus.publish(key, drift_event())
    wait_until(lambda: dashboard.snapshot()["drift"] is not None, "the drift", RECV_S)
    snap = dashboard.snapshot()
    assert snap["drift"]["data"]["phrases"] == "one crimson carton; two skids"
    assert "new wording" in snap["drift"]["message"]
    assert any(e["kind"] == "drift" and e["severity"] == "warning" for e in snap["events"])
    dashboard.bus.publish(key, drift_event("drift_cleared"))
    wait_until(lambda: dashboard.snapshot()["drift"] is None, "the drift cleared", RECV_S)


@pytest.mark.parametrize(("path", "body", "status", "field"), [
    ("/v1/proposals/accept", {"cache": "default", "ids": ["rec-1"]}, 502, "embedding"),
    ("/v1/proposals/accept", {"cache": "default", "ids": []}, 422, "ids"),
    ("/v1/proposals/accept", {"cache": "../caches", "ids": ["rec-1"]}, 422, "cache"),
    ("/v1/proposals/approve", {"cache": "default", "ids": ["rec-1"]}, 422, "decision"),
])
def test_a_review_the_embedding_service_cannot_take_is_answered_naming_why(
        dashboard: Dashboard, path: str, body: dict[str, Any], status: int,
        field: str) -> None:
    """The batch review is forwarded to the embedding service (the e2e demo test accepts a
    real proposal through the page); here none is listening, or the review is malformed."""
    assert dashboard.snapshot()["review_token"] is False  # this dashboard has no token
    r = dashboard.http.post(path, json=body)
    assert r.status_code == status, r.text
    assert r.json()["error"]["field"] == field


def test_the_fleet_overview_has_a_line_for_every_robot(dashboard: Dashboard) -> None:
    """Every robot on the bus, not only the one the page draws: its mode, newest verdict,
    the request it waits on until a decision answers it, its last decision, its alarms."""
    other = "dash2"
    fly(dashboard.bus, ROBOT, period_s=FLIGHT_PERIOD_S)
    dashboard.bus.publish(topics.event(other, "control"), Event(
        robot=other, source="control", kind="verdict_stale", severity="alarm",
        message="no verdict for 0.6 s"))

    def lines() -> dict[str, dict[str, Any]]:
        got = dashboard.http.get("/v1/fleet")
        assert got.status_code == 200, got.text
        return {r["robot"]: r for r in got.json()["robots"]}

    wait_until(lambda: other in lines() and lines()[ROBOT]["mode"] == "recovering"
               and lines()[ROBOT]["decision"] is not None, "both robots in the overview",
               FLIGHT_S)
    mine, theirs = lines()[ROBOT], lines()[other]
    assert mine["decision"]["label"] == "rooftop" and mine["decision"]["source"] == "llm"
    assert mine["pending"] is None  # answered
    assert mine["verdict"]["threshold"] == -0.7 and len(mine["position"]) == 3
    assert theirs["alarms"] == 1 and theirs["last_alarm"]["kind"] == "verdict_stale"
    assert theirs["mode"] is None  # nothing but its alarm heard yet
    assert dashboard.http.get("/v1/fleet").json()["robot"] == ROBOT
