"""A ROS 2 robot as rmw_zenoh puts it on the wire, played by a plain zenoh-python session
(no ROS installed): the tests' counterpart of the bridge.

It flies the simulated vehicle (:class:`services.sim.vehicle.SimVehicle`, real time) and
speaks only ROS: ``nav_msgs/msg/Odometry`` (CDR, ENU pose in ``map``, the twist in the body
frame, as REP 105 says) with the 33-byte attachment on the odometry topic's data key; its
camera's frames as a ``std_msgs/msg/String`` scene and a ``vision_msgs/msg/Detection2DArray``
(class ids: the indices of the detector's queries, the config's ``classes``); it reads the
set-point topic (``AccelStamped``: its flight controller tracks the acceleration, holding
past ``HOLD_S`` without a newer one, as PX4 leaves offboard mode) and the String topics.
The CDR is written with ``rosbags`` from the message definitions, never from the bridge's
own conversions, so a mistake in those cannot cancel out here.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from services.control.core.scenario import Scenario
from services.ros2 import convert, wire
from services.ros2.config import BridgeConfig
from services.sim.vehicle import Reporting, SimVehicle
from shared.bus import zenoh_config
from shared.messages import Mode, VehicleSetpoint
from shared.settings import BusSettings
from tests.zenoh_peers import wait_until
from tools.fakes.ros2_cdr import detections_cdr, odometry_cdr, string_cdr
from tools.scenes.hardware import DemoScenario, observation_text

HOLD_S = 0.5  # PX4's offboard loss timeout, roughly: past it the vehicle holds
CAMERA_PERIOD_S = 0.05
NODE = "quadrotor"


@dataclass
class Heard:
    """What the robot read from the bridge."""

    setpoints: int = 0
    attachments: list[int] = field(default_factory=list)  # sizes
    strings: dict[str, list[dict[str, Any]]] = field(default_factory=dict)  # role -> JSON
    first_setpoint_at: float | None = None  # time.time()


class RosRobot:
    """Flies ``scene``'s vehicle from ``x0`` and shows ``demo``'s camera, over ``config``'s
    topics, joining the router as ``settings`` say (as the robot's nodes would: ``ros2``)."""

    def __init__(self, settings: BusSettings, config: BridgeConfig, scene: Scenario,
                 demo: DemoScenario, x0: np.ndarray) -> None:
        self.config, self.scene, self.demo = config, scene, demo
        self.session = zenoh.open(zenoh_config(settings))
        self.zid = str(self.session.zid())
        self.lock = threading.Lock()
        self.vehicle = SimVehicle(scene, x0, Reporting(rate_hz=100.0), now=time.time(),
                                  robot=config.robot)
        self.heard = Heard()
        self.mapped = {m.role: m for m in config.topics()}
        self.node = wire.Node(config.domain_id, self.zid, NODE)
        self.ids = {phrase: class_id for class_id, phrase in
                    (config.inputs.detections.classes.items() if config.inputs.detections
                     else ())}
        self._seq: dict[str, int] = {}
        self._publishers: dict[str, Any] = {}
        self._declared: list[Any] = []
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.frame_id = config.inputs.odometry.frame_id if config.inputs.odometry else "map"

    # ------------------------------------------------------------------ wire

    def key(self, role: str) -> str:
        m = self.mapped[role]
        return wire.data_key(self.config.domain_id, m.name, m.ros_type,
                             convert.type_hash(m.ros_type))

    def token(self, role: str) -> str:
        """The robot's endpoint of ``role``'s topic: its liveliness token (its GID's source)."""
        m = self.mapped[role]
        kind = "MP" if m.direction == "in" else "MS"  # the robot's side of each topic
        return self.node.entity_token(m.entity_id, kind, m.name, m.ros_type,
                                      convert.type_hash(m.ros_type), wire.qos_keyexpr())

    def put(self, role: str, payload: bytes) -> None:
        """``payload`` on ``role``'s data key with the attachment rmw_zenoh writes."""
        key = self.key(role)
        if key not in self._publishers:
            self._publishers[key] = self.session.declare_publisher(key)
        self._seq[role] = self._seq.get(role, 0) + 1
        attachment = wire.Attachment(self._seq[role], time.time_ns(),
                                     wire.gid(self.token(role)))
        self._publishers[key].put(payload, attachment=attachment.encode())

    # ------------------------------------------------------------------ running

    def start(self) -> None:
        liveliness = self.session.liveliness()
        self._declared.append(liveliness.declare_token(self.node.token()))
        for role, m in self.mapped.items():
            self._declared.append(liveliness.declare_token(self.token(role)))
            if m.direction == "out":
                self._declared.append(self.session.declare_subscriber(
                    self.key(role), self._on_output(role)))
        for target in (self._fly, self._camera):
            thread = threading.Thread(target=target, daemon=True)
            thread.start()
            self._threads.append(thread)

    def _on_output(self, role: str) -> Any:
        def on_sample(sample: zenoh.Sample) -> None:
            raw = sample.payload.to_bytes()
            size = 0 if sample.attachment is None else len(sample.attachment.to_bytes())
            with self.lock:
                self.heard.attachments.append(size)
                if role == "setpoint":
                    self._take_setpoint(raw)
                else:
                    text = convert.typestore().deserialize_cdr(raw, "std_msgs/msg/String").data
                    self.heard.strings.setdefault(role, []).append(json.loads(text))
        return on_sample

    def _take_setpoint(self, raw: bytes) -> None:
        msg = convert.typestore().deserialize_cdr(raw, "geometry_msgs/msg/AccelStamped")
        t = convert.seconds(msg.header.stamp)
        a = msg.accel.linear
        self.heard.setpoints += 1
        if self.heard.first_setpoint_at is None:
            self.heard.first_setpoint_at = time.time()
        sp = VehicleSetpoint(robot=self.config.robot, seq=self.heard.setpoints, state_seq=0,
                             state_stamp=t, t=t, valid_until=t + HOLD_S, mode=Mode.NOMINAL,
                             acceleration=(a.x, a.y, a.z), position=(0.0, 0.0, 0.0),
                             velocity=(0.0, 0.0, 0.0))
        self.vehicle.receive(sp, time.time())

    def _fly(self) -> None:
        while not self._stop.is_set():
            with self.lock:
                due = self.vehicle.next_event()
            self._stop.wait(max(0.0, min(due - time.time(), 0.01)))
            with self.lock:
                reports = self.vehicle.advance(time.time())
            for report in reports:
                self.put("odometry", odometry_cdr(report.state, self.frame_id))

    def _camera(self) -> None:
        while not self._stop.wait(CAMERA_PERIOD_S):
            with self.lock:
                seen = self.demo.detections(self.vehicle.truth[0:3])
            if "scene" in self.mapped:
                self.put("scene", string_cdr(observation_text(seen)))
            self.put("detections", detections_cdr([(self.ids[p], 0.9) for p in seen]))

    @property
    def truth(self) -> np.ndarray:
        with self.lock:
            return self.vehicle.truth.copy()

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=5.0)
        for declared in [*self._declared, *self._publishers.values()]:
            declared.undeclare()
        self.session.close()  # type: ignore[no-untyped-call]

    def until_flown(self, flight_s: float) -> None:
        """Block until ``flight_s`` have passed since the bridge's first set-point."""
        wait_until(lambda: self.heard.first_setpoint_at is not None,
                   "the first set-point on the ROS topic", timeout=60.0)
        start = self.heard.first_setpoint_at
        assert start is not None
        wait_until(lambda: time.time() - start > flight_s, "the flight",
                   timeout=flight_s + 30.0)

    def __enter__(self) -> RosRobot:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
