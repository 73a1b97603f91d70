"""Rotations between a sensor's frame and the robot body, in plain math (called per message).

A mount is given as roll, pitch, yaw (rad) of the sensor frame relative to base_link, as a TF
from base_link to the sensor would state it: R_body_sensor = Rz(yaw) Ry(pitch) Rx(roll), so a
vector measured in the sensor frame is R_body_sensor @ v in the body frame.
"""

from __future__ import annotations

import math

Mat3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
IDENTITY: Mat3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
GRAVITY = 9.80665  # m/s^2, standard gravity (local values differ by < 0.03 m/s^2)


def rpy_matrix(roll: float, pitch: float, yaw: float) -> Mat3:
    """R = Rz(yaw) Ry(pitch) Rx(roll), rows as tuples."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return (
        (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
        (sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
        (-sp, cp * sr, cp * cr),
    )


def quat_matrix(x: float, y: float, z: float, w: float) -> Mat3:
    """Rotation matrix of a unit quaternion (x, y, z, w); normalises it first."""
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return (
        (1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)),
        (2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)),
        (2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)),
    )


def rotate(r: Mat3, v: tuple[float, float, float]) -> tuple[float, float, float]:
    a, b, c = v
    return (r[0][0] * a + r[0][1] * b + r[0][2] * c,
            r[1][0] * a + r[1][1] * b + r[1][2] * c,
            r[2][0] * a + r[2][1] * b + r[2][2] * c)


def rotated_variance(r: Mat3, cov9: tuple[float, ...], row: int) -> float:
    """Variance of component ``row`` of R v, for v with 3x3 covariance ``cov9`` (row-major)."""
    a = r[row]
    return sum(a[i] * cov9[3 * i + j] * a[j] for i in range(3) for j in range(3))


def body_x_axis(q: tuple[float, float, float, float], mount: Mat3
                ) -> tuple[float, float, float]:
    """The body's forward axis in the world, scaled by the quaternion's squared norm (no
    normalisation), given the sensor's orientation quaternion q (world <- sensor, (x, y, z, w))
    and its mount R_body_sensor: the first column of R_wb = R_ws R_bs^T, i.e. R_ws @ (row 0 of
    R_bs); the full matrix is not formed."""
    x, y, z, w = q
    m0, m1, m2 = mount[0]
    return ((w * w + x * x - y * y - z * z) * m0 + 2 * (x * y - z * w) * m1
            + 2 * (x * z + y * w) * m2,
            2 * (x * y + z * w) * m0 + (w * w - x * x + y * y - z * z) * m1
            + 2 * (y * z - x * w) * m2,
            2 * (x * z - y * w) * m0 + 2 * (y * z + x * w) * m1
            + (w * w - x * x - y * y + z * z) * m2)


def body_yaw(q: tuple[float, float, float, float], mount: Mat3) -> float:
    """Yaw (rad, about world z from world x) of the body frame (``body_x_axis``; atan2 ignores
    the quaternion's norm)."""
    ux, uy, _ = body_x_axis(q, mount)
    return math.atan2(uy, ux)


def body_x_tilt(q: tuple[float, float, float, float], mount: Mat3,
                ocov9: tuple[float, ...] | None = None) -> tuple[float, float]:
    """The world-z (up) component of the body's forward axis (``body_x_axis``, normalised),
    sin(climb angle), and its variance from the orientation covariance ``ocov9`` (rad^2, about
    the world axes, row-major; None or a non-finite one: 0). A small world rotation d turns the
    axis u by d x u, whose z is d_x u_y - d_y u_x: only roll and pitch errors about the
    horizontal axes count."""
    x, y, z, w = q
    n = x * x + y * y + z * z + w * w
    ux, uy, uz = (c / n for c in body_x_axis(q, mount))
    var = 0.0
    if ocov9 is not None:
        var = uy * uy * ocov9[0] - 2.0 * uy * ux * ocov9[1] + ux * ux * ocov9[4]
        if not (math.isfinite(var) and var > 0.0):
            var = 0.0
    return uz, var


def dot_row(r: Mat3, row: int, v: tuple[float, float, float]) -> float:
    """Component ``row`` of R v."""
    a = r[row]
    return a[0] * v[0] + a[1] * v[1] + a[2] * v[2]


def yaw_of_quat(q: tuple[float, float, float, float]) -> float:
    """Yaw (rad) of a quaternion (x, y, z, w), ZYX convention."""
    x, y, z, w = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
