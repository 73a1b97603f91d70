"""Read ROS1 .bag, ROS2 sqlite3 and MCAP bags into one time-ordered stream of measurements.

``read_stream(bag, cfg)`` reads the topics the config names through
``rosbags.highlevel.AnyReader``, converts each message into the measurement dataclasses of
``estimation.measurements`` (SI units, body frame after the sensor's mount rotation, time from
header stamps), orders them by header stamp, fixes the local ENU datum and converts GPS fixes.

Bad input never ends in a traceback: a bag or topic that cannot be used raises ``BagError``
naming the file, topic and field; a single bad message (NaN field, NO_FIX, unusable covariance,
a stamp far from its neighbours, a landmark sighting whose id is not in the map) is dropped and
counted in ``Stream.rejected`` by (topic, reason), and the stream's ``warnings`` say so.

A bag that breaks off (truncated, or damaged past some point) still gives what was read before:
the BagError carries it as ``partial``. A ROS1 bag that rosbags cannot open at all because its
index is missing or damaged (the recorder was killed, the copy was cut) is read from the front
by ``ddfuse.estimation.ros1_scan`` for that.
"""

from __future__ import annotations

import heapq
import logging
import math
import statistics
from array import array
from collections import Counter, defaultdict, deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from ddfuse.estimation import geodesy, ros1_scan, rosmsg
from ddfuse.estimation.config import LANDMARK_NOT_IN_MAP, Config, SensorConfig, landmark_maps
from ddfuse.estimation.errors import BagError
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
from ddfuse.estimation.measurements import (
    ForwardAccel,
    GpsFix,
    GroundTruthPose,
    GyroYawRate,
    Heading,
    LandmarkObservation,
    Stream,
    WheelOdometry,
    WheelSpeeds,
    truth_at_start,
)

log = logging.getLogger(__name__)

ACCEPTED_TYPES = {
    "odometry": (rosmsg.ODOMETRY, rosmsg.TWIST_STAMPED),
    "imu": (rosmsg.IMU,),
    "gps": (rosmsg.NAVSATFIX,),
    "wheels": (rosmsg.JOINT_STATE,),
    "landmarks": (rosmsg.LANDMARK,),
    "ground_truth": (rosmsg.ODOMETRY, rosmsg.POSE_STAMPED, rosmsg.NAVSATFIX),
}
# A message whose header stamp disagrees with its topic's usual stamp-to-record-time offset by
# more than this (or the reorder window, if larger) has a broken stamp and is dropped.
STAMP_TOLERANCE = 1.0  # s
# A topic that loses more than this share of its messages (or of its measurements as late: the
# reorder window too short for it), wholly or in part, gets a warning beside the count in
# ``rejected``: a run's terminal shows no log.
WARN_SHARE = 0.1
_LATE_PREFIX = "arrived after messages stamped up to more than"
NULL_ISLAND = "latitude and longitude both 0: a receiver's placeholder, not a fix"
# A stamp of zero or below is a driver's clock not yet set, never a time: rejected before the
# stamp check, whose warm-up median and drift tracking it would otherwise join.
UNSET_STAMP = "header stamp zero or negative (the sensor's clock was not set)"


class Reject(Exception):
    """A single message that cannot be used; its text is the counted reason. ``kept``: the
    measurements of the message's other fields, used all the same (a part rejected)."""

    def __init__(self, reason: str, kept: list | None = None):
        super().__init__(reason)
        self.kept = kept or []


@dataclass
class _Source:
    """One configured topic: how to extract fields and turn them into measurements."""

    topic: str
    key: str  # config key for messages, e.g. 'sensors.imu[0]'
    msgtype: str
    extract: Callable
    convert: Callable[[tuple], list]
    raw: bool  # extract takes raw ROS1 bytes
    index: int = 0  # its place in the config's order (equal stamps keep that order)


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


def _gps_fix(rec: tuple, name: str) -> GpsFix:
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

    def convert(rec: tuple) -> list:
        fix = _gps_fix(rec, s.name)
        if fixed is not None:
            fix.cov = fixed.copy()
        else:
            if rec[6] == 0:
                raise Reject(f"position_covariance_type UNKNOWN; set {key}.noise.horizontal")
            if not geodesy.enu_covariance_is_valid(rec[5]):
                raise Reject(f"position_covariance unusable (not symmetric positive definite); "
                             f"set {key}.noise.horizontal")
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


def _ground_truth_converter(msgtype: str) -> Callable[[tuple], list]:
    if msgtype == rosmsg.NAVSATFIX:
        # Converted to ENU once the datum is known (see read_stream).
        return lambda rec: [_gps_fix(rec, "ground_truth")]

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


