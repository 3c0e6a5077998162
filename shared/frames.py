"""The vehicle contract's axes and attitudes: quaternions <-> Z-Y-X Euler angles, rotation (pure).

The world frame is x forward, y left, z up (ROS REP 103's ENU-style axes, metres);
the body frame is x forward, y left, z up (FLU). An attitude travels as the unit
quaternion ``(w, x, y, z)`` that rotates body vectors into the world; the control
loop's 12-state model uses Z-Y-X Euler angles (roll ``phi``, pitch ``theta``, yaw
``psi``), the rotation ``Rz(psi) Ry(theta) Rx(phi)``.
"""

from __future__ import annotations

import math

Quaternion = tuple[float, float, float, float]


def quaternion_from_euler(phi: float, theta: float, psi: float) -> Quaternion:
    """The unit quaternion ``(w, x, y, z)`` of Z-Y-X Euler angles (rad)."""
    cr, sr = math.cos(phi / 2), math.sin(phi / 2)
    cp, sp = math.cos(theta / 2), math.sin(theta / 2)
    cy, sy = math.cos(psi / 2), math.sin(psi / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


def euler_from_quaternion(q: Quaternion) -> tuple[float, float, float]:
    """Z-Y-X Euler angles ``(phi, theta, psi)`` (rad) of a quaternion ``(w, x, y, z)``,
    normalised first; pitch is clipped to +-pi/2 at the singularity."""
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    phi = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    theta = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    psi = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return phi, theta, psi


def rotate(q: Quaternion, v: tuple[float, float, float]) -> tuple[float, float, float]:
    """``v`` rotated by the unit quaternion ``q`` ``(w, x, y, z)`` (normalised first): a
    body vector into the world for an attitude; the conjugate ``(w, -x, -y, -z)`` goes
    back."""
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    vx, vy, vz = v
    # t = 2 (q_vec x v); v' = v + w t + q_vec x t
    tx, ty, tz = 2 * (y * vz - z * vy), 2 * (z * vx - x * vz), 2 * (x * vy - y * vx)
    return (vx + w * tx + (y * tz - z * ty), vy + w * ty + (z * tx - x * tz),
            vz + w * tz + (x * ty - y * tx))
