"""``aesop bench ros2``: what the ROS 2 bridge costs, a real ``aesop serve ros2`` process.

This process listens on a private Zenoh endpoint and plays both sides: the robot's
rmw_zenoh nodes (CDR with the 33-byte attachment on the ROS keys) and the stack. The bridge
connects to it. Two phases, each ``seconds`` long at ``rate_hz``:

1. **in**: ``nav_msgs/msg/Odometry`` put on the odometry topic's data key; latency = the
   arrival here of the ``VehicleState`` whose stamp is that odometry's, minus the put (both
   on this process's monotonic clock). Two Zenoh hops plus the bridge's CDR decoding,
   checks, rotation and JSON.
2. **out**: ``VehicleSetpoint`` published on the stack's key; latency = the arrival of the
   ``AccelStamped`` carrying its ``t`` on the ROS key, minus the publish.

Reported per phase: samples, lost (not arrived 10 s after the last was sent), p50/p99/max
in ms, and the bridge process's CPU share while the phase sent (psutil), as a table or one
JSON object.
"""

from __future__ import annotations

import secrets
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import psutil
import zenoh

from services.ros2 import convert, wire
from shared import topics
from shared.bus import Bus
from shared.messages import Mode, VehicleSetpoint, VehicleState
from shared.process import ServiceProcess, free_port
from shared.settings import BusSettings
from shared.tables import table
from tools import progress
from tools.bench.bus import BenchError
from tools.bench.fairness import spread
from tools.fakes.ros2_cdr import odometry_cdr

ROBOT = "robot0"
ODOMETRY, SETPOINT = "/bench/odom", "/bench/accel"
CONFIG = f"""robot: {ROBOT}
inputs: {{odometry: {{topic: {ODOMETRY}, frame_id: map}}}}
outputs: {{setpoint: {{topic: {SETPOINT}, type: geometry_msgs/msg/AccelStamped}}}}
"""
SETTLE_S = 10.0  # after the last sample, the most a late one is waited for (then: lost)
WAIT_S = 30.0


class Timed:
    """Send times and arrival times of tagged samples (the tag: a stamp in whole ms)."""

    def __init__(self) -> None:
        self.sent: dict[int, float] = {}
        self.arrived: dict[int, float] = {}
        self.lock = threading.Lock()

    def arrive(self, stamp: float) -> None:
        now = time.monotonic()
        with self.lock:
            self.arrived.setdefault(round(stamp * 1000), now)

    def missing(self) -> bool:
        with self.lock:
            return any(k not in self.arrived for k in self.sent)

    def result(self, cpu_percent: float) -> dict[str, Any]:
        with self.lock:
            ms = [(self.arrived[k] - t) * 1000.0 for k, t in self.sent.items()
                  if k in self.arrived]
            lost = sum(k not in self.arrived for k in self.sent)
        return {**spread(ms), "sent": len(self.sent), "lost": lost,
                "bridge_cpu_percent": round(cpu_percent, 1)}


def _pace(rate_hz: float, seconds: float, send: Any) -> None:
    period, n = 1.0 / rate_hz, int(seconds * rate_hz)
    start = time.monotonic()
    for i in range(n):
        send(i)
        delay = start + (i + 1) * period - time.monotonic()
        if delay > 0:
            time.sleep(delay)


def _phase(bridge: psutil.Process, rate_hz: float, seconds: float, send: Any,
           timed: Timed) -> dict[str, Any]:
    bridge.cpu_percent(None)
    start = time.monotonic()
    _pace(rate_hz, seconds, send)
    cpu = bridge.cpu_percent(None) * (time.monotonic() - start) / seconds
    deadline = time.monotonic() + SETTLE_S
    while time.monotonic() < deadline and timed.missing():
        time.sleep(0.05)
    return timed.result(cpu)


