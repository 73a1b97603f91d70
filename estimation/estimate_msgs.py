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

__all__ = ["tf_source", "FixColumns", "FixOut", "OdometryOut", "PLANAR_VARIANCE", "PoseColumns",
           "TWIST_UNKNOWN_VARIANCE", "TransformOut", "UNKNOWN_TWIST_COVARIANCE", "fix_columns",
           "fix_covariances", "fix_of", "odometry_of", "pose_columns", "pose_covariances",
           "transform_of", "yaw_quaternion", "yaw_quaternions"]

PLANAR_VARIANCE = 1e-6  # m^2 or rad^2: z, roll, pitch (and their rates), held at 0
# m^2/s^2 or rad^2/s^2: a twist the estimator does not estimate (a landmark EKF's); huge, so
# that no consumer fuses the zeros it comes with
TWIST_UNKNOWN_VARIANCE = 1e6
# the state names the estimators give their forward speed and yaw rate
_SPEED_NAMES = ("v",)
_YAW_RATE_NAMES = ("w", "psi_dot", "yaw_rate")

_POSE_INDEX = (0, 1, 5)  # ROS 6x6 rows (x, y, z, roll, pitch, yaw): where (x, y, yaw) go
_PLANAR_INDEX = (2, 3, 4)
# the same as flat indices into the row-major 36: where a 3x3 (x, y, yaw) block's 9 cells go,
# and the planar axes' diagonal
_POSE_CELLS = np.array([6 * i + j for i in _POSE_INDEX for j in _POSE_INDEX])
_PLANAR_CELLS = np.array([7 * i for i in _PLANAR_INDEX])
_TWIST_CELLS = np.array([0, 5, 30, 35])  # (speed, yaw rate) 2x2 into the twist's 6x6
_TIGHT_RATE_CELLS = np.array([7 * i for i in (1, 2, 3, 4)])  # lateral speed, planar rates


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


