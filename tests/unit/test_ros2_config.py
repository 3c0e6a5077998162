"""The ROS 2 bridge's config (services/ros2/config.py), ``aesop ros2 keys``, the ``ros2``
user's ACL and ``aesop up --ros2``'s plan."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.ros2 import convert, wire
from services.ros2.config import (
    MAX_SAMPLE_BYTES,
    ODOMETRY,
    STRING,
    ConfigError,
    Input,
    load_config,
    parse_config,
)
from shared.messages import MAX_TEXT_CHARS
from tools import cli
from tools.stack.acl import (
    MAX_MESSAGE_BYTES,
    ROS2,
    ROS2_BRIDGE,
    ros_keys,
    stack_acl,
    users_of,
)
from tools.stack.up import PlanError, Ports, StackOptions, plan_stack

QUADROTOR = Path(__file__).resolve().parents[2] / "deploy" / "ros2" / "quadrotor.yaml"


@pytest.mark.parametrize("path", sorted(QUADROTOR.parent.glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_config_loads_and_maps_odometry(path: Path):
    config = load_config(path)
    assert any(m.ros_type == "nav_msgs/msg/Odometry" for m in config.topics())


def test_the_shipped_quadrotor_config_maps_odometry_in_and_the_setpoint_out():
    config = load_config(QUADROTOR)
    roles = {m.role: m for m in config.topics()}
    assert roles["odometry"].ros_type == "nav_msgs/msg/Odometry"
    assert roles["setpoint"].ros_type == "geometry_msgs/msg/AccelStamped"
    assert [m.entity_id for m in config.topics()] == list(range(1, len(roles) + 1))
    assert [m.direction for m in config.topics()] == \
        ["in"] * 3 + ["out"] * 4  # inputs first
    detections = config.inputs.detections
    assert detections is not None
    assert detections.classes["10"] == "a quadrotor on the red box"


@pytest.mark.parametrize(("text", "names"), [
    ("robot: r1\n", "maps no topic"),
    ("inputs: {odometry: {topic: /odom, fram_id: map}}", "inputs.odometry.fram_id"),
    ("inputs: {odometry: {topic: 'a//b'}}", "inputs.odometry.topic"),
    ("inputs: {odometry: {topic: /odom, type: std_msgs/msg/String}}", "inputs.odometry.type"),
    ("outputs: {setpoint: {topic: /sp, type: geometry_msgs/msg/Twist}}",
     "outputs.setpoint.type"),
    ("inputs: {odometry: {topic: /odom, type_hash: TypeHashNotSupported}}",
     "inputs.odometry.type_hash"),
    ("inputs: {detections: {topic: /d, classes: {'1': ''}}}", "inputs.detections.classes"),
    ("inputs: {scene: {topic: /s, max_bytes: 600000}}", "inputs.scene.max_bytes"),
    ("inputs: {odometry: {topic: /odom, max_bytes: 100}}", "inputs.odometry.max_bytes"),
    ("outputs: {mode: {topic: /m, max_bytes: 4096}}", "outputs.mode.max_bytes"),
    ("domain_id: 300\ninputs: {odometry: {topic: /odom}}", "domain_id"),
    ("robot: 'a b'\ninputs: {odometry: {topic: /odom}}", "robot"),
    ("[1, 2]", "a mapping"),
    ("inputs: {", "not YAML"),
])
def test_a_bad_config_names_what_is_wrong(text: str, names: str):
    with pytest.raises(ConfigError, match=names.replace(".", r"\.")):
        parse_config(text, "f.yaml")


def test_a_type_hash_in_the_config_overrides_the_type_stores():
    given = "RIHS01_" + "ab" * 32
    config = parse_config(f"inputs: {{odometry: {{topic: odom, type_hash: {given}}}}}\n"
                          "namespace: /robot1")
    [odom] = config.topics()
    assert odom.name == "/robot1/odom" and odom.settings.type_hash == given


def test_each_input_takes_samples_up_to_its_max_bytes_under_what_the_router_passes():
    """Issue 43, finding 4: a size per sample below the 1 MiB the stack's router passes
    (a robot's own router passes any), each kind's default well above what it needs."""
    config = load_config(QUADROTOR)
    sizes = {m.role: m.settings.max_bytes for m in config.topics()
             if isinstance(m.settings, Input)}
    assert sizes == {"odometry": 16 * 1024, "scene": 64 * 1024, "detections": 256 * 1024}
    assert max(sizes.values()) <= MAX_SAMPLE_BYTES < MAX_MESSAGE_BYTES
    assert sizes["scene"] >= 4 * MAX_TEXT_CHARS + convert.min_cdr_bytes(STRING)  # UTF-8
    assert sizes["odometry"] > convert.min_cdr_bytes(ODOMETRY) + 2 * 256  # two frames' names
    given = parse_config("inputs: {detections: {topic: /d, max_bytes: 524288}}")
    assert given.inputs.detections is not None
    assert given.inputs.detections.max_bytes == MAX_SAMPLE_BYTES


def test_keys_prints_data_keys_first_then_the_liveliness_tokens(
        capsys: pytest.CaptureFixture[str]):
    assert cli.main(["ros2", "keys", "--config", str(QUADROTOR)]) == 0
    lines = capsys.readouterr().out.splitlines()
    config = load_config(QUADROTOR)
    n = len(list(config.topics()))
    assert len(lines) == 2 * n + 1
    odometry = "nav_msgs/msg/Odometry"
    assert lines[0] == wire.data_key(0, "/mavros/local_position/odom", odometry,
                                     convert.type_hash(odometry))
    assert all(not line.startswith("@") for line in lines[:n])
    assert lines[n] == "@ros2_lv/0/*/0/0/NN/%/%/aesop_bridge"
    assert lines[n + 1].startswith("@ros2_lv/0/*/0/1/MS/%/%/aesop_bridge/"
                                   "%mavros%local_position%odom/nav_msgs::msg::dds_::Odometry_/")
    assert lines[-1].split("/")[5] == "MP"  # the last output


def test_keys_with_a_bad_or_missing_config_is_a_usage_error(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    bad = tmp_path / "bad.yaml"
    bad.write_text("inputs: {odometry: {topic: /odom, typo: 1}}\n")
    assert cli.main(["ros2", "keys", "--config", str(bad)]) == 2
    assert "inputs.odometry.typo" in capsys.readouterr().err
    assert cli.main(["ros2", "keys", "--config", str(tmp_path / "none.yaml")]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_the_ros2_users_may_use_their_topics_and_only_the_bridge_its_robots_inputs():
    """The robot's nodes (ros2) the mapped ROS keys only; the bridge (ros2-bridge) those and
    its robot's inputs, its keys to receive and its health token (issue 43: a node put the
    robot's inputs around the bridge's checks)."""
    config = load_config(QUADROTOR)
    acl = stack_acl(["robot0"], config)
    assert {ROS2, ROS2_BRIDGE} <= set(users_of(["robot0"], ros2=True))
    assert not {ROS2, ROS2_BRIDGE} & set(users_of(["robot0"]))
    policies = {p["id"]: p for p in acl["policies"]}
    rules = {r["id"]: r for r in acl["rules"]}
    keys = ros_keys(config)
    assert "0/mavros/local_position/odom/*/*" in keys
    assert "0/mavros/local_position/odom/*/*/@adv/**" in keys  # advanced pub/sub
    assert keys[-1] == "@ros2_lv/0/**"  # the graph
    assert all(k.startswith(("0/", "@ros2_lv/0/")) for k in keys)  # its domain only
    for user in (ROS2, ROS2_BRIDGE):
        assert {"ros2-ros-in", "ros2-ros-out"} <= set(policies[user]["rules"])
        assert all(rules[r]["key_exprs"] == keys for r in ("ros2-ros-in", "ros2-ros-out"))
    node, bridge = set(policies[ROS2]["rules"]), set(policies[ROS2_BRIDGE]["rules"])
    assert not any(rules[r]["key_exprs"] != keys for r in node)  # nothing of the stack's
    assert {"ros2-puts", "ros2-health", "robot0-receive"} <= bridge
    assert set(rules["ros2-puts"]["key_exprs"]) == {
        "aesop/robot0/observation", "aesop/robot0/vehicle/state", "aesop/robot0/event/ros2"}
    assert rules["ros2-health"]["key_exprs"] == ["aesop/health/ros2"]
    assert not {ROS2, ROS2_BRIDGE} & {u for s in stack_acl(["robot0"])["subjects"]
                                      for u in s["usernames"]}


def test_up_with_ros2_runs_the_bridge_instead_of_the_simulated_vehicle(tmp_path: Path):
    options = StackOptions(data_dir=tmp_path, ports=Ports(1, 2, 3, 4, 5, 6, 7), rate_hz=5.0,
                           python="py", ros2=QUADROTOR)
    plan = plan_stack(options, {}, "t" * 24)
    names = [s.name for s in plan.services]
    assert names == ["fake-llm", "embedding", "reasoner", "ros2", "control", "dashboard"]
    bridge = plan.services[3]
    assert bridge.argv[-2:] == ("serve", "ros2") and bridge.port == 7  # the vehicle's port
    assert bridge.env["AESOP_ROS2_CONFIG"] == str(QUADROTOR)
    assert bridge.env["AESOP_ZENOH_USER"] == ROS2_BRIDGE and ROS2_BRIDGE in plan.passwords
    assert ROS2 in plan.passwords  # the robot's nodes, in the session file aesop up writes
    assert plan.hub.argv[-2:] == ("--ros2", str(QUADROTOR))
    other = tmp_path / "other.yaml"
    other.write_text("robot: robot7\ninputs: {odometry: {topic: /odom}}\n")
    with pytest.raises(ValueError, match="robot7"):
        plan_stack(StackOptions(data_dir=tmp_path, ros2=other), {}, "t" * 24)


def test_a_yaml_syntax_error_names_the_file_and_the_line(tmp_path: Path):
    broken = tmp_path / "broken.yaml"
    broken.write_text("robot: robot0\ninputs:\n  odometry: {topic: /odom\n  scene: x\n")
    with pytest.raises(ConfigError) as caught:
        load_config(broken)
    message = str(caught.value)
    assert message.startswith(f"{broken}:4:8: not YAML: "), message  # file:line:column
    assert "<unicode string>" not in message and "\n" not in message  # one line, one name


def test_a_ros2_config_in_a_frame_control_does_not_fly_in_is_refused(tmp_path: Path):
    """Control refuses every state not in its frame (AESOP_CONTROL_VEHICLE's ``frame``):
    a bridge config that names another is refused where both are known, not flown blind."""
    wrong = tmp_path / "wrld.yaml"
    wrong.write_text("inputs: {odometry: {topic: /odom, frame: wrld}}\n")
    with pytest.raises(ConfigError, match=rf"^{wrong}: inputs\.odometry\.frame: 'wrld' is "
                       r"not 'world', the frame control flies in \(AESOP_CONTROL_VEHICLE"):
        load_config(wrong, frame="world")
    assert load_config(wrong).inputs.odometry is not None  # the frame alone: no control known
    with pytest.raises(PlanError, match=rf"{wrong}: inputs\.odometry\.frame: 'wrld' .*'world'"):
        plan_stack(StackOptions(data_dir=tmp_path, ros2=wrong), {}, "t" * 24)
    # control told to fly in it: the same config is taken
    plan = plan_stack(StackOptions(data_dir=tmp_path, ros2=wrong),
                      {"AESOP_CONTROL_VEHICLE__FRAME": "wrld"}, "t" * 24)
    assert "ros2" in [s.name for s in plan.services]
    assert load_config(QUADROTOR, frame="world").inputs.odometry is not None
