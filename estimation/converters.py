"""Converters from a ROS message's extracted fields to measurements, one per sensor kind.

A converter takes the record a ``ddfuse.estimation.rosmsg`` extractor gives for one message
(header stamp first, s) and returns the measurements of ``ddfuse.estimation.measurements`` it
holds: SI units, body frame after the sensor's mount rotation (``SensorConfig.mount_rpy``),
variances from the config's ``noise`` (std) where given, else from the message. A message that
cannot be used raises ``Reject`` with the reason that is counted (``Stream.rejected``); one whose
other fields are still good carries their measurements in ``Reject.kept``.

Kinds: ``odometry`` (Odometry / TwistStamped -> WheelOdometry, speed along the slope projected
on the horizontal when the config names an IMU's ``slope``), ``imu`` (Imu -> Heading,
GyroYawRate, ForwardAccel with gravity removed unless ``accel_gravity: level``), ``gps``
(NavSatFix -> GpsFix, geodetic; ENU is set by the reader once the datum is known), ``wheels``
(JointState -> WheelSpeeds, rad/s), ``landmarks`` (range m / bearing rad sightings, checked
against the map), ``magnetometer`` (MagneticField -> global Heading,
``ddfuse.estimation.magnetometer``), ``local_heading`` (an orientation without north -> local
Heading, ``ddfuse.estimation.local_heading``) and the ground truth (pose or NavSatFix). The bag
reader (``ddfuse.estimation.bags``) and the live converter (``ddfuse.estimation.live``) use the same
converters (``converter``).
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable

import numpy as np
from ddfuse.estimation import geodesy, rosmsg
from ddfuse.estimation.config import (
    DEFAULT_GPS_MIN_STD,
    LANDMARK_NOT_IN_MAP,
    Config,
    SensorConfig,
)
from ddfuse.estimation.frames import (
    GRAVITY,
    IDENTITY,
    body_x_tilt,
    body_yaw,
    dot_row,
    rotate,
    rotated_variance,
    rpy_matrix,
)
from ddfuse.estimation.local_heading import local_heading_converter
from ddfuse.estimation.magnetometer import magnetometer_converter
from ddfuse.estimation.measurements import (
    ForwardAccel,
    GpsFix,
    GroundTruthPose,
    GyroYawRate,
    Heading,
    LandmarkObservation,
    WheelOdometry,
    WheelSpeeds,
)
from ddfuse.estimation.reject import Reject

__all__ = ["CONVERTERS", "NULL_ISLAND", "Reject", "converter", "gps_fix",
           "ground_truth_converter", "slope_cells", "unknown_landmarks_note"]

log = logging.getLogger(__name__)

NULL_ISLAND = "latitude and longitude both 0: a receiver's placeholder, not a fix"


def _var(sensor: SensorConfig, key: str, name: str, noise_key: str, value: float | None) -> float:
    """The variance to use: the config's noise (std) if given, else the message's value."""
    std = sensor.noise.get(noise_key)
    if std is not None:
        return std * std
    if value is None:
        raise Reject(f"{name}: message carries no covariance; set {key}.noise.{noise_key}")
    if not (math.isfinite(value) and value > 0.0):
        raise Reject(f"{name} is {value!r} (zero or non-finite); set {key}.noise.{noise_key}")
    return value


def _finite(*vals: float) -> bool:
    return all(math.isfinite(v) for v in vals)


def _odometry_converter(s: SensorConfig, key: str, slopes: dict | None = None
                        ) -> Callable[[tuple], list]:
    mount = IDENTITY if s.mount_rpy == (0.0, 0.0, 0.0) else rpy_matrix(*s.mount_rpy)
    use_v, use_w = "v" in s.use, "yaw_rate" in s.use
    name = s.name
    # with `slope`: the IMU's latest cos(climb) (its converter writes it, ``slope_cells``)
    slope = slopes.get(s.slope) if s.slope is not None and slopes else None

    def convert(rec: tuple) -> list:
        t, lin, ang, cov = rec[0], rec[-3], rec[-2], rec[-1]
        if mount is not IDENTITY:
            lin, ang = rotate(mount, lin), rotate(mount, ang)
        v, w = lin[0], ang[2]
        # a NaN in a component the config does not use costs nothing (use: [yaw_rate])
        if not (math.isfinite(t) and (math.isfinite(v) or not use_v)
                and (math.isfinite(w) or not use_w)):
            raise Reject("non-finite stamp or twist")
        cv = cw = None
        if cov is not None:
            if mount is IDENTITY:
                cv, cw = cov[0], cov[35]
            else:
                lin9 = tuple(cov[6 * i + j] for i in range(3) for j in range(3))
                ang9 = tuple(cov[6 * (i + 3) + j + 3] for i in range(3) for j in range(3))
                cv, cw = rotated_variance(mount, lin9, 0), rotated_variance(mount, ang9, 2)
        var_v = _var(s, key, "twist.covariance[0]", "v", cv) if use_v else math.nan
        if slope is not None and use_v:
            # the wheels roll along the slope; the planar estimators move on the horizontal
            c = slope[0]
            v, var_v = v * c, var_v * c * c
        return [WheelOdometry(
            t, v if use_v else None, w if use_w else None, var_v,
            _var(s, key, "twist.covariance[35]", "yaw_rate", cw) if use_w else math.nan,
            name)]

    return convert


def _imu_converter(s: SensorConfig, key: str, slopes: dict | None = None
                   ) -> Callable[[tuple], list]:
    mount = IDENTITY if s.mount_rpy == (0.0, 0.0, 0.0) else rpy_matrix(*s.mount_rpy)
    # an odometry sensor's `slope` names this IMU: its latest cos(climb) goes in the cell the
    # odometry's converter reads (``slope_cells``)
    slope = slopes.get(s.name) if slopes else None
    use_yaw, use_w, use_a = "yaw" in s.use, "yaw_rate" in s.use, "accel" in s.use
    level = s.accel_gravity == "level"
    gravity_why = f", needed to remove gravity from the acceleration ({key}.accel_gravity: level " \
        "takes the ground as level)"
    name = s.name
    # Covariances rarely change between messages: rotate each distinct one once.
    cache: dict[tuple, float] = {}

    def var(field: str, noise_key: str, cov9: tuple, row: int) -> float:
        k = (field, cov9)
        v = cache.get(k)
        if v is None:
            bag_var = cov9[4 * row] if mount is IDENTITY else rotated_variance(mount, cov9, row)
            v = cache[k] = _var(s, key, field, noise_key, bag_var)
        return v

    def check_orientation(q: tuple, ocov: tuple, why: str) -> None:
        if ocov[0] == -1.0:
            raise Reject(f"orientation not provided (orientation_covariance[0] = -1){why}")
        qx, qy, qz, qw = q
        if not abs(qx * qx + qy * qy + qz * qz + qw * qw - 1.0) < 2e-3:
            raise Reject(f"orientation is not a finite unit quaternion{why}")

    def convert(rec: tuple) -> list:
        t, q, ocov, w, wcov, a, acov = rec
        if not math.isfinite(t):
            raise Reject("non-finite stamp")
        out: list = []
        # A bad orientation costs the parts that need it (the yaw; the acceleration, whose
        # gravity it removes), not the message's gyro: one Reject at the end keeps the rest.
        bad_q = None
        if use_yaw or (use_a and not level) or slope is not None:
            try:
                check_orientation(q, ocov, "")
            except Reject as e:
                bad_q = str(e)
        if slope is not None and bad_q is None:  # else the last good one holds
            up = body_x_tilt(q, mount)[0]
            slope[0] = math.sqrt(max(0.0, 1.0 - up * up))
        lost = None
        if use_yaw:
            if bad_q is not None:
                lost = f"{bad_q}: yaw not used"
            else:  # a zero variance rejects the message, as for every field
                out.append(Heading(t, body_yaw(q, mount),
                                   var("orientation_covariance[8]", "yaw", ocov, 2), name,
                                   "imu_orientation"))
        if use_w:
            wz = w[2] if mount is IDENTITY else dot_row(mount, 2, w)
            if not math.isfinite(wz):
                raise Reject("non-finite angular_velocity")
            out.append(GyroYawRate(t, wz, var("angular_velocity_covariance[8]", "yaw_rate",
                                              wcov, 2), name))
        if use_a:
            ax = a[0] if mount is IDENTITY else dot_row(mount, 0, a)
            if not math.isfinite(ax):
                raise Reject("non-finite linear_acceleration")
            va = var("linear_acceleration_covariance[0]", "accel", acov, 0)
            if level:
                out.append(ForwardAccel(t, ax, va, name))
            elif bad_q is not None:
                lost = (f"{bad_q}: yaw not used, nor linear_acceleration (its gravity removal "
                        f"needs the orientation; {key}.accel_gravity: level takes the ground as "
                        "level)" if use_yaw else
                        f"linear_acceleration not used: {bad_q}{gravity_why}")
            else:
                # specific force = acceleration - gravity: on a slope the climb's g sin(angle)
                # is in the reading (errata 000 #24); the tilt's error adds to the variance
                up, vup = body_x_tilt(q, mount, ocov)
                out.append(ForwardAccel(t, ax - GRAVITY * up, va + GRAVITY * GRAVITY * vup, name))
        if lost is not None:
            raise Reject(lost, kept=out)
        return out

    return convert


def gps_fix(rec: tuple, name: str) -> GpsFix:
    """A NavSatFix record (stamp s, status, lat deg, lon deg, alt m, covariance 9-tuple m^2,
    covariance type) as a geodetic GpsFix of sensor ``name``; a NaN altitude becomes 0. Reject
    for NO_FIX, a non-finite stamp, a position out of range or on Null Island."""
    t, status, lat, lon, alt, cov9, _ = rec
    if status < 0:
        raise Reject("status NO_FIX")
    if not math.isfinite(t):
        raise Reject("non-finite stamp")
    if not (_finite(lat, lon) and -90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise Reject("latitude/longitude not finite or out of range")
    if lat == 0.0 and lon == 0.0:
        # no robot stands on Null Island to 1e-9 deg; as the first_fix datum it put every
        # later fix thousands of km away
        raise Reject(NULL_ISLAND)
    if not math.isfinite(alt):
        alt = 0.0  # NavSatFix uses NaN for "no altitude"; the horizontal fix is still good
    return GpsFix(t, lat, lon, alt, np.array(cov9, dtype=float).reshape(3, 3), status, name)


def _gps_converter(s: SensorConfig, key: str) -> Callable[[tuple], list]:
    h = s.noise.get("horizontal")
    vert = s.noise.get("vertical", 2.0 * h if h else None)
    fixed = np.diag([h * h, h * h, vert * vert]) if h else None
    given = s.min_std

    def floor_of(status: int) -> tuple[float, str]:
        std = given if given is not None else DEFAULT_GPS_MIN_STD.get(status, 0.01)
        why = f"{key}.min_std" if given is not None else \
            f"the default for NavSatStatus {status}; set {key}.min_std"
        return std, (f"stated horizontal covariance below the floor ({std:g} m)^2 ({why}); "
                     "the fix is used with the floor")

    floors = {st: floor_of(st) for st in DEFAULT_GPS_MIN_STD}
    warned: list = []  # the first floored fix is logged

    def convert(rec: tuple) -> list:
        fix = gps_fix(rec, s.name)
        if fixed is not None:
            fix.cov = fixed.copy()
            return [fix]
        if rec[6] == 0:
            raise Reject(f"position_covariance_type UNKNOWN; set {key}.noise.horizontal")
        if not geodesy.enu_covariance_is_valid(rec[5]):
            raise Reject(f"position_covariance unusable (not symmetric positive definite); "
                         f"set {key}.noise.horizontal")
        std, floored = floors.get(fix.status) or floor_of(fix.status)
        lam, vec = np.linalg.eigh(fix.cov[:2, :2])
        if lam[0] < std * std:
            if not warned:
                warned.append(lam[0])
                log.warning("%s: a fix states a horizontal variance of %g m^2, below the floor "
                            "(%g m)^2; the floor is used and such fixes counted", s.topic,
                            lam[0], std)
            fix.cov[:2, :2] = (vec * np.maximum(lam, std * std)) @ vec.T
            raise Reject(floored, kept=[fix])
        return [fix]

    return convert


def _wheels_converter(s: SensorConfig, key: str) -> Callable[[tuple], list]:
    left, right = s.joints
    var = s.noise["speed"] ** 2

    def convert(rec: tuple) -> list:
        t, names, vel = rec
        try:
            wl, wr = vel[names.index(left)], vel[names.index(right)]
        except (ValueError, IndexError):
            raise Reject(f"joints {left!r}/{right!r} not both in name[] with a velocity") from None
        if not _finite(t, wl, wr):
            raise Reject("non-finite stamp or velocity")
        return [WheelSpeeds(t, wl, wr, var, var, s.name)]

    return convert


def _landmarks_converter(s: SensorConfig, key: str, landmarks: dict | None = None,
                         unknown: Counter | None = None) -> Callable[[tuple], list]:
    """Sightings of sensor ``s``. With ``landmarks`` (the map, id -> (x, y)) a sighting of an
    id not in it is dropped (``LANDMARK_NOT_IN_MAP``), its id counted in ``unknown``. A range
    of 0 is a range finder's "no return", not a distance."""
    use_b = "bearing" in s.use

    def convert(rec: tuple) -> list:
        t, lid, rng, brg, rv, bv, has_b = rec
        if landmarks is not None and lid not in landmarks:
            if unknown is not None:
                unknown[lid] += 1
            raise Reject(LANDMARK_NOT_IN_MAP)
        if not (_finite(t, rng) and rng > 0.0):
            raise Reject("range not finite or not positive")
        has_b = has_b and use_b
        if has_b and not math.isfinite(brg):
            raise Reject("bearing not finite")
        r_var = _var(s, key, "range_variance", "range", rv)
        b_var = _var(s, key, "bearing_variance", "bearing", bv) if has_b else math.nan
        return [LandmarkObservation(t, lid, rng, brg if has_b else math.nan, r_var, b_var, has_b,
                                    s.name)]

    return convert