def open_reader(bag: Path):
    """An opened AnyReader for a ROS1 bag, a ROS2 bag directory or an .mcap/.db3 file."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    bag = Path(bag)
    if not bag.exists():
        raise BagError(f"{bag}: no such file or directory")
    path = bag
    if bag.is_file() and bag.suffix in (".mcap", ".db3"):
        path = bag.parent  # rosbags opens ROS2 bags by their directory (with metadata.yaml)
        if not (path / "metadata.yaml").is_file():
            raise BagError(f"{bag}: a ROS2 bag file needs its metadata.yaml beside it")
    elif bag.is_dir() and not (bag / "metadata.yaml").is_file():
        raise BagError(f"{bag}: a directory, but not a ROS2 bag (no metadata.yaml in it); give "
                       "a ROS1 .bag file or a ROS2 bag directory")
    store = get_typestore(Stores.ROS1_NOETIC if bag.suffix == ".bag" else Stores.ROS2_HUMBLE)
    try:
        reader = AnyReader([path], default_typestore=store)
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError, AssertionError, IndexError) as e:
        # rosbags asserts on a damaged ROS1 index (a garbled IndexData record), which the
        # caller then reads from the front, as one without an index
        raise BagError(f"{bag}: cannot read bag ({type(e).__name__ if not str(e) else e}); "
                       "is it truncated or not a bag?") from None
    return reader


def configured_topics(cfg: Config) -> list[tuple[str, str, SensorConfig | None, str]]:
    """(kind, config key, sensor or None for ground truth, topic) of each configured topic."""
    wanted: list[tuple[str, str, SensorConfig | None, str]] = []
    counters: Counter = Counter()
    for s in cfg.sensors:
        wanted.append((s.kind, f"sensors.{s.kind}[{counters[s.kind]}]", s, s.topic))
        counters[s.kind] += 1
    if cfg.ground_truth_topic:
        wanted.append(("ground_truth", "ground_truth", None, cfg.ground_truth_topic))
    return wanted


def _absent(bag: Path, topic: str, key: str, present) -> BagError:
    return BagError(f"{bag}: topic {topic} ({key}.topic) is not in the bag; "
                    f"topics present: {', '.join(sorted(present)) or 'none'}")


def _source(bag: Path, wanted: tuple, msgtype: str, ros1: bool, landmarks: dict | None = None,
            unknown: Counter | None = None, slopes: dict | None = None) -> _Source:
    """The source of one configured topic whose messages are of ``msgtype``; ``ros1``: the
    messages come as ROS1 bytes, so the fast struct extractors apply. ``landmarks``,
    ``unknown``: a landmark sensor's map and count of unknown ids; ``slopes``: the config's
    ``slope_cells`` (``converter``)."""
    kind, key, s, topic = wanted
    if msgtype not in ACCEPTED_TYPES[kind]:
        need = " or ".join(rosmsg.short_type(t) for t in ACCEPTED_TYPES[kind])
        raise BagError(f"{bag}: topic {topic} has type {rosmsg.short_type(msgtype)}, "
                       f"but {key} needs {need}")
    fast, slow = rosmsg.EXTRACTORS[msgtype]
    use_raw = fast is not None and ros1
    conv = (converter(kind, s, key, landmarks, unknown, slopes) if s
            else _ground_truth_converter(msgtype))
    return _Source(topic, key, msgtype, fast if use_raw else slow, conv, use_raw)


def _sources(cfg: Config, connections, bag: Path, ros1: bool, landmarks: dict | None = None,
             unknown: dict[str, Counter] | None = None) -> list[_Source]:
    """The sources of the configured topics, checked against the bag's ``connections`` (each
    with .topic and .msgtype); BagError naming the topic if one is absent or of a wrong type.
    ``landmarks``: the map the sightings' ids are checked against, the ids not in it counted
    in ``unknown[topic]``."""
    conns = {c.topic: c for c in connections}
    out = []
    slopes = slope_cells(cfg)
    for w in configured_topics(cfg):
        topic = w[3]
        if topic not in conns:
            raise _absent(bag, topic, w[1], conns)
        out.append(_source(bag, w, conns[topic].msgtype, ros1, landmarks,
                           None if unknown is None else unknown[topic], slopes))
    return out


class _StampCheck:
    """Drops records of one source whose header stamp disagrees with the source's usual
    stamp-to-record-time offset by more than ``tolerance`` (a clock jump): such a message would
    otherwise land minutes away from its neighbours. A stamp of zero or below never reaches it
    (``UNSET_STAMP``): it would drag the warm-up's median and the drift's.

    The usual offset is the median over the source's first ``WARMUP`` records (or those within
    ``WARMUP_S`` seconds of record time of its first, or all it has at the end of the bag), held
    back until then; afterwards it follows the median of the last ``WARMUP`` accepted ones, so
    a slow drift is followed. A source with fewer than 3 records is not checked."""

    WARMUP = 15
    WARMUP_S = 5.0

    __slots__ = ("pending", "first_rt", "ref", "recent", "n", "bad")

    def __init__(self) -> None:
        self.pending: list | None = []  # (stamp, record time, payload) during the warm-up
        self.first_rt = math.nan
        self.ref = 0.0
        self.recent: list[float] = []
        self.n = 0  # records seen
        self.bad = 0  # records dropped

    def end_warmup(self, tolerance: float) -> list:
        """The warm-up's records that pass, in their order; the check is armed from now on."""
        recs, self.pending = self.pending or [], None
        if not recs:
            return []
        offsets = [t - rt for t, rt, _ in recs]
        self.ref = statistics.median(offsets)
        if len(recs) < 3:
            return recs
        keep = [r for r, off in zip(recs, offsets, strict=True)
                if abs(off - self.ref) <= tolerance]
        self.bad += len(recs) - len(keep)
        self.recent = [r[0] - r[1] for r in keep][-self.WARMUP:]
        return keep

    def ok(self, t: float, rt: float, tolerance: float) -> bool:
        off = t - rt
        if abs(off - self.ref) > tolerance:
            self.bad += 1
            return False
        recent = self.recent
        recent.append(off)
        if len(recent) >= 2 * self.WARMUP:
            del recent[:self.WARMUP]
            self.ref = statistics.median(recent)
        return True