def run_ros2_bench(*, seconds: float, rate_hz: float, table_out: bool) -> dict[str, Any]:
    token = secrets.token_urlsafe(24)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    odom_key = wire.data_key(0, ODOMETRY, "nav_msgs/msg/Odometry",
                             convert.type_hash("nav_msgs/msg/Odometry"))
    accel_key = wire.data_key(0, SETPOINT, "geometry_msgs/msg/AccelStamped",
                              convert.type_hash("geometry_msgs/msg/AccelStamped"))
    with tempfile.TemporaryDirectory(prefix="aesop-bench-ros2-") as tmp, \
            Bus.open(BusSettings(zenoh_listen=[endpoint], robot=ROBOT), "bench") as bus:
        config = Path(tmp) / "bridge.yaml"
        config.write_text(CONFIG)
        port = free_port()
        env = {"AESOP_ADMIN_TOKEN": token, "AESOP_ZENOH_CONNECT": endpoint,
               "AESOP_ZENOH_LISTEN": "", "AESOP_ROBOT": ROBOT, "AESOP_ROS2_CONFIG": str(config)}
        with ServiceProcess(["serve", "ros2", "--port", str(port)], port=port, env=env,
                            log_path=Path(tmp) / "ros2.log") as proc:
            bridge = psutil.Process(proc.pid)
            gid = wire.gid(wire.Node(0, str(bus.session.zid()), "bench").entity_token(
                1, "MP", ODOMETRY, "nav_msgs/msg/Odometry",
                convert.type_hash("nav_msgs/msg/Odometry"), wire.qos_keyexpr()))
            ins, outs = Timed(), Timed()
            bus.each(topics.vehicle_state(ROBOT), VehicleState,
                     lambda got: ins.arrive(got.message.stamp))

            def on_accel(sample: zenoh.Sample) -> None:
                msg = convert.deserialize(sample.payload.to_bytes(),
                                          "geometry_msgs/msg/AccelStamped")
                outs.arrive(convert.seconds(msg.header.stamp))

            bus.session.declare_subscriber(accel_key, on_accel)
            publisher = bus.session.declare_publisher(odom_key)

            def put_odometry(i: int) -> None:
                stamp = 1000.0 + i * 0.001  # its tag: a whole number of ms
                payload = odometry_cdr(VehicleState(robot=ROBOT, seq=i, stamp=stamp,
                                                    position=(1.0, 2.0, 3.0),
                                                    velocity=(0.5, 0.0, 0.0)))
                ins.sent[round(stamp * 1000)] = time.monotonic()
                publisher.put(payload, attachment=wire.Attachment(
                    i + 1, time.time_ns(), gid).encode())

            _wait_through(put_odometry, ins)
            ins.sent.clear()
            ins.arrived.clear()
            progress.step(f"odometry in at {rate_hz:g} Hz for {seconds:g} s", 1, 2)
            inbound = _phase(bridge, rate_hz, seconds, put_odometry, ins)

            def put_setpoint(i: int) -> None:
                t = 5000.0 + i * 0.001
                sp = VehicleSetpoint(robot=ROBOT, seq=i + 1, state_seq=1, state_stamp=t, t=t,
                                     valid_until=t + 0.15, mode=Mode.NOMINAL,
                                     acceleration=(0.1, 0.0, 0.0), position=(0.0, 0.0, 1.0),
                                     velocity=(0.0, 0.0, 0.0))
                outs.sent[round(t * 1000)] = time.monotonic()
                bus.publish(topics.vehicle_setpoint(ROBOT), sp)

            progress.step(f"set-points out at {rate_hz:g} Hz for {seconds:g} s", 2, 2)
            outbound = _phase(bridge, rate_hz, seconds, put_setpoint, outs)
    result = {"rate_hz": rate_hz, "seconds": seconds, "in": inbound, "out": outbound}
    if table_out:
        print_ros2_table(result)
    return result


def _wait_through(put: Any, timed: Timed) -> None:
    """Odometry until one comes back as a state: the bridge and its routes are up."""
    deadline = time.monotonic() + WAIT_S
    i = 1_000_000  # tags of their own
    while not timed.arrived:
        if time.monotonic() > deadline:
            raise BenchError("the bridge passed no odometry on")
        put(i)
        i += 1
        time.sleep(0.05)


def print_ros2_table(result: dict[str, Any]) -> None:
    rows = [{"path": name, "sent": r["sent"], "lost": r["lost"], "p50 ms": r["p50"],
             "p99 ms": r["p99"], "max ms": r["max"], "bridge CPU %": r["bridge_cpu_percent"]}
            for name, r in (("odometry -> vehicle/state", result["in"]),
                            ("vehicle/setpoint -> AccelStamped", result["out"]))]
    print(table(f"the ROS 2 bridge at {result['rate_hz']:g} Hz, {result['seconds']:g} s each "
                "way (aesop serve ros2, one process)", rows))