def ground_truth_converter(msgtype: str) -> Callable[[tuple], list]:
    """The converter of a ground-truth topic of ``msgtype``: a pose (x, y m, yaw rad from the
    quaternion) or a NavSatFix (geodetic; put into ENU by the reader once the datum is known)."""
    if msgtype == rosmsg.NAVSATFIX:
        # Converted to ENU once the datum is known (see read_stream).
        return lambda rec: [gps_fix(rec, "ground_truth")]

    def convert(rec: tuple) -> list:
        t, p, q = rec[0], rec[1], rec[2]
        if not _finite(t, p[0], p[1], *q):
            raise Reject("non-finite pose")
        x, y, z, w = q
        return [GroundTruthPose(t, p[0], p[1],
                                math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))]

    return convert


CONVERTERS = {
    "odometry": _odometry_converter,
    "imu": _imu_converter,
    "gps": _gps_converter,
    "wheels": _wheels_converter,
    "landmarks": _landmarks_converter,
    "magnetometer": magnetometer_converter,
    "local_heading": local_heading_converter,
}


def slope_cells(cfg: Config) -> dict[str, list[float]]:
    """Per IMU that an odometry sensor's ``slope`` names, a one-element list holding its
    latest cos(climb angle) (1.0 until its first orientation): the IMU's converter writes it,
    the odometry's reads it. Messages are converted in the order they are read, so the climb
    is the IMU's newest at most a reorder window away: the ground's slope changes slowly."""
    return {s.slope: [1.0] for s in cfg.of_kind("odometry") if s.slope is not None}


