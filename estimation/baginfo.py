"""Facts about a bag (topics, types, counts, rates, span, covariance sanity) and a suggested config.

``bag_info(path)`` decodes every message of the types ddfuse understands and summarises each
topic from its header stamps; ``suggest_config(info)`` turns the facts into a config tree that
``estimation.config.parse_config`` accepts. For an IMU, the mean specific force tells which sensor
axis points up (gravity) and the correlation of each gyro axis with the odometry yaw rate tells
which axis measures yaw rate: the suggested ``mount`` rotates that axis onto body z.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from ddfuse.estimation import gps_scatter, heading_survey, ros1_scan, rosmsg
from ddfuse.estimation.bag_reader import open_reader
from ddfuse.estimation.bags import BagStream
from ddfuse.estimation.config import (
    DEFAULT_GPS_MIN_STD,
    DEFAULT_MAX_SPEED,
    DEFAULT_MAX_YAW_RATE,
    parse_config,
)
from ddfuse.estimation.converters import Reject, gps_fix
from ddfuse.estimation.errors import BagError, DdfuseError
from ddfuse.estimation.frames import GRAVITY, body_x_tilt, rpy_matrix, yaw_of_quat
from ddfuse.estimation.geodesy import geodetic_to_enu
from ddfuse.estimation.gps_scatter import FixScatter
from ddfuse.estimation.truth_screen import screen_truth


@dataclass
class TopicInfo:
    """What one topic holds. Rates from header stamps (Hz); times in seconds."""

    topic: str
    msgtype: str
    count: int
    t0: float = math.nan
    t1: float = math.nan
    rate_hz: float = math.nan
    median_dt: float = math.nan
    out_of_order: int = 0  # messages whose stamp is older than the previous one's
    notes: list[str] = field(default_factory=list)  # covariance sanity and other findings
    # For IMUs: mean specific force per sensor axis (m/s^2) and gyro axes' correlation with
    # the odometry yaw rate; for NavSatFix: status counts.
    accel_mean: tuple[float, float, float] | None = None
    gyro_corr: tuple[float, float, float] | None = None
    gyro_series: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    yaw_rate_series: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    has_orientation: bool = False
    orientations: np.ndarray | None = field(default=None, repr=False)  # (N, 4) x, y, z, w
    # the speed along the ground over the horizontal one, less 1 (mean 1/cos(climb) - 1 of
    # the body's forward axis, the suggested mount applied); None without orientation
    slope_excess: float | None = None
    cov_ok: bool = True  # the message covariances are usable as they are
    # messages of other types on the same topic (type -> count): not in these facts, which
    # are of ``msgtype`` alone (``count`` counts those)
    other_types: dict[str, int] = field(default_factory=dict)
    # For NavSatFix: how well neighbouring fixes predict each (its correlation_time rule)
    scatter: FixScatter | None = None


@dataclass
class BagInfo:
    path: Path
    topics: list[TopicInfo]
    t0: float
    t1: float
    error: str | None = None  # the bag breaks off (truncated): why, and where the facts stop

    @property
    def duration(self) -> float:
        return self.t1 - self.t0


def _diag_summary(name: str, values: list[float]) -> tuple[str, bool]:
    a = np.asarray(values, float)
    if a.size == 0:
        return f"{name}: none", False
    bad = int(np.sum(~np.isfinite(a) | (a <= 0)))
    lo, hi = np.nanmin(a), np.nanmax(a)
    text = f"{name} {lo:.3g}..{hi:.3g}" if lo != hi else f"{name} {lo:.3g}"
    if bad:
        text += f" ({bad} zero/invalid: set noise in the config)"
    return text, bad == 0


def _below_floor(recs: list[tuple]) -> tuple[int, float, float] | None:
    """Of NavSatFix records (stamp, status, lat, lon, alt, cov9, cov_type): how many state a
    horizontal variance (the smaller eigenvalue of the east/north block, m^2) under the floor
    for their status (``DEFAULT_GPS_MIN_STD``), the smallest such variance and its floor (m);
    None when none does."""
    n, low = 0, None
    for r in recs:
        if r[1] < 0 or r[6] == 0 or not all(map(math.isfinite, r[5])):
            continue
        std = DEFAULT_GPS_MIN_STD.get(r[1], DEFAULT_GPS_MIN_STD[0])
        var = float(np.linalg.eigvalsh(np.reshape(r[5], (3, 3))[:2, :2])[0])
        if 0.0 < var < std * std:
            n += 1
            low = (var, std) if low is None or var < low[0] else low
    return (n, *low) if n else None


def _summarise(info: TopicInfo, recs: list[tuple]) -> None:
    # an unset (zero or negative) or non-finite stamp is no time: as the reader drops such a
    # message, the facts leave it out (one zero stamp made a 30 Hz IMU 3.6e12 Hz)
    unset = [r for r in recs if not (r[0] > 0.0 and math.isfinite(r[0]))]
    if unset:
        recs = [r for r in recs if r[0] > 0.0 and math.isfinite(r[0])]
        info.notes.append(f"{len(unset)} message(s) with a zero, negative or non-finite header "
                          "stamp (a clock not set): left out of these facts; ddfuse drops them"
                          + ("; every message has one, so the topic is unusable"
                             if not recs else ""))
        if not recs:
            return
    t = np.array([r[0] for r in recs])
    info.t0, info.t1 = float(t.min()), float(t.max())
    if len(t) > 1:
        ts = np.sort(t)
        info.rate_hz = (len(t) - 1) / max(ts[-1] - ts[0], 1e-9)
        info.median_dt = float(np.median(np.diff(ts)))
        info.out_of_order = int(np.sum(np.diff(t) < 0))
    mt = info.msgtype
    if _is_ground_truth(info.topic):
        info.notes.append("looks like ground truth (pose used for scoring only)")
        if mt in (rosmsg.ODOMETRY, rosmsg.POSE_STAMPED):
            _truth_glitches(info, recs)
        return
    if mt == rosmsg.ODOMETRY:
        cov = np.array([r[5] for r in recs])
        a, ok1 = _diag_summary("twist var v", cov[:, 0])
        b, ok2 = _diag_summary("yaw_rate", cov[:, 35])
        info.notes.append(f"{a}, {b}")
        info.cov_ok = ok1 and ok2
        info.yaw_rate_series = (t, np.array([r[4][2] for r in recs]))
    elif mt == rosmsg.IMU:
        ocov = np.array([r[2] for r in recs])
        info.has_orientation = bool(np.all(ocov[:, 0] != -1.0))
        if info.has_orientation:
            info.orientations = np.array([r[1] for r in recs], float)
        acc = np.array([r[5] for r in recs])
        info.accel_mean = tuple(float(v) for v in acc.mean(axis=0))
        info.gyro_series = (t, np.array([r[3] for r in recs]))
        a, ok1 = _diag_summary("gyro var z", np.array([r[4][8] for r in recs]))
        b, _ = _diag_summary("yaw var", ocov[:, 8]) if info.has_orientation else ("no yaw", True)
        info.notes.append(f"{a}, {b}; mean specific force (x, y, z) = "
                          + ", ".join(f"{v:+.2f}" for v in info.accel_mean) + " m/s^2")
        info.cov_ok = ok1
    elif mt == rosmsg.NAVSATFIX:
        status = [r[1] for r in recs]
        ctype = {r[6] for r in recs}
        a, ok = _diag_summary("var east", [r[5][0] for r in recs])
        nofix = sum(s < 0 for s in status)
        unusable = sum(r[1] >= 0 and not _usable_fix(r) for r in recs)
        info.notes.append(f"{a}; covariance type {sorted(ctype)}; "
                          f"{nofix} NO_FIX of {len(status)}"
                          + (f"; {unusable} more with a position ddfuse drops (latitude/"
                             "longitude out of range or both 0)" if unusable else ""))
        info.cov_ok = ok and 0 not in ctype
        low = _below_floor(recs)
        if low:
            n, var, std = low
            info.notes.append(
                f"{n} fix(es) state a horizontal variance below what a receiver of their status "
                f"can claim (smallest {var:.3g} m^2, floor ({std:g} m)^2): ddfuse fuses them with "
                "the floor (the GPS sensor's min_std sets it)")
        info.scatter = fix_scatter(recs, info.cov_ok)
        if info.scatter is not None:
            info.notes.append(info.scatter.describe())
    elif mt == rosmsg.LANDMARK:
        ids = sorted({r[1] for r in recs}, key=lambda s: (len(s), s))
        info.notes.append(f"{len(ids)} landmark ids: {', '.join(ids)}")


def _truth_glitches(info: TopicInfo, recs: list[tuple]) -> None:
    """A note on the pose truth's samples no robot can produce (``truth_screen``, at the
    default limits: the bag alone says nothing of the robot's)."""
    recs = sorted(recs, key=lambda r: r[0])
    t = np.array([r[0] for r in recs])
    pose = np.array([(r[1][0], r[1][1], yaw_of_quat(r[2])) for r in recs], float)
    _, found = screen_truth(info.topic, t, pose, DEFAULT_MAX_SPEED, DEFAULT_MAX_YAW_RATE)
    line = found.warning(float(t[0]))
    if line:
        info.notes.append(line.removeprefix(f"{info.topic}: ")
                          + " (at the default robot limits: ddfuse run takes the config's)")


