"""An estimate as what ROS tools read: the contents of ``nav_msgs/Odometry``,
``sensor_msgs/NavSatFix`` and a ``geometry_msgs/TransformStamped``, independent of any transport.

Every output that leaves ddfuse (the ROS node's topics, ``estimates.mcap``, the Foxglove live
view) is built from these, so that the equations (yaw to quaternion, the planar covariance laid
into ROS's 6x6, the local frame back to latitude/longitude) are written once; each transport
only copies fields into its own message classes.

Frames (REP-103/105): the pose is in the local ENU frame (``Config.local_frame``, x east, y
north, yaw from east counter-clockwise), the twist in the robot's base frame
(``Config.base_frame``, x forward, z up). ddfuse estimates a planar pose: z, roll and pitch are
held at 0, and their variances set to ``PLANAR_VARIANCE`` (the planar model's assumption,
stated as a tight prior as robot_localization's ``two_d_mode`` does), never left at 0, which
many consumers read as "unknown" or reject as singular.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from ddfuse.estimation import geodesy
from ddfuse.estimation.estimator import Estimate

__all__ = ["FixOut", "OdometryOut", "PLANAR_VARIANCE", "TWIST_UNKNOWN_VARIANCE", "TransformOut",
           "fix_of", "odometry_of", "transform_of", "yaw_quaternion"]

PLANAR_VARIANCE = 1e-6  # m^2 or rad^2: z, roll, pitch (and their rates), held at 0
# m^2/s^2 or rad^2/s^2: a twist the estimator does not estimate (a landmark EKF's); huge, so
# that no consumer fuses the zeros it comes with
TWIST_UNKNOWN_VARIANCE = 1e6
# the state names the estimators give their forward speed and yaw rate
_SPEED_NAMES = ("v",)
_YAW_RATE_NAMES = ("w", "psi_dot", "yaw_rate")

_POSE_INDEX = (0, 1, 5)  # ROS 6x6 rows (x, y, z, roll, pitch, yaw): where (x, y, yaw) go
_PLANAR_INDEX = (2, 3, 4)


@dataclass(frozen=True, slots=True)
class OdometryOut:
    """The fields of a ``nav_msgs/Odometry``. ``stamp``: s (the estimate's time, from the
    header stamps). ``position`` m and ``orientation`` (x, y, z, w) in ``frame_id``;
    ``linear`` m/s and ``angular`` rad/s in ``child_frame_id``; each covariance 36 floats,
    row-major over (x, y, z, roll, pitch, yaw), symmetric positive definite."""

    stamp: float
    frame_id: str
    child_frame_id: str
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    pose_covariance: tuple[float, ...]
    linear: tuple[float, float, float]
    angular: tuple[float, float, float]
    twist_covariance: tuple[float, ...]


@dataclass(frozen=True, slots=True)
class FixOut:
    """The fields of a ``sensor_msgs/NavSatFix``: ``latitude``/``longitude`` deg (WGS-84),
    ``altitude`` m (the datum's: the pose is planar), ``position_covariance`` 9 floats, m^2,
    row-major over (east, north, up) as REP-145 and NavSatFix define it, type KNOWN (3)."""

    stamp: float
    frame_id: str
    latitude: float
    longitude: float
    altitude: float
    position_covariance: tuple[float, ...]
    position_covariance_type: int = 3  # sensor_msgs/NavSatFix COVARIANCE_TYPE_KNOWN


@dataclass(frozen=True, slots=True)
class TransformOut:
    """The fields of a ``geometry_msgs/TransformStamped``: the pose of ``child_frame_id`` in
    ``frame_id`` (translation m, rotation (x, y, z, w))."""

    stamp: float
    frame_id: str
    child_frame_id: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation by ``yaw`` rad about z."""
    return (0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw))


def _spd(c: np.ndarray) -> np.ndarray:
    """``c`` symmetrised; NaN where it is not finite (a consumer must not take it as exact)."""
    c = 0.5 * (c + c.T)
    return c if np.all(np.isfinite(c)) else np.full_like(c, math.nan)


