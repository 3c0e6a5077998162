"""The vehicle contract as a user meets it: the few lines of Python in
docs/architecture.md (section 3a), run as written, flown by ``aesop serve control`` over a
real Zenoh link; then stopped, which the loop must take as an unmonitored anomaly."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from shared import topics
from shared.bus import Bus
from shared.messages import Event, ReasonerRequest
from shared.process import ServiceProcess, free_port
from shared.settings import BusSettings
from tests.vehicles import NominalDetector
from tests.zenoh_peers import wait_until

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(180)]

ROOT = Path(__file__).resolve().parents[2]
ROBOT = "robot7"
WAIT_S = 30.0


def example() -> str:
    """The example vehicle, as the architecture document shows it."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    section = text[text.index("## 3a. The vehicle contract"):text.index("## 4. Messages")]
    (code,) = re.findall(r"```python\n(.*?)```", section, re.S)
    return code


@pytest.fixture
def control(tmp_path: Path) -> Iterator[tuple[ServiceProcess, str]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    port = free_port()
    env = {"AESOP_ZENOH_LISTEN": endpoint, "AESOP_ROBOT": ROBOT}
    with ServiceProcess(["serve", "control", "--port", str(port), "--scenario", "hardware"],
                        port=port, env=env, log_path=tmp_path / "control.log",
                        ready_timeout_s=90, unset=["AESOP_ADMIN_TOKEN"]) as proc:
        yield proc, endpoint


def test_the_documented_vehicle_is_flown_and_its_silence_is_an_anomaly(
        control: tuple[ServiceProcess, str], tmp_path: Path) -> None:
    proc, endpoint = control
    script = tmp_path / "my_vehicle.py"
    script.write_text(example())
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("AESOP_")},
           "AESOP_ROBOT": ROBOT, "AESOP_ZENOH_CONNECT": endpoint,
           "PYTHONPATH": str(ROOT)}
    with Bus.open(BusSettings(zenoh_connect=[endpoint]), "tester") as bus, \
            httpx.Client(base_url=proc.url, timeout=10) as http:
        events: list[Event] = []
        requests: list[ReasonerRequest] = []
        subscribers = [  # every one, in order (a Latest slot would keep only the newest)
            bus.session.declare_subscriber(topics.events(ROBOT), lambda sample: events.append(
                Event.decode(sample.payload.to_bytes()))),
            bus.session.declare_subscriber(topics.reasoner_request(ROBOT),
                                           lambda sample: requests.append(
                                               ReasonerRequest.decode(sample.payload.to_bytes())))]
        detector = NominalDetector(bus, ROBOT)
        vehicle = subprocess.Popen([sys.executable, str(script)], env=env,
                                   stdin=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            def flying() -> bool:
                body = http.get("/v1/state").json()
                state = body["state"]
                return (body["mode"] == "nominal" and state is not None
                        and state["x"][0] > -3.0 and body["vehicle"]["setpoints"] > 20)

            wait_until(flying, "the loop to fly the vehicle a metre toward the goal", WAIT_S)
            body = http.get("/v1/state").json()
            assert body["vehicle"]["fresh"] and body["vehicle"]["clock"] == "sync"
            assert body["vehicle"]["refused"] == 0 and body["vehicle"]["age_p50_ms"] < 50
            vehicle.kill()  # the vehicle stops talking mid-flight
            vehicle.wait(10)
            wait_until(lambda: any(e.kind == "state_stale" for e in events),
                       "the stale-state alarm", WAIT_S)
            wait_until(lambda: bool(requests), "a request about the vehicle", WAIT_S)
            assert "vehicle's state" in requests[0].observation.text
            assert 0 not in [o.index for o in requests[0].options]
            assert http.get("/v1/state").json()["mode"] in ("anomaly_pending", "recovering")
        finally:
            detector.close()
            for subscriber in subscribers:
                subscriber.undeclare()
            if vehicle.poll() is None:
                vehicle.kill()
            vehicle.wait(10)
            assert vehicle.stderr is not None
            err = vehicle.stderr.read().decode(errors="replace")
            assert "Traceback" not in err, err