# m: the GPS noise the suggested config states for a topic whose covariances are unusable
SUGGESTED_GPS_SIGMA = 2.0


def _fused_variance(rec: tuple, cov_ok: bool) -> float:
    """The per-axis horizontal variance (m^2) a NavSatFix record is fused with under the
    suggested config: ``SUGGESTED_GPS_SIGMA`` squared when the topic's covariances are not
    usable, else half the trace of its stated horizontal covariance with the converter's
    default floor for its status (``DEFAULT_GPS_MIN_STD``) on each eigenvalue."""
    if not cov_ok:
        return SUGGESTED_GPS_SIGMA ** 2
    if not all(map(math.isfinite, rec[5])):
        return math.nan
    std = DEFAULT_GPS_MIN_STD.get(rec[1], 0.01)
    lam = np.linalg.eigvalsh(np.reshape(rec[5], (3, 3))[:2, :2])
    return float(np.maximum(lam, std * std).mean())


def fix_scatter(recs: list[tuple], cov_ok: bool = True) -> FixScatter | None:
    """How well the neighbouring fixes predict each fix (``estimation.gps_scatter``), of the
    NavSatFix records (t, status, lat, lon, alt, cov9, cov_type) the reader would take, each
    with the variance the suggested config fuses it with (``_fused_variance``); None with too
    few fixes."""
    ok = [r for r in recs if _usable_fix(r)]
    if len(ok) < gps_scatter.MIN_FIXES:
        return None
    t = np.array([r[0] for r in ok])
    lat, lon = (np.array([r[k] for r in ok]) for k in (2, 3))
    e, n, _ = geodetic_to_enu(lat, lon, np.zeros_like(lat), lat[0], lon[0], 0.0)
    var = [_fused_variance(r, cov_ok) for r in ok]
    return gps_scatter.fix_scatter(t, np.column_stack([e, n]), np.array(var))