def converter(kind: str, s: SensorConfig, key: str, landmarks: dict | None = None,
              unknown: Counter | None = None, slopes: dict | None = None
              ) -> Callable[[tuple], list]:
    """The converter of sensor ``s`` (config key ``key``) of ``kind``: the bag reader's and the
    live converter's. A landmark converter checks the sightings' ids against ``landmarks`` (the
    merged map; None: not checked), counting the ids not in it in ``unknown``. ``slopes``: the
    config's ``slope_cells``, shared by all its converters."""
    if kind == "landmarks":
        return _landmarks_converter(s, key, landmarks, unknown)
    if kind in ("odometry", "imu"):
        return CONVERTERS[kind](s, key, slopes)
    return CONVERTERS[kind](s, key)


def unknown_landmarks_note(cfg: Config, landmarks: dict, unknown: Counter) -> str:
    """What to tell about sightings dropped as ``LANDMARK_NOT_IN_MAP``: the map file(s), a few
    of the ids seen (most frequent first) and a few of the map's (a map for another run)."""
    maps = list(dict.fromkeys(str(s.map) for s in cfg.of_kind("landmarks")))
    seen = [k for k, _ in unknown.most_common()]
    ids = list(landmarks)

    def few(xs: list) -> str:
        return ", ".join(repr(x) for x in xs[:5]) + (f" ... ({len(xs)} in all)"
                                                       if len(xs) > 5 else "")

    return (f"map {' and '.join(maps)} has ids {few(ids)}; the sightings' ids not in it: "
            f"{few(seen)} (is the map the one for this run?)")
