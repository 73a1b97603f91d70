"""Measurement types shared by every estimator.

All units are SI; time ``t`` is float seconds taken from the message's header stamp.
Angles are radians, counter-clockwise positive. Frames:

* body: x forward, y left, z up (REP 103), after the sensor's mount rotation has been applied.
* local: the ENU frame about the datum (x east, y north); with a landmark map, the map's frame.
  Heading (yaw) is measured from the local x axis, counter-clockwise.

``sensor`` names the configured sensor the measurement came from (its topic unless the config
gives a name), so that estimators can look up per-sensor settings and report per-sensor statistics.
Variances are those the estimator should use: from the config's ``noise`` when given, else from
the message's covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass(slots=True)
class WheelOdometry:
    """Body-frame forward speed and yaw rate from wheel odometry (nav_msgs/Odometry twist,
    geometry_msgs/TwistStamped). A component that the config does not ``use`` is None."""

    t: float
    v: float | None  # m/s, body x
    yaw_rate: float | None  # rad/s, about body z
    v_var: float  # (m/s)^2
    yaw_rate_var: float  # (rad/s)^2
    sensor: str = "odometry"


@dataclass(slots=True)
class WheelSpeeds:
    """Left and right wheel angular speeds (sensor_msgs/JointState velocity), rad/s.
    Forward speed is r (w_l + w_r) / 2, yaw rate r (w_r - w_l) / L."""

    t: float
    left: float  # rad/s
    right: float  # rad/s
    left_var: float  # (rad/s)^2
    right_var: float  # (rad/s)^2
    sensor: str = "wheels"

    def twist(self, wheel_radius: float, track_width: float
              ) -> tuple[float, float, float, float]:
        """(v m/s, yaw rate rad/s, var(v) (m/s)^2, var(yaw rate) (rad/s)^2) for wheel radius
        and track width in m, the two wheels' errors independent. v and the yaw rate are
        correlated only when the wheels' variances differ; that covariance is not returned."""
        r, L = wheel_radius, track_width
        s = self.left_var + self.right_var
        return (0.5 * r * (self.left + self.right), r * (self.right - self.left) / L,
                0.25 * r * r * s, r * r * s / (L * L))


@dataclass(slots=True)
class GyroYawRate:
    """Yaw rate about body z from a gyro, rad/s, after the mount rotation."""

    t: float
    yaw_rate: float  # rad/s
    var: float  # (rad/s)^2
    sensor: str = "imu"


@dataclass(slots=True)
class Heading:
    """Absolute yaw of the body frame as the sensor reports it, rad, wrapped to (-pi, pi].

    It may differ from local ENU heading by an offset (magnetic declination, a disturbed
    magnetometer, a sensor that starts at zero); the sensor's ``heading_offset`` config says how.
    ``source`` is 'imu_orientation', 'compass' or 'pose'."""

    t: float
    yaw: float  # rad
    var: float  # rad^2
    sensor: str = "imu"
    source: str = "imu_orientation"


@dataclass(slots=True)
class ForwardAccel:
    """Forward acceleration along body x, m/s^2: the IMU's specific force after the mount
    rotation, less gravity's component along body x from the IMU's orientation (config
    ``accel_gravity: orientation``, the default) or taken as is (``level``)."""

    t: float
    accel: float  # m/s^2
    var: float  # (m/s^2)^2
    sensor: str = "imu"


@dataclass(slots=True)
class GpsFix:
    """A GNSS fix (sensor_msgs/NavSatFix) and its position in the local ENU frame.

    ``cov`` is the 3x3 ENU position covariance, m^2 (NavSatFix's own order: east, north, up).
    ``enu`` is filled by the stream once the datum is known: (east, north, up) in metres, in the
    ENU frame at ``datum`` (lat deg, lon deg, alt m), which the stream fills alongside it.
    ``status`` is NavSatStatus.status (-1 no fix, 0 fix, 1 SBAS, 2 GBAS). ``odometry_agrees``
    is the GPS watch's verdict on the fix (``estimation.gps_watch``): whether its distance from
    an earlier fix matches the odometry's dead-reckoned distance (None: not compared)."""

    t: float
    lat: float  # deg
    lon: float  # deg
    alt: float  # m, above the WGS-84 ellipsoid
    cov: np.ndarray  # (3, 3), m^2, ENU
    status: int = 0
    sensor: str = "gps"
    enu: tuple[float, float, float] | None = None
    datum: tuple[float, float, float] | None = None
    odometry_agrees: bool | None = None


@dataclass(slots=True)
class LandmarkObservation:
    """Range and bearing from the body origin to a known landmark.

    ``bearing`` is measured in the body frame from the x axis, counter-clockwise, rad.
    ``has_bearing`` False means a range-only sighting (bearing is then meaningless)."""

    t: float
    landmark_id: str
    range: float  # m
    bearing: float  # rad
    range_var: float  # m^2
    bearing_var: float  # rad^2
    has_bearing: bool = True
    sensor: str = "landmarks"