def _usable_fix(rec: tuple) -> bool:
    """Whether the reader would take the NavSatFix record's position (its checks: status,
    stamp, latitude/longitude in range, not (0, 0)): one fix at 95 deg latitude made the
    scatter 388 km."""
    try:
        gps_fix(rec, "")
    except Reject:
        return False
    return rec[0] > 0.0


def _is_ground_truth(topic: str) -> bool:
    t = topic.lower().replace("_", "").replace("-", "")
    return "groundtruth" in t or t.endswith("/gt") or "vicon" in t or "mocap" in t


def bag_info(path: str | Path) -> BagInfo:
    """Decode every message of a known type in the bag and summarise each topic.

    A ROS1 bag that rosbags cannot open because its index is missing or damaged (truncated) is
    read from the front by ``estimation.ros1_scan``, as ``ddfuse run`` does: the BagInfo of what
    could be read is returned with ``error`` saying that the bag is truncated and where it
    stops."""
    path = Path(path)
    try:
        reader = open_reader(path)
    except BagError as e:
        if not ros1_scan.has_magic(path):
            raise
        return _bag_info_unindexed(path, e)
    recs: dict[str, list] = {}
    infos: dict[str, TopicInfo] = {}
    read = 0
    damage = None
    try:
        per_type: dict[str, dict[str, int]] = {}  # topic -> message type -> count
        for c in reader.connections:
            types = per_type.setdefault(c.topic, {})
            types[c.msgtype] = types.get(c.msgtype, 0) + c.msgcount
        for topic, types in per_type.items():
            infos[topic] = _topic_of_types(topic, types)
        if not any(i.count for i in infos.values()):
            raise BagError(f"{path}: the bag has no messages ("
                           + (f"topics {', '.join(sorted(infos))}, each empty"
                              if infos else "no topics")
                           + "): nothing to inspect or suggest a config from")
        known = [c for c in reader.connections if c.msgtype in rosmsg.EXTRACTORS]
        for conn, _, raw in reader.messages(connections=known):
            read += 1
            if conn.msgtype != infos[conn.topic].msgtype:  # a second type on the topic
                continue
            fast, slow = rosmsg.EXTRACTORS[conn.msgtype]
            try:
                rec = fast(raw) if fast and not reader.is2 else slow(
                    reader.deserialize(raw, conn.msgtype))
            except Exception:  # counted below as undecodable
                continue
            recs.setdefault(conn.topic, []).append(rec)
    except BagError:
        raise
    except Exception as e:  # rosbags raises many types on damaged storage
        # what was read before the damage is still worth showing, as for a truncated bag
        damage = f"{type(e).__name__}: {e}"
    finally:
        reader.close()
    if damage is not None and not read:
        raise BagError(f"{path}: bag is damaged or truncated ({damage}); no message could be "
                       "read")
    info = _finish(path, infos, recs, cut_short=damage is not None)
    if damage is not None:
        info.error = (f"{path}: bag is damaged or truncated ({damage}); the facts above are of "
                      f"the {read} messages read before it (the counts are the index's)")
    return info