class BagStream:
    """The configured topics of a bag as one stream of measurements in header-stamp order,
    decoded while it is iterated: memory stays bounded however long the bag is.

    rosbags yields messages in record (receive) order; header stamps may be a little out of that
    order. A reorder buffer keyed by header stamp holds each measurement until the newest stamp
    is ``reorder_window`` seconds past it (default: the config's ``reorder_window``), then
    passes it on; a measurement that arrives after later-stamped ones were passed on is dropped
    and counted in ``rejected`` under its topic ("arrived ... later than reorder_window"), and a
    warning names the topic. Each topic's broken stamps are dropped as ``_StampCheck`` says.
    Measurements with equal stamps keep the order of a stable sort by (source, record order).

    Known before iterating (``prime`` decodes ahead as far as needed, holding what it read):
    ``t0`` (the first stamp), ``datum`` (the config's, or the first GPS fix's), the first
    ground-truth pose at or after ``t0`` (``first_truth``), ``landmarks``. Known after:
    ``t1``, ``count``, ``type_counts()``, ``rejected``, the ground truth (``truth_arrays()``,
    ``ground_truth``; kept as compact arrays, unless ``keep_truth`` is False), ``decode_s``.

    A bag that breaks off (truncated, damaged past some point; a ROS1 bag without its index is
    read from the front by ``ddfuse.estimation.ros1_scan``) ends the iteration early: ``error`` then
    says why, in one line naming the file. Errors that leave nothing to estimate on (a topic
    absent or of the wrong type, a bag that cannot be read at all) raise BagError, at
    construction or, for those only seen at the end of the bag (every message of a topic
    rejected, a topic whose clock jumps), when the iteration ends."""

    PRIME_SPAN = 30.0  # s of data past t0 that prime() reads ahead looking for the truth

    def __init__(self, bag: str | Path, cfg: Config, *, reorder_window: float | None = None,
                 keep_truth: bool = True) -> None:
        from time import perf_counter

        t_a = perf_counter()
        self.bag = bag = Path(bag)
        self.source = str(bag)
        self.cfg = cfg
        self.depth = cfg.reorder_window if reorder_window is None else float(reorder_window)
        if not self.depth >= 0.0:
            raise BagError(f"{bag}: reorder window must be >= 0 s, got {self.depth!r}")
        self.tolerance = max(STAMP_TOLERANCE, self.depth)
        self.keep_truth = keep_truth
        self.datum: tuple[float, float, float] | None = (
            cfg.datum if isinstance(cfg.datum, tuple) else None)
        self.landmarks = landmark_maps(cfg, bag)
        # topic -> ids of its sightings not in the map (dropped as LANDMARK_NOT_IN_MAP)
        self.unknown_landmarks: defaultdict[str, Counter] = defaultdict(Counter)
        self.rejected: Counter = Counter()
        self.late: Counter = Counter()  # topic -> measurements that came too late to reorder
        self._lateness: dict[str, float] = {}  # topic -> the most a late one lagged the newest
        self._offered: Counter = Counter()  # topic -> measurements offered to the buffer
        self._seen: Counter = Counter()
        # what the run should tell its user (a topic mostly late, a topic without messages):
        # whole sentences naming the bag and topic, also logged
        self.warnings: list[str] = []
        self.t0: float | None = None
        self.t1: float | None = None
        self.count = 0
        self._counts: Counter = Counter()  # (sensor, measurement type) -> n
        self.error: str | None = None
        self.decode_s = 0.0
        self._frac = 0.0
        self._truth = (array("d"), array("d"), array("d"), array("d"))
        self._truth_fixes: list[GpsFix] = []  # truth fixes waiting for the datum
        self._truth_found = False  # a truth pose at or after t0 has been seen
        self._head: deque = deque()
        self._started = False
        self._wanted = configured_topics(cfg)
        self._gps_source = any(w[0] == "gps" for w in self._wanted)
        self._truth_idx = next((i for i, w in enumerate(self._wanted)
                                if w[1] == "ground_truth"), -1)
        self._has_truth = self._truth_idx >= 0
        self._reader = None
        self._scan = None
        self._indexed = True  # False: a ROS1 bag read from the front for want of its index
        self._sources: list[_Source] = []
        index = (ros1_scan.index_connections(bag) if bag.is_file() and ros1_scan.has_magic(bag)
                 else None)
        if index is not None:
            # An intact ROS1 bag: its topics are checked against the connections of its index,
            # then it is read from the front by the scanner (rosbags' reader would load the
            # index of every message first: 90 MB for a 2 h bag).
            self._sources = _sources(cfg, index, bag, ros1=True, landmarks=self.landmarks,
                                     unknown=self.unknown_landmarks)
            self._scan = ros1_scan.Ros1Scan(bag)
        else:
            try:
                self._reader = open_reader(bag)
            except BagError as e:
                if not ros1_scan.has_magic(bag):
                    raise
                log.info("%s; reading it without its index", e)
                self._open_error = e
                self._scan = ros1_scan.Ros1Scan(bag)
                self._indexed = False
            else:
                try:
                    self._sources = _sources(cfg, self._reader.connections, bag,
                                             not self._reader.is2, self.landmarks,
                                             self.unknown_landmarks)
                except BagError:
                    self._reader.close()
                    raise
        for i, src in enumerate(self._sources):
            src.index = i
        self._gen = self._emitted()
        self.decode_s += perf_counter() - t_a

    # --- what is known ---------------------------------------------------------------------

    @property
    def duration(self) -> float:
        return (self.t1 - self.t0) if self.t0 is not None and self.t1 is not None else 0.0

    def fraction(self) -> float:
        """How much of the bag has been read, 0..1."""
        return self._frac

    def type_counts(self) -> Counter:
        """(sensor, measurement type name) -> measurements passed on so far."""
        return Counter({(s, t.__name__): n for (s, t), n in self._counts.items()})

    def truth_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """The ground truth so far: stamps (N,) s and poses (N, 3) (x m, y m, yaw rad; yaw NaN
        for a NavSatFix truth), in stamp order."""
        t, x, y, yaw = (np.array(a, float) for a in self._truth)
        return t, np.column_stack([x, y, yaw]) if len(t) else np.zeros((0, 3))

    @property
    def ground_truth(self) -> list[GroundTruthPose]:
        t, pose = self.truth_arrays()
        return [GroundTruthPose(float(ti), float(p[0]), float(p[1]), float(p[2]))
                for ti, p in zip(t, pose, strict=True)]

    def first_truth(self) -> GroundTruthPose | None:
        """The ground-truth pose at t0 (``measurements.truth_at_start``); None without truth.
        Call after ``prime``."""
        return truth_at_start(*self.truth_arrays(), self.t0)

    def prime(self) -> BagStream:
        """Decode ahead until the stream's start, its datum and the first ground truth at or
        after its start are known (what estimators are built from), holding the measurements
        read on the way for the iteration. Returns self."""
        from time import perf_counter

        t_a = perf_counter()
        need_datum = self.datum is None and self._gps_source
        try:
            while True:
                if self.t0 is not None and not (need_datum and self.datum is None):
                    if not self._has_truth or self._truth_found:
                        break
                    if self._head and self._head[-1].t - self.t0 > self.PRIME_SPAN:
                        break
                m = next(self._gen, None)
                if m is None:
                    break
                self._head.append(m)
        finally:
            self.decode_s += perf_counter() - t_a
        return self

    def __iter__(self) -> Iterator:
        if self._started:
            raise RuntimeError("a BagStream can be iterated once")
        self._started = True
        return self._iterate_all()

    def _iterate_all(self) -> Iterator:
        from time import perf_counter as clock

        head = self._head
        while head:
            yield head.popleft()
        if not self.keep_truth:
            self._truth = (array("d"), array("d"), array("d"), array("d"))
        gen = self._gen
        t_a = clock()
        for m in gen:
            self.decode_s += clock() - t_a
            yield m
            t_a = clock()
        self.decode_s += clock() - t_a

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    # --- the pipeline: raw messages -> measurements -> stamp check -> reorder -> out -----------

    def _raw(self) -> Iterator[tuple[_Source, int, object]]:
        """(source, record time ns, raw message) from the indexed reader or the scanner; stops
        early (setting ``_stopped``) when the storage fails."""
        if self._scan is not None:
            yield from self._raw_unindexed()
            return
        reader = self._reader
        sources = self._sources
        by_topic: dict[str, list[_Source]] = defaultdict(list)
        for src in sources:
            by_topic[src.topic].append(src)
        conns = [c for c in reader.connections if c.topic in by_topic]
        start, span = reader.start_time, max(1, reader.end_time - reader.start_time)
        expected = {c.topic: 0 for c in reader.connections}
        for c in reader.connections:
            expected[c.topic] += c.msgcount
        self._read_counts: Counter = Counter()
        read_counts = self._read_counts
        try:
            try:
                for i, (conn, rec_ns, raw) in enumerate(reader.messages(connections=conns)):
                    if i % 2000 == 0:
                        self._frac = (rec_ns - start) / span
                    for src in by_topic[conn.topic]:
                        read_counts[src.key] += 1
                        yield src, rec_ns, raw
            except BagError:
                raise
            except Exception as e:  # rosbags raises many types on damaged storage
                self._stopped = (f"bag is damaged or truncated after "
                                 f"{sum(read_counts.values())} messages "
                                 f"({type(e).__name__}: {e})")
                return
            short = [(s.topic, read_counts[s.key], expected[s.topic]) for s in sources
                     if read_counts[s.key] < expected[s.topic]]
            if short:
                topic, got, want = short[0]
                self._stopped = (f"bag is damaged: topic {topic} has {want} messages in its "
                                 f"index but only {got} could be read")
        finally:
            self._frac = 1.0
            self.close()

    def _raw_unindexed(self) -> Iterator[tuple[_Source, int, bytes]]:
        """The scanner's messages on configured topics. Sources are made at their topic's first
        connection record; messages are decoded as on the indexed path (struct extractors on
        the ROS1 bytes where rosmsg has one, else rosbags' deserialiser with the types that the
        bag's own connection records define, as AnyReader does for ROS1 bags)."""
        from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore

        bag, scan = self.bag, self._scan
        by_topic: dict[str, list[tuple]] = defaultdict(list)
        for w in self._wanted:
            by_topic[w[3]].append(w)
        made: dict[str, _Source] = {s.key: s for s in self._sources}  # config key -> source
        self._made = made
        routes: dict[int, list[_Source]] = {}  # connection id -> the sources it feeds
        store = self._store = get_typestore(Stores.EMPTY)
        order = {w[1]: i for i, w in enumerate(self._wanted)}
        self._used = 0  # messages read on configured topics

        def route(conn: ros1_scan.Connection, w: tuple) -> _Source:
            src = made.get(w[1])
            if src is None:
                src = made[w[1]] = _source(bag, w, conn.msgtype, ros1=True,
                                           landmarks=self.landmarks,
                                           unknown=self.unknown_landmarks[conn.topic])
                src.index = order[w[1]]
                self._sources.append(src)
            elif src.msgtype != conn.msgtype:
                raise BagError(f"{bag}: topic {conn.topic} has messages of two types, "
                               f"{rosmsg.short_type(src.msgtype)} and "
                               f"{rosmsg.short_type(conn.msgtype)}")
            if not src.raw and conn.msgtype not in store.fielddefs:
                try:
                    store.register(get_types_from_msg(conn.msgdef, conn.msgtype)
                                   if conn.msgdef
                                   else get_typestore(Stores.ROS1_NOETIC).fielddefs)
                except TypesysError as e:
                    raise BagError(f"{bag}: topic {conn.topic}: cannot use the bag's "
                                   f"definition of {rosmsg.short_type(conn.msgtype)} "
                                   f"({e})") from None
            return src

        st = scan.status
        try:
            for i, item in enumerate(scan):
                if type(item) is ros1_scan.Connection:
                    routes[item.id] = [route(item, w) for w in by_topic.get(item.topic, ())]
                    continue
                if i % 2000 == 0:
                    self._frac = st.offset / max(1, st.file_size)
                srcs = routes[item.conn.id]
                if srcs:
                    self._used += 1
                for src in srcs:
                    yield src, item.time_ns, item.data
        except ros1_scan.ScanError as e:
            if self._indexed:
                raise BagError(f"{bag}: cannot read bag ({e})") from None
            raise BagError(f"{self._open_error}; reading it without the index fails too: "
                           f"{e}") from None
        finally:
            self._frac = 1.0

    def _emitted(self) -> Iterator:
        """Every measurement in stamp order (the generator behind iteration and prime)."""
        self._stopped: str | None = None
        rejected, offered = self.rejected, self._offered
        checks: dict[int, _StampCheck] = {}
        heap: list = []
        push, pop = heapq.heappush, heapq.heappop
        depth, tol = self.depth, self.tolerance
        deserialize = None
        seq = 0
        newest = -math.inf  # the newest stamp pushed
        released = -math.inf  # the stamp of the last measurement passed on
        # the newest stamp when it was: a late one needed a reorder window of this minus its
        # stamp (not the newest at its own admission, which a topic's warm-up may hold back)
        released_newest = -math.inf
        warming: set[int] = set()  # sources still in their stamp check's warm-up
        last_raw, last_msg = None, None

        def admit(ms: list, j: int, src: _Source) -> None:
            """Into the reorder buffer, or dropped as late: measurements of source ``j``."""
            nonlocal seq, newest
            offered[src.topic] += len(ms)
            for m in ms:
                t = m.t
                if t < released:
                    self._late(src, t, released, released_newest)
                    continue
                push(heap, (t, j, seq, m))
                seq += 1
                if t > newest:
                    newest = t

        seen = self._seen  # topic -> messages read (per source reading it, as ``rejected``)
        raw_items = self._raw()
        if self._scan is None:
            deserialize = self._reader.deserialize
        try:
            for src, rec_ns, raw in raw_items:
                seen[src.topic] += 1
                if deserialize is None:
                    deserialize = self._store.deserialize_ros1
                try:
                    if src.raw:
                        rec = src.extract(raw)
                    else:
                        # Several sources may share a topic: deserialise each message once.
                        # Compare the bytes object itself (kept alive here), never its id(),
                        # which CPython reuses once the previous message is freed.
                        if raw is not last_raw:
                            last_raw, last_msg = raw, deserialize(raw, src.msgtype)
                        rec = src.extract(last_msg)
                    t_rec = rec[0]
                    if t_rec <= 0.0 and t_rec > -math.inf:  # non-finite: the converters' reason
                        rejected[(src.topic, UNSET_STAMP)] += 1
                        continue
                    out = src.convert(rec)
                except Reject as e:
                    rejected[(src.topic, str(e))] += 1
                    if not e.kept:
                        continue
                    out = e.kept
                except Exception as e:  # a message that fails to decode is one bad message
                    rejected[(src.topic, f"cannot decode message: {type(e).__name__}: {e}")] += 1
                    continue
                rt = rec_ns * 1e-9
                idx = src.index
                chk = checks.get(idx)
                if chk is None:
                    chk = checks[idx] = _StampCheck()
                    chk.first_rt = rt
                    warming.add(idx)
                passed = None
                if out:  # one check per message: its measurements share its header stamp
                    chk.n += 1
                    if chk.pending is not None:
                        chk.pending.append((out[0].t, rt, out))
                    elif chk.ok(out[0].t, rt, tol):
                        passed = out
                if warming:
                    for j in list(warming):
                        c = checks[j]
                        if len(c.pending) >= _StampCheck.WARMUP or \
                                rt - c.first_rt > _StampCheck.WARMUP_S:
                            warming.discard(j)
                            for _, _, ms in c.end_warmup(tol):
                                admit(ms, j, self._source_of(j))
                if passed is not None:
                    admit(passed, idx, src)
                if not warming:
                    cut = newest - depth
                    while heap and heap[0][0] < cut:
                        item = pop(heap)
                        released, released_newest = item[0], newest
                        m = self._out(item)
                        if m is not None:
                            yield m
            # the end of the bag: every warm-up ends, the buffer empties
            for j in sorted(warming):
                for _, _, ms in checks[j].end_warmup(tol):
                    admit(ms, j, self._source_of(j))
            while heap:
                item = pop(heap)
                released = item[0]
                m = self._out(item)
                if m is not None:
                    yield m
        finally:
            self.close()
        self._finish(checks)

    def _source_of(self, index: int) -> _Source:
        return next(s for s in self._sources if s.index == index)

    def _late(self, src: _Source, t: float, released: float, newest: float) -> None:
        """Count a measurement stamped ``t`` that came after ``released`` was passed on, when
        the newest stamp was ``newest``: a reorder window of ``newest - t`` would have kept
        it (releases happen at the same messages whatever the window)."""
        self.late[src.topic] += 1
        if newest - t > self._lateness.get(src.topic, 0.0):
            self._lateness[src.topic] = newest - t
        self.rejected[(src.topic, f"{_LATE_PREFIX} "
                                  f"reorder_window ({self.depth:g} s) later had been passed on; "
                                  "raise reorder_window to keep it")] += 1
        if self.late[src.topic] == 1:
            log.warning("%s: %s: a message stamped %.3f s before the last one passed on came "
                        "too late to reorder (reorder_window %g s); dropped and counted",
                        self.bag, src.topic, released - t, self.depth)

    def _out(self, item: tuple):
        """Finish one measurement leaving the reorder buffer: truth goes to the truth arrays,
        a GPS fix gets its ENU position; returns the measurement to pass on, or None."""
        m = item[3]
        if item[1] == self._truth_idx:
            if type(m) is GpsFix:
                if self.datum is None and not self._gps_source:
                    self.datum = (m.lat, m.lon, m.alt)
                if self.datum is None:
                    self._truth_fixes.append(m)
                else:
                    e, n, _ = geodesy.geodetic_to_enu(m.lat, m.lon, m.alt, *self.datum)
                    self._add_truth(m.t, e, n, math.nan)
            else:
                self._add_truth(m.t, m.x, m.y, m.yaw)
            return None
        if type(m) is GpsFix:
            if self.datum is None:
                self.datum = (m.lat, m.lon, m.alt)
                self._flush_truth_fixes()
            m.enu = geodesy.geodetic_to_enu(m.lat, m.lon, m.alt, *self.datum)
            m.datum = self.datum
        t = m.t
        if self.t0 is None:
            self.t0 = t
            if len(self._truth[0]) and self._truth[0][-1] >= t - 1e-9:
                self._truth_found = True
        if self.t1 is None or t > self.t1:
            self.t1 = t
        self.count += 1
        self._counts[(m.sensor, type(m))] += 1
        return m

    def _add_truth(self, t: float, x: float, y: float, yaw: float) -> None:
        if self._started and not self.keep_truth:
            return
        tt, xx, yy, ww = self._truth
        tt.append(t)
        xx.append(x)
        yy.append(y)
        ww.append(yaw)
        if not self._truth_found and self.t0 is not None and t >= self.t0 - 1e-9:
            self._truth_found = True

    def _flush_truth_fixes(self) -> None:
        fixes, self._truth_fixes = self._truth_fixes, []
        if not fixes:
            return
        e, n, _ = geodesy.geodetic_to_enu(np.array([f.lat for f in fixes]),
                                          np.array([f.lon for f in fixes]),
                                          np.array([f.alt for f in fixes]), *self.datum)
        for f, ei, ni in zip(fixes, e, n, strict=True):
            self._add_truth(f.t, float(ei), float(ni), math.nan)

    def _finish(self, checks: dict[int, _StampCheck]) -> None:
        """At the end of the bag: the datum from a truth fix if no GPS sensor gave one, the
        counts of what was dropped, the errors that can only be seen now."""
        bag = self.bag
        if self._truth_fixes:
            if self.datum is None:
                f = self._truth_fixes[0]
                self.datum = (f.lat, f.lon, f.alt)
            self._flush_truth_fixes()
        where = what = None
        if self._scan is not None and self._indexed:
            st = self._scan.status
            if st.reason:
                self._stopped = (f"bag is damaged or truncated after {st.messages} messages "
                                 f"({st.reason})")
        elif self._scan is not None:
            st = self._scan.status
            if st.truncated:
                what = f"bag is truncated: {st.reason}"
            elif st.reason:
                what = f"bag is truncated or damaged: its index is unusable and {st.reason}"
            else:
                what = ("bag is truncated: it has no index (its recorder did not close it), so "
                        "the messages it still buffered may be missing")
            where = f"byte {st.offset} of {st.file_size}"
            if not st.messages:
                raise BagError(f"{bag}: {what}; no complete message before {where}")
            missing = [w for w in self._wanted if w[1] not in self._made]
            if missing:
                kind, key, _, topic = missing[0]
                present = {c.topic for c in self._scan.connections.values()}
                raise BagError(f"{_absent(bag, topic, key, present)} (only up to {where} could "
                               f"be read: {what})")
            if not self._used:
                raise BagError(f"{bag}: {what}; no message of the configured topics before "
                               f"{where}")
        try:
            self._check_sources(checks)
        except BagError as e:
            if where is not None:
                raise BagError(f"{e} (only up to {where} could be read: {what})") from None
            raise
        self._warn_rejected()
        for (topic, reason), n in sorted(self.rejected.items()):
            log.warning("%s: %s: %d message(s) rejected: %s", bag, topic, n, reason)
        for w in self.warnings:
            log.warning("%s", w)
        if where is not None:
            self.error = (f"{bag}: {what}; read {self._used} messages up to "
                          f"t={self.t1 if self.t1 is not None else 0.0:.3f} "
                          f"({self.duration:.1f} s of data, {where})")
        elif self._stopped is not None:
            self.error = f"{bag}: {self._stopped}"

    def _warn_rejected(self) -> None:
        """The warnings of WARN_SHARE: per topic, each reason that cost more than that share of
        its messages (a compass without orientation that only a count said was unused), and
        the measurements dropped as late, with the reorder window that keeps them."""
        for (topic, reason), n in sorted(self.rejected.items()):
            total = self._seen[topic]
            if reason.startswith(_LATE_PREFIX) or not n > WARN_SHARE * total:
                continue
            self.warnings.append(f"{self.bag}: topic {topic}: {n} of {total} messages "
                                 f"({100.0 * n / total:.0f} %) rejected, in whole or in part: "
                                 f"{reason}{self._reason_note(topic, reason)}")
        for topic, n in sorted(self.late.items()):
            total = self._offered[topic]
            if n > WARN_SHARE * total:
                lag = self._lateness[topic]
                self.warnings.append(
                    f"{self.bag}: topic {topic}: {n} of {total} measurements "
                    f"({100.0 * n / total:.0f} %) dropped as late: they came up to "
                    f"{lag:.2f} s behind the newest stamp, beyond reorder_window "
                    f"({self.depth:g} s); set reorder_window to at least "
                    f"{math.ceil(lag * 10.0) / 10.0:g} s (or --reorder-window) to keep them")

    def _reason_note(self, topic: str, reason: str) -> str:
        """More on a rejection ``reason`` of ``topic`` for its warning or error: for sightings
        not in the map, the map and the ids (``unknown_landmarks_note``); else nothing."""
        if reason != LANDMARK_NOT_IN_MAP:
            return ""
        return "; " + unknown_landmarks_note(self.cfg, self.landmarks,
                                             self.unknown_landmarks[topic])

    def _check_sources(self, checks: dict[int, _StampCheck]) -> None:
        bag, rejected = self.bag, self.rejected
        empty = []
        for src in sorted(self._sources, key=lambda s: s.index):
            chk = checks.get(src.index)
            if chk is None:
                bad = {r: n for (tp, r), n in rejected.items() if tp == src.topic}
                if bad:
                    reason = max(bad.items(), key=lambda x: x[1])[0]
                    raise BagError(f"{bag}: topic {src.topic} ({src.key}): all "
                                   f"{sum(bad.values())} messages rejected: {reason}"
                                   f"{self._reason_note(src.topic, reason)}")
                empty.append(src)  # a message either converts (a check) or is counted
                continue
            if chk.bad:
                rejected[(src.topic, f"header stamp more than {self.tolerance:g} s off its "
                                     "topic's clock (time went backwards or jumped)")] += chk.bad
                if chk.n >= 3 and chk.bad > 0.1 * chk.n:
                    raise BagError(
                        f"{bag}: topic {src.topic} ({src.key}): {chk.bad} of {chk.n} stamps "
                        f"jump by more than {self.tolerance:g} s against the bag's record "
                        "time; the bag mixes clocks or time goes backwards beyond "
                        "reorder_window")
        sensors = [s for s in self._sources if s.key != "ground_truth"]
        if sensors and {s.index for s in sensors} <= {s.index for s in empty}:
            raise BagError(f"{bag}: no configured sensor topic has a message "
                           f"({', '.join(f'{s.topic} ({s.key})' for s in sensors)}): nothing "
                           "to estimate from")
        for src in empty:
            self.warnings.append(f"{bag}: topic {src.topic} ({src.key}) has no messages; "
                                 "the run goes on without it")