def tf_source(names, choice: str | None = None) -> str | None:
    """Of the estimators ``names``, the one whose pose is broadcast as the TF local -> base
    (the node, estimates.mcap): ``choice`` (config ``node.tf``; 'none' for no TF) when it is
    among them, else the smoother when it runs, else the first; None for no names."""
    names = list(names)
    if choice == "none":
        return None
    if choice in names:
        return choice
    return "smoother" if "smoother" in names else (names[0] if names else None)


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation by ``yaw`` rad about z."""
    return tuple(yaw_quaternions(np.array([yaw], dtype=float))[0].tolist())


def yaw_quaternions(yaw: np.ndarray) -> np.ndarray:
    """(N, 4) (x, y, z, w) of rotations by ``yaw`` (N,) rad about z."""
    yaw = np.asarray(yaw, dtype=float)
    q = np.zeros((len(yaw), 4))
    q[:, 2], q[:, 3] = np.sin(0.5 * yaw), np.cos(0.5 * yaw)
    return q


def _spd(c: np.ndarray) -> np.ndarray:
    """``c`` (..., k, k) symmetrised; all NaN where a matrix is not finite (a consumer must not
    take it as exact)."""
    c = 0.5 * (c + np.swapaxes(c, -1, -2))
    bad = ~np.isfinite(c).all(axis=(-2, -1))
    if np.any(bad):
        c[bad] = math.nan
    return c


def pose_covariances(pose_cov: np.ndarray) -> np.ndarray:
    """(N, 36): the planar pose covariances ``pose_cov`` (N, 3, 3) over world (x, y, yaw) laid
    into ROS's 6x6 (row-major over x, y, z, roll, pitch, yaw), the planar axes at
    PLANAR_VARIANCE."""
    c = np.asarray(pose_cov, dtype=float).reshape(-1, 3, 3)
    out = np.zeros((len(c), 36))
    out[:, _POSE_CELLS] = _spd(c).reshape(-1, 9)
    out[:, _PLANAR_CELLS] = PLANAR_VARIANCE
    return out


def _twist_covariance(tc: np.ndarray) -> np.ndarray:
    """(36,): the (speed, yaw rate) covariance ``tc`` (2, 2) in ROS's 6x6; the lateral speed
    (the planar model's no-slip assumption) and the planar rates as tight as the planar axes."""
    twist = np.zeros(36)
    twist[_TWIST_CELLS] = np.asarray(tc, dtype=float).ravel()
    twist[_TIGHT_RATE_CELLS] = PLANAR_VARIANCE
    return twist


# the twist covariance of an estimate without a twist (a track's samples: t, pose, pose_cov)
UNKNOWN_TWIST_COVARIANCE = tuple(
    _twist_covariance(np.diag([TWIST_UNKNOWN_VARIANCE, TWIST_UNKNOWN_VARIANCE])).tolist())


@dataclass(frozen=True)
class PoseColumns:
    """N estimates' pose as the columns of ``nav_msgs/Odometry``'s pose and a TF (what
    ``odometry_of`` and ``transform_of`` give one by one): ``stamp`` (N,) s, ``position``
    (N, 3) m, ``orientation`` (N, 4) (x, y, z, w), ``pose_covariance`` (N, 36)."""

    stamp: np.ndarray
    position: np.ndarray
    orientation: np.ndarray
    pose_covariance: np.ndarray


@dataclass(frozen=True)
class FixColumns:
    """N estimates as the columns of ``sensor_msgs/NavSatFix`` (what ``fix_of`` gives one by
    one): ``stamp`` (N,) s, ``latitude``/``longitude`` (N,) deg, ``altitude`` (N,) m,
    ``position_covariance`` (N, 9) m^2 over (east, north, up)."""

    stamp: np.ndarray
    latitude: np.ndarray
    longitude: np.ndarray
    altitude: np.ndarray
    position_covariance: np.ndarray


def pose_columns(t: np.ndarray, pose: np.ndarray, pose_cov: np.ndarray) -> PoseColumns:
    """A track's samples, ``t`` (N,) s, ``pose`` (N, 3) (x m, y m, yaw rad) and ``pose_cov``
    (N, 3, 3) in the local frame, as ``PoseColumns``: a long run's estimates at once."""
    pose = np.asarray(pose, dtype=float).reshape(-1, 3)
    position = np.zeros((len(pose), 3))
    position[:, :2] = pose[:, :2]
    return PoseColumns(np.asarray(t, dtype=float), position, yaw_quaternions(pose[:, 2]),
                       pose_covariances(pose_cov))


def fix_columns(t: np.ndarray, pose: np.ndarray, pose_cov: np.ndarray,
                datum: tuple[float, float, float]) -> FixColumns:
    """A track's samples (as ``pose_columns``) as ``FixColumns`` about ``datum`` (lat deg,
    lon deg, alt m: the local frame's origin); the covariance as ``fix_covariances``."""
    pose = np.asarray(pose, dtype=float).reshape(-1, 3)
    lat, lon, alt = geodesy.enu_to_geodetic(pose[:, 0], pose[:, 1], np.zeros(len(pose)), *datum)
    return FixColumns(np.asarray(t, dtype=float), np.atleast_1d(lat).astype(float),
                      np.atleast_1d(lon).astype(float), np.atleast_1d(alt).astype(float),
                      fix_covariances(pose_cov))


def fix_covariances(pose_cov: np.ndarray) -> np.ndarray:
    """(N, 9) m^2 over (east, north, up): the position block of the pose covariances
    ``pose_cov`` (N, 3, 3) (ENU and the local frame share axes), up PLANAR_VARIANCE."""
    c = np.asarray(pose_cov, dtype=float).reshape(-1, 3, 3)
    cov = np.zeros((len(c), 3, 3))
    cov[:, :2, :2] = _spd(c[:, :2, :2])
    cov[:, 2, 2] = PLANAR_VARIANCE
    return cov.reshape(-1, 9)


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
    v, w, tc = _twist(e)
    return OdometryOut(
        stamp=float(e.t), frame_id=frame_id, child_frame_id=child_frame_id,
        position=(float(e.pose[0]), float(e.pose[1]), 0.0),
        orientation=yaw_quaternion(float(e.pose[2])),
        pose_covariance=tuple(pose_covariances(e.pose_cov)[0].tolist()), linear=(v, 0.0, 0.0),
        angular=(0.0, 0.0, w), twist_covariance=tuple(_twist_covariance(tc).tolist()))


def fix_of(e: Estimate, datum: tuple[float, float, float], frame_id: str) -> FixOut:
    """``e``'s position as the fields of a ``sensor_msgs/NavSatFix`` about ``datum`` (lat deg,
    lon deg, alt m: the local frame's origin); ``frame_id`` the frame whose origin the fix
    locates (the base frame). The east/north covariance is ``e.pose_cov``'s position block
    (ENU and the local frame share axes), up ``PLANAR_VARIANCE``."""
    # scalars through geodesy: its arithmetic on numpy scalars is 3x faster than on (1,) arrays
    lat, lon, alt = geodesy.enu_to_geodetic(float(e.pose[0]), float(e.pose[1]), 0.0, *datum)
    return FixOut(stamp=float(e.t), frame_id=frame_id, latitude=float(lat),
                  longitude=float(lon), altitude=float(alt),
                  position_covariance=tuple(fix_covariances(e.pose_cov)[0].tolist()))


def transform_of(e: Estimate, frame_id: str, child_frame_id: str) -> TransformOut:
    """The transform from ``frame_id`` (local) to ``child_frame_id`` (base) at ``e``: the
    robot's pose, as tf2 broadcasts it (the position and orientation of ``odometry_of``)."""
    return TransformOut(stamp=float(e.t), frame_id=frame_id, child_frame_id=child_frame_id,
                        translation=(float(e.pose[0]), float(e.pose[1]), 0.0),
                        rotation=yaw_quaternion(float(e.pose[2])))