def _twist(e: Estimate) -> tuple[float, float, np.ndarray]:
    """(speed m/s, yaw rate rad/s, their 2x2 covariance) from the estimate's state; zeros with
    TWIST_UNKNOWN_VARIANCE where the estimator has no such state."""
    names = e.state_names
    idx = [next((names.index(n) for n in group if n in names), None)
           for group in (_SPEED_NAMES, _YAW_RATE_NAMES)]
    vals = [0.0, 0.0]
    cov = np.diag([TWIST_UNKNOWN_VARIANCE, TWIST_UNKNOWN_VARIANCE])
    if e.state is None:
        return 0.0, 0.0, cov
    for a, i in enumerate(idx):
        if i is None:
            continue
        vals[a] = float(e.state[i])
        if e.state_cov is not None:
            for b, j in enumerate(idx):
                if j is not None:
                    cov[a, b] = e.state_cov[i, j]
    return vals[0], vals[1], _spd(cov)


def odometry_of(e: Estimate, frame_id: str, child_frame_id: str) -> OdometryOut:
    """``e`` as the fields of a ``nav_msgs/Odometry`` (module docstring: frames, planar axes).
    The pose covariance is ``e.pose_cov`` (world (x, y, yaw)); the twist (forward speed, yaw
    rate) and its covariance come from ``e.state`` where the estimator estimates them."""
    x, y, yaw = (float(v) for v in e.pose)
    pose = np.zeros((6, 6))
    pose[np.ix_(_POSE_INDEX, _POSE_INDEX)] = _spd(np.asarray(e.pose_cov, dtype=float))
    v, w, tc = _twist(e)
    twist = np.zeros((6, 6))
    twist[np.ix_((0, 5), (0, 5))] = tc
    # lateral speed: the planar model's no-slip assumption, as tight as the planar axes
    for c, i in ((pose, _PLANAR_INDEX), (twist, (1, 2, 3, 4))):
        c[i, i] = PLANAR_VARIANCE
    return OdometryOut(
        stamp=float(e.t), frame_id=frame_id, child_frame_id=child_frame_id,
        position=(x, y, 0.0), orientation=yaw_quaternion(yaw),
        pose_covariance=tuple(pose.ravel().tolist()), linear=(v, 0.0, 0.0),
        angular=(0.0, 0.0, w), twist_covariance=tuple(twist.ravel().tolist()))


def fix_of(e: Estimate, datum: tuple[float, float, float], frame_id: str) -> FixOut:
    """``e``'s position as the fields of a ``sensor_msgs/NavSatFix`` about ``datum`` (lat deg,
    lon deg, alt m: the local frame's origin); ``frame_id`` the frame whose origin the fix
    locates (the base frame). The east/north covariance is ``e.pose_cov``'s position block
    (ENU and the local frame share axes), up ``PLANAR_VARIANCE``."""
    lat, lon, alt = geodesy.enu_to_geodetic(float(e.pose[0]), float(e.pose[1]), 0.0, *datum)
    cov = np.zeros((3, 3))
    cov[:2, :2] = _spd(np.asarray(e.pose_cov, dtype=float)[:2, :2])
    cov[2, 2] = PLANAR_VARIANCE
    return FixOut(stamp=float(e.t), frame_id=frame_id, latitude=float(lat),
                  longitude=float(lon), altitude=float(alt),
                  position_covariance=tuple(cov.ravel().tolist()))


def transform_of(e: Estimate, frame_id: str, child_frame_id: str) -> TransformOut:
    """The transform from ``frame_id`` (local) to ``child_frame_id`` (base) at ``e``: the
    robot's pose, as tf2 broadcasts it."""
    x, y, yaw = (float(v) for v in e.pose)
    return TransformOut(stamp=float(e.t), frame_id=frame_id, child_frame_id=child_frame_id,
                        translation=(x, y, 0.0), rotation=yaw_quaternion(yaw))
