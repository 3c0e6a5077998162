"""A second airframe, unlike the built-in simulator, behind the vehicle contract alone
(docs/architecture.md 3a): what a robot team would bring (issue 46).

- **Rigid body** with rotor drag (a force ``-R D R^T v``) and motor lag (thrust and
  moments reach the airframe through a first-order lag of ``MOTOR_LAG_S``), integrated
  on the wall clock in steps of ``STEP_S``.
- **A geometric tracking controller on SE(3)** (Lee, Leok and McClamroch 2010) with no rate
  or tilt clamp: the force from the reference's acceleration and its position and
  velocity errors, the attitude that points the thrust there, the moments from the
  attitude and rate errors.
- **Its reference**, as the contract says a vehicle makes it: each set-point's position and
  velocity, carried on by the commanded acceleration (the one due now: it follows
  ``ahead``), which it realizes with the scene's ``acceleration_lag`` (the planning
  model's); a new set-point's plan is reached over ``BLEND_S``, not stepped to; past
  ``valid_until`` it holds, easing from the last command into a hold where its reference is
  over ``EASE_S``. It answers the reset query (and takes no set-point planned from a state
  before it or before it started: another flight's), publishes its state at
  ``--rate-hz`` ``--delay-s`` after the instant it is valid for (with the acceleration it
  realizes of the commands: its reference's), and its truth on
  ``vehicle/truth`` at 100 Hz; it answers clock queries (its clock is the wall clock), so
  the loop compensates the delay.

It runs at real-time priority where it may (as root): its physics and flight controller
stand for hardware of their own, which CPU hogs on the robot's computer do not starve.

``--stats FILE``: what it measured (JSON, written every second): the set-points' age at
arrival, the holds begun between two set-points of one flight (a flight: from a reset to
the next), its largest body rate and tilt.

Run: ``AESOP_ROBOT=... AESOP_ZENOH_*=... python -m tests.airframe --rate-hz 100``
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np

from services.control.core.scenario import load_scenario
from shared import topics
from shared.bus import Bus
from shared.messages import VehicleClock, VehicleReset, VehicleSetpoint, VehicleState
from shared.settings import BusSettings
from tools.stack.up import hardware_scenario

G = 9.81
MASS = 1.3  # kg
INERTIA = np.array([0.014, 0.014, 0.024])  # kg m^2, body axes
DRAG = np.diag([0.35, 0.35, 0.1])  # N s/m, in the body frame (rotor drag)
MOTOR_LAG_S = 0.02
STEP_S = 0.002
KX, KV = 5.0 * MASS, 3.6 * MASS  # N/m, N s/m
KR, KW = 5.6, 0.42  # N m/rad, N m s/rad: about 20 rad/s, damped 0.75
HOLD_KP, HOLD_KD, HOLD_ACCEL = 1.0, 1.8, 1.0  # 1/s^2, 1/s, m/s^2
EASE_S = 0.2
BLEND_S = 0.25  # s: a new set-point's plan reached (exponentially) over this
TRUTH_HZ = 100.0


def hat(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def vee(m: np.ndarray) -> np.ndarray:
    return np.array([m[2, 1], m[0, 2], m[1, 0]])


def rotation_step(w: np.ndarray, dt: float) -> np.ndarray:
    """exp(hat(w) dt) (Rodrigues)."""
    angle = float(np.linalg.norm(w)) * dt
    if angle < 1e-12:
        return np.eye(3)
    k = hat(w / np.linalg.norm(w))
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the rotation matrix ``r``."""
    t = float(np.trace(r))
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = (0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s)
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = ((r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s)
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = ((r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s)
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = ((r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s)
    n = math.sqrt(sum(v * v for v in q))
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


class Airframe:
    """The body, its controller and its reference (module docstring); time in seconds of
    ``time.monotonic()``."""

    def __init__(self, lag: np.ndarray, start: np.ndarray) -> None:
        self.lag = np.asarray(lag, dtype=float)
        self.reset(start)

    def reset(self, position: np.ndarray) -> None:
        self.p, self.v = np.asarray(position, dtype=float).copy(), np.zeros(3)
        self.r, self.w = np.eye(3), np.zeros(3)
        self.f, self.m = MASS * G, np.zeros(3)  # thrust and moments as the motors give them
        self.p_ref, self.v_ref, self.a_ref = self.p.copy(), np.zeros(3), np.zeros(3)
        self.p_plan, self.v_plan = self.p.copy(), np.zeros(3)  # the reference less its offset
        self.off_p, self.off_v = np.zeros(3), np.zeros(3)  # from the newest set-point's plan
        self.hold_from: np.ndarray | None = np.zeros(3)  # holding, eased from this command
        self.hold_at = self.p.copy()
        self.hold_since = -math.inf

    def follow(self, position: np.ndarray, velocity: np.ndarray, age: float) -> None:
        """A new set-point, ``age`` s after its instant: the reference goes on from its
        plan, reached over ``BLEND_S`` (a step in the reference is a step in attitude)."""
        age = max(age, 0.0)
        plan_p = position + velocity * age + 0.5 * self.a_ref * age * age
        plan_v = velocity + self.a_ref * age
        self.off_p, self.off_v = self.p_ref - plan_p, self.v_ref - plan_v
        self.p_plan, self.v_plan = plan_p, plan_v
        self.hold_from = None

    def hold(self, now: float) -> None:
        if self.hold_from is None:  # the reference goes on from where it is
            self.p_plan, self.v_plan = self.p_ref.copy(), self.v_ref.copy()
            self.off_p, self.off_v = np.zeros(3), np.zeros(3)
            self.hold_from, self.hold_at = self.a_ref.copy(), self.p_ref.copy()
            self.hold_since = now

    def step(self, command: np.ndarray | None, now: float, dt: float) -> None:
        """One step: the reference carried on by ``command`` (None: the hold's), the
        controller, the body."""
        if command is None:
            pd = HOLD_KP * (self.hold_at - self.p_ref) - HOLD_KD * self.v_ref
            hold = np.clip(pd, -HOLD_ACCEL, HOLD_ACCEL)
            ease = min(1.0, (now - self.hold_since) / EASE_S)
            assert self.hold_from is not None
            command = (1.0 - ease) * self.hold_from + ease * hold
        # the commanded acceleration, realized with the planning model's lag
        k = np.where(self.lag > 0, dt / np.maximum(self.lag, 1e-9), 1.0)
        self.a_ref = self.a_ref + np.minimum(k, 1.0) * (command - self.a_ref)
        self.v_plan = self.v_plan + self.a_ref * dt
        self.p_plan = self.p_plan + self.v_plan * dt
        fade = math.exp(-dt / BLEND_S)
        self.off_p, self.off_v = self.off_p * fade, self.off_v * fade
        self.p_ref, self.v_ref = self.p_plan + self.off_p, self.v_plan + self.off_v
        # the geometric controller
        force = KX * (self.p_ref - self.p) + KV * (self.v_ref - self.v) \
            + MASS * (self.a_ref + np.array([0.0, 0.0, G])) + self.r @ DRAG @ self.r.T @ self.v
        b3 = force / np.linalg.norm(force)
        b2 = np.cross(b3, np.array([1.0, 0.0, 0.0]))
        b2 /= np.linalg.norm(b2)
        rd = np.column_stack([np.cross(b2, b3), b2, b3])
        e_r = 0.5 * vee(rd.T @ self.r - self.r.T @ rd)
        thrust = float(force @ self.r[:, 2])
        moments = -KR * e_r - KW * self.w + np.cross(self.w, INERTIA * self.w)
        # the motors, then the body
        a = dt / MOTOR_LAG_S
        self.f += a * (thrust - self.f)
        self.m = self.m + a * (moments - self.m)
        accel = (self.f * self.r[:, 2] - self.r @ DRAG @ self.r.T @ self.v) / MASS \
            - np.array([0.0, 0.0, G])
        self.v = self.v + accel * dt
        self.p = self.p + self.v * dt
        self.w = self.w + (self.m - np.cross(self.w, INERTIA * self.w)) / INERTIA * dt
        self.r = self.r @ rotation_step(self.w, dt)
        if self.p[2] < 0.0:  # the floor
            self.p[2], self.v[2] = 0.0, max(self.v[2], 0.0)

    def tilt(self) -> float:
        return math.acos(max(-1.0, min(1.0, float(self.r[2, 2]))))

    def state(self, robot: str, seq: int, stamp: float) -> VehicleState:
        return VehicleState(robot=robot, seq=seq, stamp=stamp,
                            position=tuple(float(x) for x in self.p),
                            velocity=tuple(float(x) for x in self.v),
                            attitude=quaternion(self.r),
                            body_rates=tuple(float(x) for x in self.w),
                            acceleration=tuple(float(x) for x in self.a_ref))


class Stats:
    def __init__(self) -> None:
        self.ages_ms: deque[float] = deque(maxlen=100_000)
        self.holds = 0  # begun between two set-points of one flight
        self.hold_log: list[dict[str, float]] = []  # when each began, how long, the gap
        self.first: list[dict[str, object]] = []  # each flight's first set-point, as taken
        self.max_rate = 0.0
        self.max_tilt = 0.0
        self.followed = 0
        self.stalls = 0  # times the body fell more than 0.2 s behind the wall clock
        self.at_max: dict[str, object] = {}  # what it was doing at its largest body rate
        self.max_speed = 0.0  # the largest speed on one axis in flight
        self.at_max_speed: dict[str, object] = {}  # and what it was doing then

    def summary(self) -> dict[str, object]:
        ages = np.array(self.ages_ms) if self.ages_ms else None
        return {"setpoints": self.followed, "holds": self.holds, "hold_log": self.hold_log[:20],
                "first_setpoints": self.first[:12],
                "stalls": self.stalls,
                "age_p50_ms": None if ages is None else round(float(np.percentile(ages, 50)), 1),
                "age_p99_ms": None if ages is None else round(float(np.percentile(ages, 99)), 1),
                "age_max_ms": None if ages is None else round(float(ages.max()), 1),
                "max_body_rate": round(self.max_rate, 3), "max_tilt": round(self.max_tilt, 3),
                "at_max_rate": self.at_max, "max_speed": round(self.max_speed, 3),
                "at_max_speed": self.at_max_speed}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rate-hz", type=float, default=100.0)
    parser.add_argument("--delay-s", type=float, default=0.0)
    parser.add_argument("--stats", type=Path, default=None)
    args = parser.parse_args()
    try:  # its physics and flight controller stand for hardware of their own: never starved
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(20))
    except (OSError, AttributeError):
        with contextlib.suppress(OSError):
            os.nice(-10)
    scenario = load_scenario(hardware_scenario())
    settings = BusSettings()
    robot = settings.robot
    body = Airframe(np.asarray(scenario.acceleration_lag), np.asarray(scenario.start_center))
    stats = Stats()
    resets: deque[np.ndarray] = deque()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    seq = 0
    offset = time.time() - time.monotonic()  # the vehicle's clock is the wall clock

    def reset(asked: VehicleReset) -> VehicleState:
        resets.append(np.asarray(asked.position, dtype=float))
        return VehicleState(robot=robot, seq=seq, position=asked.position,
                            velocity=(0.0, 0.0, 0.0))

    with Bus.open(settings, "vehicle") as bus:
        setpoints = bus.latest(topics.vehicle_setpoint(robot), VehicleSetpoint)
        bus.serve(topics.vehicle_reset(robot), VehicleReset, reset)
        bus.answer(topics.vehicle_clock(robot), lambda: VehicleClock(robot=robot))
        state_key, truth_key = topics.vehicle_state(robot), topics.vehicle_truth(robot)
        now = time.monotonic()
        t = now  # the body's time
        reset_at, taken, holding = now, None, False
        held_from = now
        since = now + offset  # its clock at the last reset
        next_state, next_truth, next_stats = t, t, t + 1.0
        outbox: deque[tuple[float, VehicleState]] = deque()
        while not stop.is_set():
            now = time.monotonic()
            while resets:
                body.reset(resets.popleft())
                reset_at, taken, holding = now, None, False
                since = now + offset
            if t < now - 0.2:  # more than 0.2 s behind (a stall): skip, not catch up
                stats.stalls += 1
                t = now - 0.2
            while t + STEP_S <= now:
                t += STEP_S
                clock = t + offset
                got = setpoints.get()
                if got is not None and got is not taken and reset_at < got.received_at <= t \
                        and got.message.state_stamp >= since \
                        and got.message.acceleration is not None:  # arrived by now, this flight's
                    sp = got.message
                    if holding and taken is not None:
                        stats.holds += 1  # the flight went on after a hold
                        stats.hold_log.append({
                            "s_since_reset": round(held_from - reset_at, 2),
                            "held_s": round(t - held_from, 3),
                            "gap_s": round(got.received_at - taken.received_at, 3),
                            "new_age_ms": round((got.received_at + offset - sp.t) * 1e3, 1),
                            "last_seq": taken.message.seq, "new_seq": sp.seq})
                    if taken is None:
                        stats.first.append({
                            "s_since_reset": round(t - reset_at, 3),
                            "planned_from_s": round(sp.state_stamp - since, 3),
                            "t_s": round(sp.t - since, 3),
                            "off_m": round(float(np.linalg.norm(
                                np.asarray(sp.position) - body.p)), 3),
                            "position": [round(x, 2) for x in sp.position],
                            "at": body.p.round(2).tolist()})
                    taken, holding = got, False
                    stats.followed += 1
                    stats.ages_ms.append((got.received_at + offset - sp.t) * 1000.0)
                    body.follow(np.asarray(sp.position), np.asarray(sp.velocity),
                                clock - sp.t)
                command = None
                if taken is not None and clock <= taken.message.valid_until:
                    command = np.asarray(taken.message.command_at(clock), dtype=float)
                else:
                    held_from = t if not holding else held_from
                    holding = True
                    body.hold(t)
                body.step(command, t, STEP_S)
                if taken is not None:  # in flight: from its first set-point on
                    rate = float(np.abs(body.w[:2]).max())
                    if rate > stats.max_rate:
                        stats.max_rate = rate
                        stats.at_max = {"s_since_reset": round(t - reset_at, 2),
                                        "holding": holding, "seq": taken.message.seq,
                                        "off_v": round(float(np.linalg.norm(body.off_v)), 3),
                                        "off_p": round(float(np.linalg.norm(body.off_p)), 3),
                                        "a_ref": body.a_ref.round(2).tolist(),
                                        "command": None if command is None
                                        else command.round(2).tolist()}
                    stats.max_tilt = max(stats.max_tilt, body.tilt())
                    speed = float(np.abs(body.v).max())
                    if speed > stats.max_speed:
                        stats.max_speed = speed
                        stats.at_max_speed = {
                            "s_since_reset": round(t - reset_at, 2), "holding": holding,
                            "seq": taken.message.seq, "v": body.v.round(3).tolist(),
                            "v_ref": body.v_ref.round(3).tolist(),
                            "v_plan": body.v_plan.round(3).tolist(),
                            "setpoint_v": [round(x, 3) for x in taken.message.velocity],
                            "a_ref": body.a_ref.round(2).tolist(),
                            "command": None if command is None
                            else command.round(2).tolist()}
                if t >= next_state:
                    next_state += 1.0 / args.rate_hz
                    outbox.append((t + args.delay_s, body.state(robot, seq, t + offset)))
                    seq += 1
                if t >= next_truth:
                    next_truth += 1.0 / TRUTH_HZ
                    bus.publish(truth_key, body.state(robot, seq, t + offset))
            while outbox and outbox[0][0] <= now:
                bus.publish(state_key, outbox.popleft()[1])
            if args.stats is not None and now >= next_stats:
                next_stats = now + 1.0
                args.stats.write_text(json.dumps(stats.summary()))
            time.sleep(max(0.0, t + STEP_S - time.monotonic()))
    if args.stats is not None:
        args.stats.write_text(json.dumps(stats.summary()))


if __name__ == "__main__":
    main()
