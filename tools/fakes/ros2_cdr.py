"""A ROS 2 robot's messages in CDR, from their definitions: the tests' robot, ``aesop bench ros2``.

Written as a robot's nodes write them, from the message definitions (``rosbags``), never
from the bridge's own conversions (:mod:`services.ros2.convert` reads them), so a mistake in
those cannot cancel out: for the tests' robot and ``aesop bench ros2``."""

from __future__ import annotations

import numpy as np

from services.ros2 import convert
from shared.frames import rotate
from shared.messages import VehicleState


def odometry_cdr(state: VehicleState, frame_id: str = "map") -> bytes:
    """``state`` as a ``nav_msgs/msg/Odometry`` in CDR: the pose in ``frame_id``, the twist
    in the body frame (REP 105), covariances unknown (zero)."""
    types = convert.typestore().types
    w, x, y, z = state.attitude
    body_v = rotate((w, -x, -y, -z), state.velocity)
    v3 = types["geometry_msgs/msg/Vector3"]
    msg = types["nav_msgs/msg/Odometry"](
        header=convert.header(state.stamp, frame_id), child_frame_id="base_link",
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](*state.position),
                orientation=types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)),
            covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=v3(*body_v),
                                                    angular=v3(*state.body_rates)),
            covariance=np.zeros(36)))
    return convert.serialize(msg, "nav_msgs/msg/Odometry")


def detections_cdr(hypotheses: list[tuple[str, float]], stamp: float = 0.0) -> bytes:
    """A ``vision_msgs/msg/Detection2DArray`` in CDR: one detection per ``(class id,
    score)``."""
    types = convert.typestore().types
    header = convert.header(stamp, "camera")
    pose = types["geometry_msgs/msg/PoseWithCovariance"](
        pose=types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](0.0, 0.0, 0.0),
            orientation=types["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0)),
        covariance=np.zeros(36))
    box = types["vision_msgs/msg/BoundingBox2D"](
        center=types["vision_msgs/msg/Pose2D"](
            position=types["vision_msgs/msg/Point2D"](x=320.0, y=240.0), theta=0.0),
        size_x=40.0, size_y=40.0)
    found = [types["vision_msgs/msg/Detection2D"](
        header=header, results=[types["vision_msgs/msg/ObjectHypothesisWithPose"](
            hypothesis=types["vision_msgs/msg/ObjectHypothesis"](class_id=c, score=s),
            pose=pose)], bbox=box, id=str(i)) for i, (c, s) in enumerate(hypotheses)]
    return convert.serialize(types["vision_msgs/msg/Detection2DArray"](
        header=header, detections=found), "vision_msgs/msg/Detection2DArray")


def string_cdr(text: str) -> bytes:
    return convert.serialize(convert.typestore().types["std_msgs/msg/String"](data=text),
                             "std_msgs/msg/String")
