"""A local heading Theta_l (seed 000): a yaw in the robot's start frame, with no north
reference -- an odometry's pose orientation (nav_msgs/Odometry), an IMU's orientation without a
magnetometer (sensor_msgs/Imu), a pose (geometry_msgs/PoseStamped).

It becomes a ``Heading`` with source 'pose': yaw = psi + offset, the offset to ENU the robot's
unknown start yaw (so ``heading_offset`` defaults to 'estimate'; a number when the start yaw is
known). The unicycle EKF and the smoother fuse it as any heading with an offset; ekf_igvc as
seed 000's Theta_l row on psi (``igvc_measurements.heading_rows`` with ``local``). One orientation
topic gives one heading row only (``config._one_heading_per_reading``, errata 000 #40).

Variance: the config's ``noise.yaw`` (rad), else an Imu's orientation_covariance[8]; an
odometry's or a pose's message carries none that ddfuse reads, so those need ``noise.yaw``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from ddfuse.estimation.config import SensorConfig
from ddfuse.estimation.frames import IDENTITY, body_yaw, rpy_matrix
from ddfuse.estimation.measurements import Heading
from ddfuse.estimation.reject import Reject

__all__ = ["local_heading_converter"]


def local_heading_converter(s: SensorConfig, key: str) -> Callable[[tuple], list]:
    """The converter of local heading ``s`` (config key ``key``): a record of an Odometry
    (t, position, quaternion, ...; 6 fields), an Imu (t, quaternion, orientation covariance,
    ...; 7) or a PoseStamped (t, position, quaternion; 3) -> one Heading (source 'pose')."""
    mount = IDENTITY if s.mount_rpy == (0.0, 0.0, 0.0) else rpy_matrix(*s.mount_rpy)
    std = s.noise.get("yaw")
    fixed = None if std is None else std * std
    name = s.name

    def convert(rec: tuple) -> list:
        t = rec[0]
        if len(rec) == 7:  # Imu
            q, ocov = rec[1], rec[2]
            if ocov[0] == -1.0:
                raise Reject("orientation not provided (orientation_covariance[0] = -1)")
            var = fixed if fixed is not None else ocov[8]
        else:  # Odometry, PoseStamped
            q, var = rec[2], fixed
        if var is None:
            raise Reject(f"the message carries no yaw variance; set {key}.noise.yaw")
        if not (math.isfinite(var) and var > 0.0):
            raise Reject(f"orientation_covariance[8] is {var!r} (zero or non-finite); set "
                         f"{key}.noise.yaw")
        if not (math.isfinite(t) and all(math.isfinite(c) for c in q)):
            raise Reject("non-finite stamp or orientation")
        if not abs(sum(c * c for c in q) - 1.0) < 2e-3:
            raise Reject("orientation is not a unit quaternion")
        return [Heading(t, body_yaw(q, mount), var, name, "pose")]

    return convert
