"""A ROS 2 robot flies the hardware scenario through the bridge (issue 29), on the whole
stack as processes (``aesop up --ros2 deploy/ros2/quadrotor.yaml``): the router enforces
the ``ros2`` user's ACL, and the robot is a plain zenoh-python session speaking rmw_zenoh's
wire format (:mod:`tests.ros2_robot`), no ROS installed.

Scenario 2a: another quadrotor on the red box. The robot's camera sees it near the box,
the detector flags it, the fake LLM answers "alternative landing site" and the robot must
end on the blue box, having flown only on the set-points it read from its ROS topic.
"""

from __future__ import annotations

import asyncio
import json
import secrets
from pathlib import Path

import numpy as np
import pytest

from services.control.core.scenario import load_scenario
from services.embedding.client import EmbeddingClient
from services.ros2.config import load_config
from shared.settings import BusSettings
from tests.demo_stack import running_stack
from tests.ros2_robot import RosRobot
from tools.demo.flights import demo_scenario
from tools.demo.report import ended_in
from tools.scenes.hardware import build_scene_cache
from tools.stack.up import DETECTOR_CACHE, hardware_scenario

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(600)]

TOKEN = secrets.token_urlsafe(24)
QUADROTOR = Path(__file__).resolve().parents[2] / "deploy" / "ros2" / "quadrotor.yaml"
SCENE = load_scenario(hardware_scenario())
FLIGHT_S = 28.0  # from the first set-point: the way in, the anomaly, T = 10 s, at rest


async def build_cache(url: str) -> None:
    async with EmbeddingClient(url, token=TOKEN, timeout_s=120) as client:
        await build_scene_cache(client, DETECTOR_CACHE, say=lambda _: None)


def test_a_ros2_robot_flies_the_hardware_scenario_through_the_bridge(tmp_path: Path) -> None:
    config = load_config(QUADROTOR)
    demo = demo_scenario("2a-quadrotor-on-red-box")
    x0 = np.zeros(12)
    x0[0:3] = SCENE.start_center
    with running_stack(tmp_path, TOKEN, ros2=QUADROTOR) as up:
        url = up.plan.url("embedding")
        assert url is not None and up.plan.url("sim") is None  # no simulated vehicle
        asyncio.run(build_cache(url))
        # the robot joins as its rmw_zenoh nodes would: with the session config aesop up wrote
        session = BusSettings(zenoh_config=up.plan.ros2_session)
        with RosRobot(session, config, SCENE, demo, x0) as robot:
            robot.until_flown(FLIGHT_S)
            truth, heard = robot.truth, robot.heard
    said = json.dumps(heard.strings, default=str)  # all the robot read, if it fails
    assert ended_in(truth, SCENE) == "blue-box", (truth[0:3], said)
    # the decision the flight ended with; an earlier one answers an anomaly the loop raised
    # itself for a late state or verdict (a loaded machine), which it must
    decisions = heard.strings.get("decision", [])
    stale = [a for a in heard.strings.get("alarms", []) if a["kind"].endswith("_stale")]
    assert decisions and decisions[-1]["label"] == "alternative landing site", said
    assert len(decisions) <= 1 + len(stale), said
    modes = [m["mode"] for m in heard.strings.get("mode", []) if m["mode"] != "waiting"]
    assert modes[0] == "nominal" and "anomaly_pending" in modes and modes[-1] == "recovering", \
        said
    assert heard.setpoints > 15 * 20  # the 20 Hz loop's, for most of the flight
    assert set(heard.attachments) == {33}  # rmw_zenoh's, on every sample the bridge sent