@dataclass(slots=True)
class GroundTruthPose:
    """A reference pose in the local frame (x east, y north, yaw from x), for scoring only."""

    t: float
    x: float  # m
    y: float  # m
    yaw: float  # rad
    sensor: str = "ground_truth"


# truth samples further apart than this around the start are not interpolated between (s)
TRUTH_INTERPOLATION_GAP = 0.25


def truth_at_start(t: np.ndarray, pose: np.ndarray, t0: float | None) -> GroundTruthPose | None:
    """The truth pose at the stream's start ``t0`` (s) from samples at stamps ``t`` (N,) s,
    sorted, and poses (N, 3) (x m, y m, yaw rad): interpolated between the samples on either
    side when they are at most TRUTH_INTERPOLATION_GAP apart (a robot moving at the start would
    otherwise begin where the next sample is), else the first sample at or after t0 (the last
    one when none is). None without samples."""
    if not len(t):
        return None
    t0 = -math.inf if t0 is None else t0
    i = min(int(np.searchsorted(t, t0 - 1e-9)), len(t) - 1)
    x, y, yaw = (float(v) for v in pose[i])
    if i > 0 and t[i - 1] < t0 < t[i] and t[i] - t[i - 1] <= TRUTH_INTERPOLATION_GAP:
        a = pose[i - 1]
        w = (t0 - t[i - 1]) / (t[i] - t[i - 1])
        dyaw = (yaw - a[2] + math.pi) % (2.0 * math.pi) - math.pi
        x, y = a[0] + w * (x - a[0]), a[1] + w * (y - a[1])
        yaw = (a[2] + w * dyaw + math.pi) % (2.0 * math.pi) - math.pi
        return GroundTruthPose(t0, float(x), float(y), float(yaw))
    return GroundTruthPose(float(t[i]), x, y, yaw)


Measurement = (
    WheelOdometry
    | WheelSpeeds
    | GyroYawRate
    | Heading
    | ForwardAccel
    | GpsFix
    | LandmarkObservation
    | GroundTruthPose
)
"""Anything an estimator may be fed. Estimators ignore GroundTruthPose."""

_isfinite = math.isfinite

# Per kind, whether the numbers an estimator reads are finite: one isfinite of their sum (a
# NaN or an infinity in any term makes it non-finite; only finite values near 1e308 could
# overflow it, none a sensor gives): cheap enough for every message. What a message leaves
# NaN by design is not read: the variance of an odometry quantity not used, a range-only
# sighting's bearing, a NavSatFix truth's yaw, a fix's altitude (NaN when unknown).
_FINITE = {
    WheelOdometry: lambda m: _isfinite(m.t + (0.0 if m.v is None else m.v + m.v_var)
                                       + (0.0 if m.yaw_rate is None
                                          else m.yaw_rate + m.yaw_rate_var)),
    WheelSpeeds: lambda m: _isfinite(m.t + m.left + m.right + m.left_var + m.right_var),
    GyroYawRate: lambda m: _isfinite(m.t + m.yaw_rate + m.var),
    Heading: lambda m: _isfinite(m.t + m.yaw + m.var),
    ForwardAccel: lambda m: _isfinite(m.t + m.accel + m.var),
    LandmarkObservation: lambda m: _isfinite(m.t + m.range + m.range_var + (
        m.bearing + m.bearing_var if m.has_bearing else 0.0)),
    GroundTruthPose: lambda m: _isfinite(m.t + m.x + m.y),
    GpsFix: lambda m: _isfinite(m.t + m.lat + m.lon + (m.enu[0] + m.enu[1] if m.enu is not None
                                                       else 0.0))
    and bool(np.isfinite(m.cov[:2, :2]).all()),
}


def is_finite(m) -> bool:
    """Whether the numbers an estimator reads from ``m`` are finite (its stamp included; a GPS
    fix's lat, lon, horizontal covariance and ENU position; see ``_FINITE``). The bag reader
    and ``ddfuse.estimation.live`` reject messages with non-finite fields; a hand-built measurement
    may still hold one, and a NaN handed to gtsam poisons the whole window."""
    check = _FINITE.get(type(m))
    return True if check is None else check(m)


@dataclass(slots=True)
class Stream:
    """One time-ordered list of measurements read from a bag, with what the reader learned.

    ``datum`` is the (lat deg, lon deg, alt m) of the local ENU origin, None without GPS.
    ``rejected`` counts single messages dropped as invalid, by (topic, reason).
    ``landmarks`` maps landmark id to its (x, y) in the local frame, m."""

    measurements: list
    ground_truth: list[GroundTruthPose] = field(default_factory=list)
    datum: tuple[float, float, float] | None = None
    landmarks: dict[str, tuple[float, float]] = field(default_factory=dict)
    rejected: dict[tuple[str, str], int] = field(default_factory=dict)
    source: str = ""
    t0: float = 0.0
    t1: float = 0.0

    @property
    def duration(self) -> float:
        return self.t1 - self.t0