def _bag_info_unindexed(path: Path, open_error: BagError) -> BagInfo:
    """bag_info of a ROS1 bag without a usable index, read from the front (see bag_info)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    scan = ros1_scan.Ros1Scan(path)
    store = get_typestore(Stores.EMPTY)
    recs: dict[str, list] = {}
    infos: dict[str, TopicInfo] = {}
    try:
        for item in scan:
            if type(item) is ros1_scan.Connection:
                infos.setdefault(item.topic, TopicInfo(item.topic, item.msgtype, 0))
                fast = rosmsg.EXTRACTORS.get(item.msgtype, (None, None))[0]
                if item.msgtype in rosmsg.EXTRACTORS and fast is None and \
                        item.msgtype not in store.fielddefs:
                    # a definition that cannot be used: its messages count as undecodable
                    with contextlib.suppress(Exception):
                        store.register(get_types_from_msg(item.msgdef, item.msgtype)
                                       if item.msgdef
                                       else get_typestore(Stores.ROS1_NOETIC).fielddefs)
                continue
            conn = item.conn
            info = infos[conn.topic]
            if conn.msgtype != info.msgtype:  # a second type on the topic: the first one's facts
                info.other_types[conn.msgtype] = info.other_types.get(conn.msgtype, 0) + 1
                continue
            info.count += 1
            if conn.msgtype not in rosmsg.EXTRACTORS:
                continue
            fast, slow = rosmsg.EXTRACTORS[conn.msgtype]
            try:
                rec = fast(item.data) if fast else slow(
                    store.deserialize_ros1(item.data, conn.msgtype))
            except Exception:  # counted as undecodable
                continue
            recs.setdefault(conn.topic, []).append(rec)
    except ros1_scan.ScanError as e:
        raise BagError(f"{open_error}; reading it without the index fails too: {e}") from None
    st = scan.status
    what, where = st.unindexed_end()
    if not st.messages:
        raise BagError(f"{path}: {what}; no complete message before {where}")
    info = _finish(path, infos, recs)
    info.error = (f"{path}: {what}; the facts above are of the {st.messages} messages up to "
                  f"{where}")
    return info


def _topic_of_types(topic: str, types: dict[str, int]) -> TopicInfo:
    """The TopicInfo of a topic whose connections carry ``types`` (message type -> count):
    of its most frequent type (the first of equal ones), the others in ``other_types``."""
    main = max(types, key=lambda k: types[k])
    return TopicInfo(topic, main, types[main],
                     other_types={k: n for k, n in types.items() if k != main})


def _mixed_types_note(info: TopicInfo) -> str:
    """What inspect says of a topic that carries messages of several types."""
    others = ", ".join(f"{n} {rosmsg.short_type(k)}" for k, n in info.other_types.items())
    return (f"carries messages of {len(info.other_types) + 1} types: {info.count} "
            f"{rosmsg.short_type(info.msgtype)} and {others} (two publishers on one topic?); "
            f"these facts are of the {rosmsg.short_type(info.msgtype)} messages alone")


def _finish(path: Path, infos: dict[str, TopicInfo], recs: dict[str, list],
            cut_short: bool = False) -> BagInfo:
    """The BagInfo of the records read; ``cut_short``: the reading stopped at damage, so the
    messages of a topic's count that were not read need not be undecodable."""
    for info in infos.values():
        if info.other_types:
            info.notes.append(_mixed_types_note(info))
    for topic, lst in recs.items():
        _summarise(infos[topic], lst)
        undecoded = infos[topic].count - len(lst)
        if undecoded:
            infos[topic].notes.append(
                f"{undecoded} of its {infos[topic].count} messages lie past the damage or could "
                "not be decoded" if cut_short else f"{undecoded} message(s) could not be decoded")
    _correlate_gyros(list(infos.values()))
    for info in infos.values():
        _climb(info)
    t0 = min((i.t0 for i in infos.values() if math.isfinite(i.t0)), default=0.0)
    t1 = max((i.t1 for i in infos.values() if math.isfinite(i.t1)), default=0.0)
    return BagInfo(path, sorted(infos.values(), key=lambda i: i.topic), t0, t1)