def open_stream(bag: str | Path, cfg: Config, *, reorder_window: float | None = None,
                keep_truth: bool = True) -> BagStream:
    """A primed BagStream of ``bag`` (see there): its start, datum and initial truth known,
    ready to be run."""
    return BagStream(bag, cfg, reorder_window=reorder_window, keep_truth=keep_truth).prime()


def read_stream(bag: str | Path, cfg: Config, progress: Callable[[float], None] | None = None,
                *, reorder_window: float | None = None) -> Stream:
    """Read the configured topics of ``bag`` into a Stream ordered by header stamp: the whole
    of a BagStream (see there) in memory, for the tests and tools that want a list.

    ``progress``, if given, is called with the fraction of the bag read so far.
    Raises BagError (naming the file, topic and field) when the bag or a topic cannot be used.
    A bag that breaks off (truncated or damaged; a ROS1 bag without a usable index is read from
    the front by ``ddfuse.estimation.ros1_scan``) raises BagError saying so, carrying the stream of
    what could be read as ``partial``."""
    bs = BagStream(bag, cfg, reorder_window=reorder_window)
    measurements = []
    for i, m in enumerate(bs):
        measurements.append(m)
        if progress and i % 2000 == 0:
            progress(bs.fraction())
    stream = Stream(measurements=measurements, ground_truth=bs.ground_truth, datum=bs.datum,
                    landmarks=bs.landmarks, rejected=dict(bs.rejected), source=str(bag),
                    t0=bs.t0 if bs.t0 is not None else 0.0,
                    t1=bs.t1 if bs.t1 is not None else 0.0)
    if bs.error is not None:
        raise BagError(bs.error, partial=stream)
    return stream
