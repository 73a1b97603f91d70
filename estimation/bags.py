"""Read ROS1 .bag, ROS2 sqlite3 and MCAP bags into one time-ordered stream of measurements.

``read_stream(bag, cfg)`` reads the topics the config names through
``rosbags.highlevel.AnyReader``, converts each message into the measurement dataclasses of
``estimation.measurements`` (SI units, body frame after the sensor's mount rotation, time from
header stamps), orders them by header stamp, fixes the local ENU datum and converts GPS fixes.

Bad input never ends in a traceback: a bag or topic that cannot be used raises ``BagError``
naming the file, topic and field; a single bad message (NaN field, NO_FIX, unusable covariance,
a stamp far from its neighbours) is dropped and counted in ``Stream.rejected`` by
(topic, reason), and the stream's ``warnings`` say so.

A bag that breaks off (truncated, or damaged past some point) still gives what was read before:
the BagError carries it as ``partial``. A ROS1 bag that rosbags cannot open at all because its
index is missing or damaged (the recorder was killed, the copy was cut) is read from the front
by ``estimation.ros1_scan`` for that.
"""

from __future__ import annotations

import logging
import math
import statistics
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NoReturn

import numpy as np

from estimation import geodesy, ros1_scan, rosmsg
from estimation.config import Config, SensorConfig, load_landmark_map
from estimation.errors import BagError
from estimation.frames import IDENTITY, body_yaw, dot_row, rotate, rotated_variance, rpy_matrix
from estimation.measurements import (
    ForwardAccel,
    GpsFix,
    GroundTruthPose,
    GyroYawRate,
    Heading,
    LandmarkObservation,
    Stream,
    WheelOdometry,
    WheelSpeeds,
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


class Reject(Exception):
    """A single message that cannot be used; its text is the counted reason."""


@dataclass
class _Source:
    """One configured topic: how to extract fields and turn them into measurements."""

    topic: str
    key: str  # config key for messages, e.g. 'sensors.imu[0]'
    msgtype: str
    extract: Callable
    convert: Callable[[tuple], list]
    raw: bool  # extract takes raw ROS1 bytes
    records: list = field(default_factory=list)  # (stamp, record_time, measurement)


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


def _odometry_converter(s: SensorConfig, key: str) -> Callable[[tuple], list]:
    mount = IDENTITY if s.mount_rpy == (0.0, 0.0, 0.0) else rpy_matrix(*s.mount_rpy)
    use_v, use_w = "v" in s.use, "yaw_rate" in s.use
    name = s.name

    def convert(rec: tuple) -> list:
        t, lin, ang, cov = rec[0], rec[-3], rec[-2], rec[-1]
        if mount is not IDENTITY:
            lin, ang = rotate(mount, lin), rotate(mount, ang)
        v, w = lin[0], ang[2]
        if not _finite(t, v, w):
            raise Reject("non-finite stamp or twist")
        cv = cw = None
        if cov is not None:
            if mount is IDENTITY:
                cv, cw = cov[0], cov[35]
            else:
                lin9 = tuple(cov[6 * i + j] for i in range(3) for j in range(3))
                ang9 = tuple(cov[6 * (i + 3) + j + 3] for i in range(3) for j in range(3))
                cv, cw = rotated_variance(mount, lin9, 0), rotated_variance(mount, ang9, 2)
        return [WheelOdometry(
            t, v if use_v else None, w if use_w else None,
            _var(s, key, "twist.covariance[0]", "v", cv) if use_v else math.nan,
            _var(s, key, "twist.covariance[35]", "yaw_rate", cw) if use_w else math.nan,
            name)]

    return convert


def _imu_converter(s: SensorConfig, key: str) -> Callable[[tuple], list]:
    mount = IDENTITY if s.mount_rpy == (0.0, 0.0, 0.0) else rpy_matrix(*s.mount_rpy)
    use_yaw, use_w, use_a = "yaw" in s.use, "yaw_rate" in s.use, "accel" in s.use
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

    def convert(rec: tuple) -> list:
        t, q, ocov, w, wcov, a, acov = rec
        if not math.isfinite(t):
            raise Reject("non-finite stamp")
        out: list = []
        if use_yaw:
            if ocov[0] == -1.0:
                raise Reject("orientation not provided (orientation_covariance[0] = -1)")
            qx, qy, qz, qw = q
            if not abs(qx * qx + qy * qy + qz * qz + qw * qw - 1.0) < 2e-3:
                raise Reject("orientation is not a finite unit quaternion")
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
            out.append(ForwardAccel(t, ax, var("linear_acceleration_covariance[0]", "accel",
                                               acov, 0), name))
        return out

    return convert


def _gps_fix(rec: tuple, name: str) -> GpsFix:
    t, status, lat, lon, alt, cov9, _ = rec
    if status < 0:
        raise Reject("status NO_FIX")
    if not (_finite(t, lat, lon) and -90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise Reject("latitude/longitude not finite or out of range")
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
            c = rec[5]
            if not (c[0] > 0 and c[4] > 0 and _finite(*c)):
                raise Reject(f"position_covariance unusable; set {key}.noise.horizontal")
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


def _landmarks_converter(s: SensorConfig, key: str) -> Callable[[tuple], list]:
    use_b = "bearing" in s.use

    def convert(rec: tuple) -> list:
        t, lid, rng, brg, rv, bv, has_b = rec
        if not _finite(t, rng) or rng < 0:
            raise Reject("range not finite or negative")
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
    store = get_typestore(Stores.ROS1_NOETIC if bag.suffix == ".bag" else Stores.ROS2_HUMBLE)
    try:
        reader = AnyReader([path], default_typestore=store)
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as e:
        raise BagError(f"{bag}: cannot read bag ({e}); is it truncated or not a bag?") from None
    return reader


def _wanted(cfg: Config) -> list[tuple[str, str, SensorConfig | None, str]]:
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


def _source(bag: Path, wanted: tuple, msgtype: str, ros1: bool) -> _Source:
    """The source of one configured topic whose messages are of ``msgtype``; ``ros1``: the
    messages come as ROS1 bytes, so the fast struct extractors apply."""
    kind, key, s, topic = wanted
    if msgtype not in ACCEPTED_TYPES[kind]:
        need = " or ".join(rosmsg.short_type(t) for t in ACCEPTED_TYPES[kind])
        raise BagError(f"{bag}: topic {topic} has type {rosmsg.short_type(msgtype)}, "
                       f"but {key} needs {need}")
    fast, slow = rosmsg.EXTRACTORS[msgtype]
    use_raw = fast is not None and ros1
    conv = CONVERTERS[kind](s, key) if s else _ground_truth_converter(msgtype)
    return _Source(topic, key, msgtype, fast if use_raw else slow, conv, use_raw)


def _sources(cfg: Config, reader, bag: Path) -> list[_Source]:
    conns = {c.topic: c for c in reader.connections}
    out = []
    for w in _wanted(cfg):
        topic = w[3]
        if topic not in conns:
            raise _absent(bag, topic, w[1], conns)
        out.append(_source(bag, w, conns[topic].msgtype, not reader.is2))
    return out


def _iterate(reader, sources: list[_Source], progress: Callable[[float], None] | None
             ) -> Iterator[tuple[_Source, int, object]]:
    by_topic: dict[str, list[_Source]] = defaultdict(list)
    for src in sources:
        by_topic[src.topic].append(src)
    conns = [c for c in reader.connections if c.topic in by_topic]
    start, span = reader.start_time, max(1, reader.end_time - reader.start_time)
    for i, (conn, rec_ns, raw) in enumerate(reader.messages(connections=conns)):
        if progress and i % 2000 == 0:
            progress((rec_ns - start) / span)
        for src in by_topic[conn.topic]:
            yield src, rec_ns, raw


def _decode(items: Iterator[tuple[_Source, int, object]], deserialize: Callable,
            read_counts: Counter, rejected: Counter) -> str | None:
    """Convert each (source, record time ns, raw message) into its source's records, counting
    messages read per config key and rejected ones per (topic, reason). Returns why reading
    stopped early (the storage raised), None if it did not; BagError passes through."""
    last_raw, last_msg = None, None
    try:
        for src, rec_ns, raw in items:
            read_counts[src.key] += 1
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
                for m in src.convert(rec):
                    src.records.append((m.t, rec_ns * 1e-9, m))
            except Reject as e:
                rejected[(src.topic, str(e))] += 1
            except Exception as e:  # a message that fails to decode is one bad message
                rejected[(src.topic, f"cannot decode message: {type(e).__name__}: {e}")] += 1
    except BagError:
        raise
    except Exception as e:  # rosbags raises many types on damaged storage
        return (f"bag is damaged or truncated after {sum(read_counts.values())} messages "
                f"({type(e).__name__}: {e})")
    return None


def read_stream(bag: str | Path, cfg: Config, progress: Callable[[float], None] | None = None
                ) -> Stream:
    """Read the configured topics of ``bag`` into a Stream ordered by header stamp.

    ``progress``, if given, is called with the fraction of the bag read so far.
    Raises BagError (naming the file, topic and field) when the bag or a topic cannot be used.
    A ROS1 bag without a usable index (the recorder was killed, the file was cut) is read from
    the front by ``estimation.ros1_scan``; the BagError saying it is truncated then carries the
    stream of what could be read as ``partial``."""
    bag = Path(bag)
    try:
        reader = open_reader(bag)
    except BagError as e:
        if not ros1_scan.has_magic(bag):
            raise
        _read_unindexed(bag, cfg, progress, e)
    damaged = None
    read_counts: Counter = Counter()
    rejected: Counter = Counter()
    try:
        sources = _sources(cfg, reader, bag)
        expected = {c.topic: c.msgcount for c in reader.connections}
        damaged = _decode(_iterate(reader, sources, progress), reader.deserialize, read_counts,
                          rejected)
        if damaged is None:
            short = [(s.topic, read_counts[s.key], expected[s.topic]) for s in sources
                     if read_counts[s.key] < expected[s.topic]]
            if short:
                topic, got, want = short[0]
                damaged = (f"bag is damaged: topic {topic} has {want} messages in its index "
                           f"but only {got} could be read")
    finally:
        reader.close()
    if damaged is not None:
        try:
            partial = _assemble(bag, cfg, sources, rejected)
        except BagError:
            partial = None
        raise BagError(f"{bag}: {damaged}", partial=partial)
    return _assemble(bag, cfg, sources, rejected)


def _read_unindexed(bag: Path, cfg: Config, progress: Callable[[float], None] | None,
                    open_error: BagError) -> NoReturn:
    """Read the ROS1 bag that rosbags could not open (``open_error``) from the front with
    ``ros1_scan`` and raise BagError saying it is truncated, with what was read as ``partial``.

    Messages are decoded as on the indexed path: struct extractors on the ROS1 bytes where
    rosmsg has one, else rosbags' deserialiser with the types defined by the bag's own
    connection records (as AnyReader does for ROS1 bags)."""
    from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore

    log.info("%s; reading it without its index", open_error)
    scan = ros1_scan.Ros1Scan(bag)
    wanted = _wanted(cfg)
    by_topic: dict[str, list[tuple]] = defaultdict(list)
    for w in wanted:
        by_topic[w[3]].append(w)
    made: dict[str, _Source] = {}  # config key -> source, made at its topic's first connection
    routes: dict[int, list[_Source]] = {}  # connection id -> the sources it feeds
    store = get_typestore(Stores.EMPTY)
    used = 0  # messages read on configured topics

    def route(conn: ros1_scan.Connection, w: tuple) -> _Source:
        src = made.get(w[1])
        if src is None:
            src = made[w[1]] = _source(bag, w, conn.msgtype, ros1=True)
            if not src.raw and conn.msgtype not in store.fielddefs:
                try:
                    store.register(get_types_from_msg(conn.msgdef, conn.msgtype) if conn.msgdef
                                   else get_typestore(Stores.ROS1_NOETIC).fielddefs)
                except TypesysError as e:
                    raise BagError(f"{bag}: topic {conn.topic}: cannot use the bag's definition "
                                   f"of {rosmsg.short_type(conn.msgtype)} ({e})") from None
        elif src.msgtype != conn.msgtype:
            raise BagError(f"{bag}: topic {conn.topic} has messages of two types, "
                           f"{rosmsg.short_type(src.msgtype)} and "
                           f"{rosmsg.short_type(conn.msgtype)}")
        return src

    def items() -> Iterator[tuple[_Source, int, bytes]]:
        nonlocal used
        st = scan.status
        try:
            for i, item in enumerate(scan):
                if type(item) is ros1_scan.Connection:
                    routes[item.id] = [route(item, w) for w in by_topic.get(item.topic, ())]
                    continue
                if progress and i % 2000 == 0:
                    progress(st.offset / max(1, st.file_size))
                srcs = routes[item.conn.id]
                if srcs:
                    used += 1
                for src in srcs:
                    yield src, item.time_ns, item.data
        except ros1_scan.ScanError as e:
            raise BagError(f"{open_error}; reading it without the index fails too: {e}") from None

    read_counts: Counter = Counter()
    rejected: Counter = Counter()
    failure = _decode(items(), store.deserialize_ros1, read_counts, rejected)
    st = scan.status
    if failure:  # the scanner stops without raising; this is a fault of ours, say so plainly
        raise BagError(f"{bag}: {failure}")
    if st.truncated:
        what = f"bag is truncated: {st.reason}"
    elif st.reason:
        what = f"bag is truncated or damaged: its index is unusable and {st.reason}"
    else:
        what = ("bag is truncated: it has no index (its recorder did not close it), so the "
                "messages it still buffered may be missing")
    where = f"byte {st.offset} of {st.file_size}"
    if not st.messages:
        raise BagError(f"{bag}: {what}; no complete message before {where}")
    missing = [w for w in wanted if w[1] not in made]
    if missing:
        kind, key, _, topic = missing[0]
        present = {c.topic for c in scan.connections.values()}
        raise BagError(f"{_absent(bag, topic, key, present)} (only up to {where} could be "
                       f"read: {what})")
    if not used:
        raise BagError(f"{bag}: {what}; no message of the configured topics before {where}")
    sources = [made[w[1]] for w in wanted]
    try:
        stream = _assemble(bag, cfg, sources, rejected)
    except BagError as e:
        raise BagError(f"{e} (only up to {where} could be read: {what})") from None
    raise BagError(f"{bag}: {what}; read {used} messages up to t={stream.t1:.3f} "
                   f"({stream.duration:.1f} s of data, {where})", partial=stream)


def _drop_bad_stamps(bag: Path, src: _Source, tolerance: float, rejected: Counter) -> list:
    """Drop records whose header stamp is inconsistent with the topic's stamp-to-record offset.

    Real bags carry small reorderings (kept and sorted) but also single broken stamps (zero, a
    clock jump) that would otherwise land the message minutes away from its neighbours."""
    recs = src.records
    if len(recs) < 3:
        return recs
    offsets = [t - rt for t, rt, _ in recs]
    med = statistics.median(offsets)
    keep = [r for r, off in zip(recs, offsets, strict=True) if abs(off - med) <= tolerance]
    bad = len(recs) - len(keep)
    if bad:
        rejected[(src.topic, f"header stamp more than {tolerance:g} s off its topic's clock "
                             "(time went backwards or jumped)")] += bad
        if bad > 0.1 * len(recs):
            raise BagError(f"{bag}: topic {src.topic} ({src.key}): {bad} of {len(recs)} stamps "
                           f"jump by more than {tolerance:g} s against the bag's record time; "
                           "the bag mixes clocks or time goes backwards beyond reorder_window")
    return keep


def _assemble(bag: Path, cfg: Config, sources: list[_Source], rejected: Counter) -> Stream:
    tolerance = max(STAMP_TOLERANCE, cfg.reorder_window)
    measurements: list = []
    truth: list = []
    for src in sources:
        n_total = len(src.records) + sum(n for (tp, _), n in rejected.items() if tp == src.topic)
        if n_total and not src.records:
            reason = max(((r, n) for (tp, r), n in rejected.items() if tp == src.topic),
                         key=lambda x: x[1])[0]
            raise BagError(f"{bag}: topic {src.topic} ({src.key}): all {n_total} messages "
                           f"rejected: {reason}")
        keep = _drop_bad_stamps(bag, src, tolerance, rejected)
        target = truth if src.key == "ground_truth" else measurements
        target.extend(r[2] for r in keep)
    # Stable sort by header stamp: messages arrive slightly out of order in real bags.
    measurements.sort(key=lambda m: m.t)
    truth.sort(key=lambda m: m.t)

    datum = _datum(cfg, measurements, truth)
    fixes = [m for m in measurements if isinstance(m, GpsFix)]
    gt_fixes = [m for m in truth if isinstance(m, GpsFix)]
    if (fixes or gt_fixes) and datum is None:
        raise BagError(f"{bag}: no GPS fix to take the datum from (frame.datum: first_fix)")
    if fixes:
        e, n, u = _to_enu(fixes, datum)
        for f, ei, ni, ui in zip(fixes, e, n, u, strict=True):
            f.enu = (float(ei), float(ni), float(ui))
    if gt_fixes:
        e, n, _ = _to_enu(gt_fixes, datum)
        truth = [GroundTruthPose(f.t, float(ei), float(ni), math.nan)
                 for f, ei, ni in zip(gt_fixes, e, n, strict=True)]

    landmarks: dict[str, tuple[float, float]] = {}
    for s in cfg.of_kind("landmarks"):
        landmarks.update(load_landmark_map(s.map))
    stamps = [m.t for m in measurements]
    stream = Stream(measurements=measurements, ground_truth=truth, datum=datum,
                    landmarks=landmarks, rejected=dict(rejected), source=str(bag),
                    t0=min(stamps) if stamps else 0.0, t1=max(stamps) if stamps else 0.0)
    for (topic, reason), n in sorted(rejected.items()):
        log.warning("%s: %s: %d message(s) rejected: %s", bag, topic, n, reason)
    return stream


def _datum(cfg: Config, measurements: list, truth: list) -> tuple[float, float, float] | None:
    if isinstance(cfg.datum, tuple):
        return cfg.datum
    for m in measurements:
        if isinstance(m, GpsFix):
            return (m.lat, m.lon, m.alt)
    for m in truth:
        if isinstance(m, GpsFix):
            return (m.lat, m.lon, m.alt)
    return None


def _to_enu(fixes: list[GpsFix], datum: tuple[float, float, float]):
    lat = np.array([f.lat for f in fixes])
    lon = np.array([f.lon for f in fixes])
    alt = np.array([f.alt for f in fixes])
    return geodesy.geodetic_to_enu(lat, lon, alt, *datum)
