"""A ROS 2 robot as rmw_zenoh robots run (issue 41): its nodes keep rmw_zenoh's default
session config, untouched but for the router's port (what ``ZENOH_CONFIG_OVERRIDE`` would
change), and reach the robot's own router (``aesop up --role robot --ros2``), which plays
rmw_zenohd: the robot's whole graph flows there, unmapped topics included; the bridge runs
on the robot, and only the stack's keys cross to the server (``aesop up --role server``)
over mutual TLS. Scenario 2a flown through it ends on the blue box.

The robot is a plain zenoh-python session speaking rmw_zenoh's wire format
(:mod:`tests.ros2_robot`), no ROS installed."""

from __future__ import annotations

import asyncio
import json
import secrets
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from services.control.core.scenario import load_scenario
from services.embedding.client import EmbeddingClient
from services.ros2 import convert, wire
from services.ros2.config import load_config
from shared.process import free_port
from shared.settings import BusSettings
from tests.demo_stack import running_stack
from tests.ros2_robot import RosRobot
from tests.zenoh_peers import wait_until
from tools.demo.flights import demo_scenario
from tools.demo.report import ended_in
from tools.scenes.hardware import build_scene_cache
from tools.stack.acl import server_users
from tools.stack.certs import write_certs
from tools.stack.up import DETECTOR_CACHE, hardware_scenario

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(600)]

TOKEN = secrets.token_urlsafe(24)
QUADROTOR = Path(__file__).resolve().parents[2] / "deploy" / "ros2" / "quadrotor.yaml"
SCENE = load_scenario(hardware_scenario())
FLIGHT_S = 28.0  # from the first set-point: the way in, the anomaly, T = 10 s, at rest
TF = "/tf"  # a topic of the robot's own graph, mapped to nothing


def node_settings(folder: Path, endpoint: str) -> BusSettings:
    """A robot node's session: rmw_zenoh's default config, the router's port changed."""
    path = folder / "rmw-zenoh-default.json5"
    path.write_text(json.dumps(wire.session_config({"connect": {"endpoints": [endpoint]}})))
    return BusSettings(zenoh_config=path)


def test_a_ros2_robot_with_its_own_router_flies_through_the_bridge_on_the_robot(
        tmp_path: Path) -> None:
    config = load_config(QUADROTOR)
    demo = demo_scenario("2a-quadrotor-on-red-box")
    x0 = np.zeros(12)
    x0[0:3] = SCENE.start_center
    certs = tmp_path / "certs"
    write_certs(certs, robots=[config.robot], services=server_users(),
                server_names=["127.0.0.1"])
    port = free_port()
    with running_stack(tmp_path / "server", TOKEN, role="server", tls=certs,
                       linked=(config.robot,), listen=(f"tls/127.0.0.1:{port}",)) as server, \
            running_stack(tmp_path / "robot", TOKEN, ros2=QUADROTOR, role="robot",
                          tls=certs / f"robot-{config.robot}",
                          server=f"127.0.0.1:{port}") as robot_side:
        url = server.plan.url("embedding")
        assert url is not None and robot_side.plan.url("ros2") is not None
        assert robot_side.plan.url("embedding") is None  # the detector is on the server
        asyncio.run(build_cache(url))
        settings = node_settings(tmp_path, robot_side.plan.endpoint)
        with RosRobot(settings, config, SCENE, demo, x0) as robot, \
                zenoh.open(zenoh.Config.from_file(str(settings.zenoh_config))) as tf_node:
            tf_heard = own_graph(robot.session, tf_node)
            robot.until_flown(FLIGHT_S)
            truth, heard = robot.truth, robot.heard
    said = json.dumps(heard.strings, default=str)
    assert tf_heard.is_set(), "the robot's own unmapped topic did not pass its own router"
    assert ended_in(truth, SCENE) == "blue-box", (truth[0:3], said)
    decisions = heard.strings.get("decision", [])
    assert decisions and decisions[-1]["label"] == "alternative landing site", said
    assert set(heard.attachments) == {33}


async def build_cache(url: str) -> None:
    async with EmbeddingClient(url, token=TOKEN, timeout_s=120) as client:
        await build_scene_cache(client, DETECTOR_CACHE, say=lambda _: None)


def own_graph(node: zenoh.Session, other: zenoh.Session) -> threading.Event:
    """One of the robot's nodes publishes a topic no config maps, another hears it: the
    robot's graph is whole on its own router (the hub's ACL would have dropped it)."""
    ros_type = "std_msgs/msg/String"
    key = wire.data_key(0, TF, ros_type, convert.type_hash(ros_type))
    heard = threading.Event()
    other.declare_subscriber(key, lambda _: heard.set())
    payload = bytes(convert.typestore().serialize_cdr(
        convert.typestore().types[ros_type](data="map -> base_link"), ros_type))
    attachment = wire.Attachment(1, time.time_ns(), wire.gid("tf publisher")).encode()
    wait_until(lambda: node.put(key, payload, attachment=attachment) or heard.is_set(),
               "the robot's own topic between two of its nodes", timeout=30.0)
    return heard