# Speeds along the ground exceeding the horizontal ones by more than this share (mean 1/cos
# of the climb angle, less 1): the suggested config projects the odometry's speed with the
# IMU's climb (`slope`). rl_jackal.bag: 0.5 % (climbs to 12 deg); rl_husky_gps.bag: 0.04 %.
SLOPE_EXCESS = 1e-3
MAX_CLIMB_SAMPLES = 5000


def _climb(info: TopicInfo) -> None:
    """An IMU's climb angles: the body's forward axis from its orientation with the suggested
    mount (``imu_mount``), a note and ``slope_excess``."""
    q = info.orientations
    if q is None or not len(q) or info.accel_mean is None:
        return
    mount = rpy_matrix(*imu_mount(info))
    step = max(1, len(q) // MAX_CLIMB_SAMPLES)
    up = np.array([body_x_tilt(tuple(r), mount)[0] for r in q[::step]])
    up = up[np.isfinite(up)]
    if not len(up):
        return
    climb = np.degrees(np.arcsin(np.clip(up, -1.0, 1.0)))
    info.slope_excess = float(np.mean(1.0 / np.sqrt(1.0 - np.clip(up, -0.999, 0.999) ** 2))
                              - 1.0)
    lo, hi = np.percentile(climb, [2.5, 97.5])
    info.notes.append(
        f"climb of the body's forward axis (its orientation, the mount below): median "
        f"{np.median(climb):+.1f} deg, 95 % within {lo:+.1f}..{hi:+.1f} deg, at most "
        f"{np.abs(climb).max():.1f} deg; speeds along the ground exceed the horizontal by "
        f"{100 * info.slope_excess:.2f} %"
        + (" (the odometry's `slope` below projects them)" if info.slope_excess > SLOPE_EXCESS
           else ""))


def _correlate_gyros(infos: list[TopicInfo]) -> None:
    """Correlate each IMU gyro axis with the first odometry's yaw rate, resampled in time."""
    odom = next((i for i in infos if i.yaw_rate_series is not None), None)
    if odom is None:
        return
    to, wo = odom.yaw_rate_series
    order = np.argsort(to)
    to, wo = to[order], wo[order]
    for imu in infos:
        if imu.gyro_series is None:
            continue
        tg, wg = imu.gyro_series
        inside = (tg >= to[0]) & (tg <= to[-1])
        if inside.sum() < 10:
            continue
        ref = np.interp(tg[inside], to, wo)
        corr = []
        for k in range(3):
            g = wg[inside, k]
            s = np.std(g) * np.std(ref)
            corr.append(float(np.mean((g - g.mean()) * (ref - ref.mean())) / s) if s > 0 else 0.0)
        imu.gyro_corr = tuple(corr)
        best = int(np.argmax(np.abs(corr)))
        imu.notes.append("gyro axes' correlation with odometry yaw rate (x, y, z) = "
                         + ", ".join(f"{c:+.2f}" for c in corr)
                         + f": yaw rate is on axis {'xyz'[best]}")
        if abs(corr[best]) < YAW_RATE_AGREEMENT:
            imu.notes.append(f"{odom.topic}'s yaw rate agrees poorly with this gyro "
                             f"({abs(corr[best]):.2f} < {YAW_RATE_AGREEMENT}: skid steering or "
                             "slipping wheels?): the suggested config takes the yaw rate from "
                             "the gyro alone")


def _mount_for_up_axis(axis: int, sign: float) -> list[float]:
    """rpy (rad) of a mount whose sensor axis ``axis`` (0 x, 1 y, 2 z), with ``sign``, is up."""
    half = round(math.pi / 2, 4)
    if axis == 2:
        return [0.0, 0.0, 0.0] if sign > 0 else [round(math.pi, 4), 0.0, 0.0]
    if axis == 1:  # Rx(+90) takes sensor +y to body +z
        return [half, 0.0, 0.0] if sign > 0 else [-half, 0.0, 0.0]
    return [0.0, -half, 0.0] if sign > 0 else [0.0, half, 0.0]  # Ry(-90) takes +x to +z


def imu_mount(info: TopicInfo) -> list[float]:
    """Suggested mount rpy for an IMU: the axis that carries the yaw rate (by correlation with
    odometry) or else gravity, rotated onto body z; sign from gravity (specific force is up)."""
    if info.accel_mean is None:
        return [0.0, 0.0, 0.0]
    acc = np.array(info.accel_mean)
    up = int(np.argmax(np.abs(acc)))
    if info.gyro_corr is not None and max(abs(c) for c in info.gyro_corr) > 0.5:
        up = int(np.argmax(np.abs(info.gyro_corr)))
    if abs(abs(acc[up]) - GRAVITY) > 2.0:
        return [0.0, 0.0, 0.0]  # no clear gravity on that axis: do not guess
    return _mount_for_up_axis(up, float(np.sign(acc[up])))


# Below this correlation (on the gyro's best axis) the odometry's yaw rate is not suggested: the
# two measure the same rate, so a well-behaved differential drive agrees far better (Husky:
# 0.86); the Jackal bag's 0.53 is skid steering, and fused, its yaw rate took every estimator
# 10 m off in 61 s (the EKF's gate rejected 43 % of it; the smoother's gyro-bias factor took
# the rest as bias).
YAW_RATE_AGREEMENT = 0.8


def odometry_yaw_rate_agrees(info: BagInfo) -> bool | None:
    """Whether the first odometry's yaw rate agrees with an IMU's gyro (best axis correlation
    >= YAW_RATE_AGREEMENT); None when no IMU could be compared with it."""
    corr = [max(abs(c) for c in t.gyro_corr) for t in info.topics if t.gyro_corr is not None]
    return None if not corr else max(corr) >= YAW_RATE_AGREEMENT


def offset_surveys(path: str | Path, tree: dict) -> list[heading_survey.OffsetSurvey]:
    """The heading offset of each compass of the bag measured against the GPS course
    (``estimation.heading_survey``), reading the bag with the odometry, IMU and GPS sensors of
    the suggested config ``tree``; [] without a compass, a GPS and an odometry speed."""
    sensors = tree.get("sensors") or {}
    if not (sensors.get("gps") and sensors.get("odometry")
            and any("yaw" in s["use"] for s in sensors.get("imu") or ())):
        return []
    sub = {"sensors": {k: sensors[k] for k in ("odometry", "imu", "gps")},
           "frame": tree.get("frame") or {"datum": "first_fix"}}
    rec = None
    try:
        cfg = parse_config(sub, f"{path} (suggested config)")
        rec = heading_survey.recorder_for(cfg)
        for m in BagStream(path, cfg).prime():
            rec.add(m)
    except DdfuseError:
        # what the bag lacks for a run (no valid fix for the datum...) is inspect's to report
        # in its facts, not the survey's: the windows fitted so far stand
        pass
    return rec.surveys() if rec is not None else []


def suggest_config(info: BagInfo, surveys: list | tuple = ()) -> dict:
    """A config tree for the bag (loadable by parse_config): one sensor per known topic. The
    odometry's yaw rate is left out when an IMU's gyro shows it disagrees with the rotation
    (``odometry_yaw_rate_agrees``). A compass whose offset wanders (``surveys``,
    ``offset_surveys``) gets the heading_offset_walk that follows it."""
    walks = {sv.sensor: heading_survey.suggested_walk(sv) for sv in surveys if sv.wanders}
    sensors: dict[str, list] = {}
    gt: tuple[str, bool] | None = None  # (topic, whether it has a heading)
    odo_w = odometry_yaw_rate_agrees(info) is not False
    sloped = next((t.topic for t in info.topics if t.slope_excess is not None
                   and t.slope_excess > SLOPE_EXCESS), None)
    for t in info.topics:
        if t.count == 0 or not math.isfinite(t.t0):  # no message read with a usable stamp
            continue
        if _is_ground_truth(t.topic):
            # a pose (with heading) over a fix (position only), whatever the topics' order
            if t.msgtype in (rosmsg.ODOMETRY, rosmsg.POSE_STAMPED) or (
                    t.msgtype == rosmsg.NAVSATFIX and gt is None):
                gt = (t.topic, t.msgtype != rosmsg.NAVSATFIX)
            continue
        if t.msgtype in (rosmsg.ODOMETRY, rosmsg.TWIST_STAMPED):
            s = {"topic": t.topic, "use": ["v", "yaw_rate"] if odo_w else ["v"]}
            if not t.cov_ok or t.msgtype == rosmsg.TWIST_STAMPED:
                s["noise"] = {"v": 0.05, "yaw_rate": 0.05} if odo_w else {"v": 0.05}
            if sloped is not None:
                s["slope"] = sloped
            sensors.setdefault("odometry", []).append(s)
        elif t.msgtype == rosmsg.IMU:
            s = {"topic": t.topic, "use": ["yaw_rate"]}
            mount = imu_mount(t)
            if mount != [0.0, 0.0, 0.0]:
                s["mount"] = {"rpy": mount}
            s["noise"] = {"yaw_rate": 0.02}
            if t.has_orientation:
                s["use"] = ["yaw", "yaw_rate"]
                s["noise"]["yaw"] = 0.05
                if t.topic in walks:
                    s["noise"]["heading_offset_walk"] = walks[t.topic]
                s["heading_offset"] = "estimate"
            s["gyro_bias"] = "estimate"
            sensors.setdefault("imu", []).append(s)
        elif t.msgtype == rosmsg.NAVSATFIX:
            s = {"topic": t.topic, "lever_arm": [0.0, 0.0]}
            if not t.cov_ok:
                s["noise"] = {"horizontal": SUGGESTED_GPS_SIGMA}
            if t.scatter is not None and t.scatter.recommended:
                s["correlation_time"] = t.scatter.recommended
            sensors.setdefault("gps", []).append(s)
        elif t.msgtype == rosmsg.LANDMARK:
            guess = info.path.with_suffix(".landmarks.yaml")
            sensors.setdefault("landmarks", []).append(
                {"topic": t.topic, "map": str(guess.resolve() if guess.is_file() else "MAP.yaml")})
    cfg: dict = {"sensors": sensors}
    if gt:
        cfg["ground_truth"] = {"topic": gt[0]}
        if gt[1]:  # a fix has no heading to start from
            cfg["initial_pose"] = "ground_truth"
    if "gps" in sensors:
        cfg["frame"] = {"datum": "first_fix"}
        cfg["smoother"] = {"lag": 10.0}
    return cfg
