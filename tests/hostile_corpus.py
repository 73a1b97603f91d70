"""The hostile-input corpus of issue 32: crafted bags (and configs) made from the simulated sample
``data/sample_husky.bag`` (it has ground truth) and, where present, the real
``rl_husky_gps.bag`` (no truth), each one fault a hostile but realistic user meets.

``python tests/hostile_corpus.py OUTDIR [CASE ...]`` writes ``OUTDIR/<case>.bag`` (or, for a
case stored as a ROS2 bag, the bag directory ``OUTDIR/<case>``) and ``OUTDIR/<case>.yaml`` for
every case (or the named ones); ``generate(outdir, names)`` does the
same from Python (``tests/test_hostile_corpus.py`` calls it into a temporary folder). Generation
is deterministic: the same bytes every time, no random numbers.

A case is a function that edits the source bag's records in place (``Bag``: its connections and
``(connection, record time ns, serialised bytes)`` records, with ``edit`` to change a decoded
message; a case's ``written`` edits the bytes of the written file), registered with
``@case(...)`` and the expectation its test checks (``Expect``): the exit code, a regex one line
of the output must match (naming the topic or file and what is wrong), the bound on each
estimator's error, and, while the fault is not handled, the issue bullet and the branch that
fixes it (the test is then a strict xfail). Its docstring states what ddfuse did with it when
the corpus was written (the "before" figures).
"""

from __future__ import annotations

import functools
import math
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
SAMPLE_BAG = ROOT / "data" / "sample_husky.bag"
SAMPLE_CONFIG = ROOT / "data" / "sample_husky.yaml"
HUSKY_BAG_NAME = "rl_husky_gps.bag"
HUSKY_CONFIG = ROOT / "data" / "configs" / "rl_husky_gps.yaml"

# the sample's topics (data/sample_husky.yaml)
ODOM, IMU, FIX = "/odom", "/imu/data", "/fix"
SENSORS = (ODOM, IMU, FIX)
HUSKY_ODOM = "/husky_velocity_controller/odom"


@dataclass(frozen=True)
class Expect:
    """What a case's run must show.

    ``rc``: the allowed exit codes. ``message``: a regex (case-insensitive) that one line of
    stdout or stderr must match, with the case's name (in its bag's and output's paths) written
    CASE there. ``bound``: the name of the accuracy check in the test (see
    ``tests/test_hostile_corpus.py``, where each bound is derived), None for none.
    ``absent``: regexes no output line may match. ``xfail``: "<bullet>; fixed by the <branch>
    branch" while ddfuse fails the case. ``counted``: the message may instead be a key of
    metrics.json's ``rejected_messages`` ("<topic>: <reason>", the count of a dropped message:
    one bad message dropped, counted and named is handled)."""

    rc: tuple[int, ...] = (0,)
    message: str | None = None
    counted: bool = False
    bound: str | None = "one_sample"
    absent: tuple[str, ...] = ()
    xfail: str | None = None


@dataclass(frozen=True)
class Case:
    name: str
    source: str  # "sample" (data/sample_husky.bag) or "husky" (rl_husky_gps.bag)
    make: Callable[[Bag], None]
    expect: Expect
    command: str = "run"  # or "inspect"
    config: Callable[[dict], None] | None = None  # edits the source config in place
    holdout: str | None = None  # the --gps-holdout of the reference run a bound is taken from
    written: Callable[[Path], None] | None = None  # edits the written bag file in place
    storage: str = "ros1"  # the case's bag: "ros1", or a ROS2 bag in "sqlite3" or "mcap"

    @property
    def doc(self) -> str:
        return (self.make.__doc__ or "").strip()


CASES: dict[str, Case] = {}


def case(source: str = "sample", *, command: str = "run", config=None, holdout=None,
         written=None, storage: str = "ros1", **expect):
    """Register the decorated function as a case named after it."""
    def register(make):
        CASES[make.__name__] = Case(make.__name__, source, make, Expect(**expect), command,
                                    config, holdout, written, storage)
        return make
    return register


# --- the source bag's records ---------------------------------------------------------------

@dataclass
class Conn:
    topic: str
    msgtype: str
    msgdef: str
    md5sum: str


@dataclass
class Bag:
    """A ROS1 bag's connections and records, edited by a case before it is written."""

    conns: list[Conn]
    records: list[list]  # [connection index, record time ns, bytes]
    store: object = field(repr=False)

    @classmethod
    def read(cls, path: Path) -> Bag:
        from rosbags.rosbag1 import Reader
        from rosbags.typesys import Stores, get_typestore

        conns, index, records = [], {}, []
        with Reader(path) as r:
            for c in r.connections:
                index[c.id] = len(conns)
                conns.append(Conn(c.topic, c.msgtype, c.msgdef.data, c.digest))
            for c, t, raw in r.messages():
                records.append([index[c.id], t, bytes(raw)])
        return cls(conns, records, get_typestore(Stores.ROS1_NOETIC))

    def write(self, path: Path) -> Path:
        from rosbags.rosbag1 import Writer

        path.unlink(missing_ok=True)
        with Writer(path) as w:
            ids = [w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef, md5sum=c.md5sum)
                   for c in self.conns]
            for ci, t, raw in self.records:
                w.write(ids[ci], t, raw)
        return path

    def write_ros2(self, path: Path, storage: str) -> Path:
        """The records, in their order, as a ROS2 bag directory at ``path`` ('sqlite3', or
        'mcap' with zstd chunks as ``ros2 bag record`` writes them): each message migrated to
        its ROS2 Humble type (the header loses its seq) and serialised as CDR."""
        import shutil

        from rosbags.convert.converter import migrate_message
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        shutil.rmtree(path, ignore_errors=True)
        dst = get_typestore(Stores.ROS2_HUMBLE)
        writer = Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3
                        if storage == "sqlite3" else StoragePlugin.MCAP)
        if storage == "mcap":
            writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        cache: dict = {}
        with writer:
            ids = [writer.add_connection(c.topic, c.msgtype, typestore=dst) for c in self.conns]
            for ci, t, raw in self.records:
                msgtype = self.conns[ci].msgtype
                msg = migrate_message(self.store, dst, msgtype, msgtype, cache,
                                      self.store.deserialize_ros1(raw, msgtype))
                writer.write(ids[ci], t, dst.serialize_cdr(msg, msgtype))
        return path

    @property
    def t0_ns(self) -> int:
        return min(t for _, t, _ in self.records)

    def of(self, topic: str) -> list[list]:
        """The records of ``topic``, in bag order (the same list objects: edit them in place)."""
        return [r for r in self.records if self.conns[r[0]].topic == topic]

    def at(self, topic: str, seconds: float) -> list:
        """The first record of ``topic`` at or after ``seconds`` past the bag's first record."""
        t = self.t0_ns + round(seconds * 1e9)
        return next(r for r in self.of(topic) if r[1] >= t)

    def edit(self, rec: list, change: Callable[[object], None]) -> None:
        """Decode ``rec``'s message, apply ``change`` to it, serialise it back."""
        msgtype = self.conns[rec[0]].msgtype
        msg = self.store.deserialize_ros1(rec[2], msgtype)
        change(msg)
        rec[2] = bytes(self.store.serialize_ros1(msg, msgtype))


def _shift_stamp(msg, ns: int) -> None:
    stamp = msg.header.stamp
    total = stamp.sec * 1_000_000_000 + stamp.nanosec + ns
    stamp.sec, stamp.nanosec = divmod(total, 1_000_000_000)


def _set_cov(cov) -> Callable[[object], None]:
    def change(m):
        m.position_covariance = np.array(cov, dtype=np.float64)
    return change


# --- single bad messages: handled already (dropped, counted, named); they must stay so ------

@case(message=r"/odom\b.*(nan|non-finite|not finite|invalid)", counted=True)
def odom_nan_speed(bag: Bag) -> None:
    """One /odom message (40 s in) with twist.linear.x = NaN.
    Before: dropped and counted ("/odom: non-finite stamp or twist": 1 in
    metrics.json), exit 0; every ATE as clean (ekf 0.114 m, batch 0.082 m)."""
    bag.edit(bag.at(ODOM, 40.0), lambda m: setattr(m.twist.twist.linear, "x", math.nan))


def _stated_gps_covariance(cfg: dict) -> None:
    """The fixes' own covariance, not the config's noise.horizontal, is what the GPS states."""
    cfg["sensors"]["gps"][0].pop("noise", None)


@case(config=_stated_gps_covariance, message=r"/fix\b.*(covariance|variance)", counted=True)
def gps_zero_covariance(bag: Bag) -> None:
    """One /fix (40 s in) stating a zero position covariance.
    Before: dropped and counted ("/fix: position_covariance unusable (not symmetric
    positive definite); set sensors.gps[0].noise.horizontal": 1), exit 0; ATE as clean (ekf
    0.114, batch 0.080 m)."""
    bag.edit(bag.at(FIX, 40.0), _set_cov([0.0] * 9))


@case(config=_stated_gps_covariance, message=r"/fix\b.*(covariance|variance|negative)",
      counted=True)
def gps_negative_covariance(bag: Bag) -> None:
    """One /fix (40 s in) stating a variance of -1 m^2 east and north.
    Before: dropped and counted (the same "position_covariance unusable" line),
    exit 0; ATE as clean (ekf 0.114, batch 0.080 m)."""
    bag.edit(bag.at(FIX, 40.0), _set_cov([-1.0, 0, 0, 0, -1.0, 0, 0, 0, 4.0]))


@case(message=r"/fix\b.*(no.?fix|status)", counted=True)
def gps_no_fix(bag: Bag) -> None:
    """One /fix (40 s in) with status NO_FIX (-1) and a position 1 km north (what a receiver
    without a fix may leave in the fields).
    Before: dropped and counted ("/fix: status NO_FIX": 1), exit 0; ATE as clean
    (ekf 0.114, smoother 0.101, batch 0.080 m)."""
    def change(m):
        m.status.status = -1
        m.latitude += 0.009
    bag.edit(bag.at(FIX, 40.0), change)


@case(message=r"/fix\b.*(\(0, ?0\)|0\.0*, ?0\.0*|zero|null island|latitude)", counted=True)
def gps_zero_zero_fix(bag: Bag) -> None:
    """One /fix (40 s in) at latitude 0, longitude 0 with status FIX.
    Before: dropped and counted ("/fix: latitude and longitude both 0: a receiver's
    placeholder, not a fix": 1), exit 0; ATE as clean (ekf 0.114, batch 0.080 m)."""
    def change(m):
        m.latitude, m.longitude = 0.0, 0.0
    bag.edit(bag.at(FIX, 40.0), change)


@case(message=r"/imu/data\b.*(quaternion|orientation)", counted=True)
def imu_zero_quaternion(bag: Bag) -> None:
    """One /imu/data message (40 s in) with orientation (0, 0, 0, 0).
    Before: counted ("/imu/data: orientation is not a finite unit quaternion: yaw not
    used ...": 1), exit 0; ATE as clean (ekf 0.114, smoother 0.101, batch 0.082 m)."""
    def change(m):
        o = m.orientation
        o.x = o.y = o.z = o.w = 0.0
    bag.edit(bag.at(IMU, 40.0), change)


# --- robot limits ------------------------------------------------------------------------------

SPEED_MESSAGE = r"/odom\b.*(speed|velocity|\bv\b|limit|max|absurd|implausible)"


@case(message=SPEED_MESSAGE)
def odom_speed_1e6(bag: Bag) -> None:
    """One /odom message (40 s in) with v = 1e6 m/s (a driver glitch).
    Before: exit 0, no warning; smoother 20.4 km ATE (119 km largest) and ERROR, batch
    ERROR (4 re-initialisations) with no track, smoother_lagged ERROR; the EKFs as clean (ekf
    0.114 m)."""
    bag.edit(bag.at(ODOM, 40.0), lambda m: setattr(m.twist.twist.linear, "x", 1e6))


@case(message=SPEED_MESSAGE)
def odom_speed_20(bag: Bag) -> None:
    """One /odom message (40 s in) with v = 20 m/s (the robot's top speed is about 1 m/s).
    Before: exit 0, no warning; smoother 1.24 m ATE (clean 0.101), smoother_lagged
    1.09 (0.088), batch 1.02 (0.082); the EKFs as clean."""
    bag.edit(bag.at(ODOM, 40.0), lambda m: setattr(m.twist.twist.linear, "x", 20.0))


@case(message=r"/imu/data\b.*(yaw.?rate|gyro|angular|limit|max|absurd|implausible)")
def imu_gyro_30(bag: Bag) -> None:
    """One /imu/data message (40 s in) with angular_velocity.z = 30 rad/s.
    Before: exit 0, no warning; smoother 0.94 m ATE (clean 0.101), smoother_lagged 0.86
    (0.088), batch 1.98 (0.082); the EKFs as clean."""
    bag.edit(bag.at(IMU, 40.0), lambda m: setattr(m.angular_velocity, "z", 30.0))


@case("husky", message=r"/husky_velocity_controller/odom\b.*(speed|velocity|\bv\b|limit|max"
      r"|absurd|implausible)", bound="near_clean_track")
def husky_odom_speed_1e6(bag: Bag) -> None:
    """rl_husky_gps.bag with one odometry message (100 s in) at v = 1e6 m/s.
    Before: exit 0, no warning; the smoother 86 km RMS from its clean track and
    ERROR, smoother_lagged 46 m and ERROR, batch ERROR with no track (4 re-initialisations);
    the EKFs within 0.5 m of their clean tracks."""
    bag.edit(bag.at(HUSKY_ODOM, 100.0), lambda m: setattr(m.twist.twist.linear, "x", 1e6))


# --- gaps --------------------------------------------------------------------------------------

GAP = (30.0, 90.0)


@case(message=r"(gap|hole|silen|outage|no (sensor )?(data|message|measurement)).*\b(59|60)"
      r"(\.\d+)? ?s|\b(59|60)(\.\d+)? ?s.*(gap|hole|silen|outage|no (data|message|measurement))",
      bound="gap")
def gap_60s(bag: Bag) -> None:
    """No message of any sensor (/odom, /imu/data, /fix) from 30 s to 90 s; the ground truth
    goes on (it scores the run).
    Before: exit 0, no warning; largest error ekf 39 m, ekf_igvc 80 m (the robot went
    60 m in the hole), smoother 39 m; ATE ekf 1.62 m, ekf_igvc 3.27, smoother 1.62, smoother_lagged
    0.15, batch 0.15 (clean 0.08-0.13)."""
    lo, hi = (bag.t0_ns + round(s * 1e9) for s in GAP)
    bag.records = [r for r in bag.records
                   if not (bag.conns[r[0]].topic in SENSORS and lo <= r[1] < hi)]


# --- ground truth ------------------------------------------------------------------------------

TRUTH = "/ground_truth"


@case(message=r"/ground_truth\b.*4 of \d+ ground-truth samples.*left out of the scores",
      bound="truth_glitch")
def truth_spins(bag: Bag) -> None:
    """Four /ground_truth poses (40 s in, 20 Hz) whose yaw turns a full circle and back in
    0.25 s, as a resampled mocap truth interpolated across +-pi the long way (UTIAS MRCLAM's,
    17 times in 1500 s); the robot's max_yaw_rate is 0.8 rad/s.
    Before: exit 0, no warning; those poses scored up to 180 deg off: mean NEES ekf 2.89 ->
    309, smoother 2.59 -> 338, batch 2.32 -> 3021 (the position ATE as clean)."""
    first = bag.of(TRUTH).index(bag.at(TRUTH, 40.0))
    for k, rec in enumerate(bag.of(TRUTH)[first:first + 4], start=1):
        def spin(m, a=2.0 * math.pi * k / 5.0):
            o = m.pose.pose.orientation
            yaw = 2.0 * math.atan2(o.z, o.w) + a
            o.x = o.y = 0.0
            o.z, o.w = math.sin(yaw / 2.0), math.cos(yaw / 2.0)
        bag.edit(rec, spin)


# --- time --------------------------------------------------------------------------------------

STEP_AT, STEP_S = 60.0, 10.0
CLOCK_STEP_MESSAGE = r"(clock|time|stamp).*(back|jump|step|earlier|decreas)"


@case(message=CLOCK_STEP_MESSAGE, bound="clock_step")
def clock_back_10s(bag: Bag) -> None:
    """The recording clock steps back 10 s at 60 s: every message after it (the ground truth
    too) has its header stamp and record time 10 s earlier, so 10 s of stamps repeat.
    Before: exit 0, no warning on the terminal; 1158 messages dropped as late (counted
    under "arrived after messages stamped up to more than reorder_window ... later"); ATE ekf
    1.05 m (clean 0.114), smoother 1.05, batch 4.68 (0.082; largest 10.3 m); NEES 418-8141."""
    step = bag.t0_ns + round(STEP_AT * 1e9)
    back = -round(STEP_S * 1e9)
    for r in bag.records:
        if r[1] >= step:
            r[1] += back
            bag.edit(r, lambda m: _shift_stamp(m, back))


@case(storage="sqlite3", message=CLOCK_STEP_MESSAGE, bound="clock_step")
def clock_back_10s_sqlite3(bag: Bag) -> None:
    """``clock_back_10s`` in a ROS2 bag with sqlite3 storage, written in the order recorded
    (rows numbered in that order, record times 10 s back after the step).
    Before: read by rosbags sorted by record time, the 10 s after the step interleaved with the
    10 s before; exit 0, no word of the clock; 108 samples rejected as physically implausible
    (/fix 22, /imu/data 81, /odom 5); ATE ekf 1.06 m (clean 0.114; largest 9.5 m), smoother
    1.26, smoother_lagged 3.09, batch 5.42 (0.082); NEES 1107-9451. After (read in row order):
    one warning, nothing rejected, ATE ekf 0.115, batch 0.082."""
    clock_back_10s(bag)


@case(storage="mcap", message=CLOCK_STEP_MESSAGE, bound="clock_step")
def clock_back_10s_mcap(bag: Bag) -> None:
    """``clock_back_10s`` in a ROS2 bag with MCAP storage (zstd chunks), written in the order
    recorded.
    Before: the figures of ``clock_back_10s_sqlite3``, to the last digit (exit 0, no word of
    the clock, 108 samples rejected, ATE ekf 1.06 m, batch 5.42). After (read in file order):
    the same as there."""
    clock_back_10s(bag)


@case(message=r"(/odom|/imu/data|/fix)\b.*duplicat|duplicat.*(/odom|/imu/data|/fix)\b",
      bound="duplicates")
def duplicates(bag: Bag) -> None:
    """Every sensor message (/odom, /imu/data, /fix) recorded twice, byte for byte.
    Before: exit 0, no warning; ATE as clean (ekf 0.118 m) but NEES ekf 2.89 -> 4.53,
    ekf_igvc 3.35 -> 4.75, smoother 2.59 -> 3.81, batch 2.32 -> 4.03."""
    out = []
    for r in bag.records:
        out.append(r)
        if bag.conns[r[0]].topic in SENSORS:
            out.append(list(r))
    bag.records = out


# --- GPS lies ----------------------------------------------------------------------------------

JUMP = (50.0, 70.0)


@case(config=_stated_gps_covariance,
      message=r"/fix\b.*(covariance|variance|sigma).*(1e-12|implausib|floor|too small|unrealistic"
      r"|below)|/fix\b.*floor")
def gps_covariance_1e_12(bag: Bag) -> None:
    """Every /fix states a position covariance of 1e-12 m^2.
    Before: exit 0, no warning about it; ATE ekf 2.34 m (clean 0.114), ekf_igvc
    2.22, smoother 2.72, smoother_lagged 2.64, batch 1.21 (0.082); NEES 7.7e3-5.4e5."""
    for r in bag.of(FIX):
        bag.edit(r, _set_cov([1e-12, 0, 0, 0, 1e-12, 0, 0, 0, 1e-12]))


@case(command="inspect",
      message=r"/fix\b.*(implausib|unrealistic|too small|suspicious|floor|below|tiny)",
      bound=None)
def inspect_gps_covariance_1e_12(bag: Bag) -> None:
    """``inspect`` on the bag whose /fix states 1e-12 m^2.
    Before: "/fix: var east 1e-12; covariance type [2]; 0 NO_FIX of 297" and
    "the stated median sigma 0.00 m would give 0.00 m", without comment."""
    gps_covariance_1e_12(bag)


@case(message=r"/fix\b.*(disagree|jump|inconsistent|odometry|reject|outlier|conflict)",
      bound="dead_reckoning", holdout=f"window:{JUMP[0]:g}:{JUMP[1]:g}")
def gps_jump_50m_20s(bag: Bag) -> None:
    """Every /fix from 50 s to 70 s is 50 m east of the truth (a multipath lock held 20 s).
    Before: exit 0, no warning; ATE ekf 20.4 m, ekf_igvc 20.5 (largest 52 m),
    smoother 8.2 km and ERROR, smoother_lagged ERROR, batch ERROR with no track; with the
    window's fixes withheld instead (the bound's reference) ekf 0.129 m, batch 0.086."""
    lo, hi = (bag.t0_ns + round(s * 1e9) for s in JUMP)
    # rad of longitude (at the sample's datum latitude, WGS84 equatorial radius)
    east = 50.0 / (6378137.0 * math.cos(math.radians(47.397742)))

    def change(m):
        m.longitude += math.degrees(east)
    for r in bag.of(FIX):
        if lo <= r[1] < hi:
            bag.edit(r, change)


# --- a damaged bag -----------------------------------------------------------------------------

def damage(path: Path) -> None:
    """Flip one byte of the message definition in /fix's first connection record (the first
    ``topic=/fix`` field of the file: in the first chunk's connection record)."""
    raw = bytearray(path.read_bytes())
    topic = raw.find(b"topic=" + FIX.encode())
    at = raw.find(b"message_definition=", topic)
    raw[at + len(b"message_definition=") + 10] |= 0x80
    path.write_bytes(bytes(raw))


@case(written=damage, message=r"CASE\.bag\b.*(damag|corrupt|invalid|unreadable|broken)")
def damaged_connection(bag: Bag) -> None:
    """The first connection record of /fix inside a chunk has one byte of its
    message_definition text flipped (0x80 set: not UTF-8 any more); every message is intact.
    Before: exit 2, "ddfuse: error: ...damaged_connection.bag: no configured sensor
    topic has a message (/odom ..., /imu/data ..., /fix ...): nothing to estimate from"; inspect
    lists every message."""


# --- tracebacks, exit codes --------------------------------------------------------------------

@case(command="inspect", bound=None, rc=(0, 2),
      message=r"/fix\b.*\b(two|2|both|mixed|several|more than one|differ\w*)\b.*\btypes\b"
      r"|/fix\b.*NavSatFix.*PoseStamped|/fix\b.*PoseStamped.*NavSatFix")
def inspect_gps_two_types(bag: Bag) -> None:
    """/fix carries a second connection of type geometry_msgs/PoseStamped (10 messages, 1 Hz
    from 20 s) beside its NavSatFix.
    Before: a traceback (IndexError in baginfo._summarise, ``ctype = {r[6] for r
    in recs}``)."""
    msgtype = "geometry_msgs/msg/PoseStamped"
    defs = bag.store.generate_msgdef(msgtype)
    bag.conns.append(Conn(FIX, msgtype, defs[0], defs[1]))
    ci = len(bag.conns) - 1
    for k in range(10):
        t = bag.t0_ns + round((20 + k) * 1e9)
        T = bag.store.types
        msg = T[msgtype](
            T["std_msgs/msg/Header"](0, T["builtin_interfaces/msg/Time"](
                *divmod(t, 1_000_000_000)), "gps"),
            T["geometry_msgs/msg/Pose"](T["geometry_msgs/msg/Point"](0.0, 0.0, 0.0),
                                        T["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0)))
        bag.records.append([ci, t, bytes(bag.store.serialize_ros1(msg, msgtype))])
    bag.records.sort(key=lambda r: r[1])


def _no_initial_pose(cfg: dict) -> None:
    cfg.pop("initial_pose", None)


@case(config=_no_initial_pose, bound=None, rc=(1, 2, 3),
      message=r"(every|all|no|none of the) estimators?\b.*(error|fail|never|no estimate|stopped)",
      absent=(r"initial_pose: ground_truth",))
def every_estimator_error(bag: Bag) -> None:
    """Only the first /fix is kept and the config sets no initial_pose: no estimator can start
    (the heading comes from the GPS course, which one fix cannot give).
    Before: exit 0; every row ERROR "no estimate: it never started", the EKFs'
    adding "with initial_pose: ground_truth an EKF waits for a GroundTruthPose measurement"
    though the config sets no initial_pose."""
    fixes = bag.of(FIX)
    bag.records = [r for r in bag.records if r is fixes[0] or bag.conns[r[0]].topic != FIX]


# --- generating --------------------------------------------------------------------------------

def source_paths(source: str, shared_data: Path | None = None) -> tuple[Path, Path]:
    """(bag, config) of a source; the real bag is looked for in ``shared_data``."""
    if source == "sample":
        return SAMPLE_BAG, SAMPLE_CONFIG
    if shared_data is None:
        shared_data = os.environ.get("DDFUSE_SHARED_DATA", ROOT.parent / "shared" / "data")
    return Path(shared_data) / HUSKY_BAG_NAME, HUSKY_CONFIG


@functools.cache
def _read(path: Path) -> Bag:
    return Bag.read(path)


def generate(outdir: Path, names=None, shared_data: Path | None = None) -> dict[str, Path]:
    """Write ``<case>.bag`` and ``<case>.yaml`` into ``outdir`` for the named cases (default:
    all whose source bag is present); returns {case: bag path}."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    written = {}
    for name in names or CASES:
        c = CASES[name]
        bag_path, config_path = source_paths(c.source, shared_data)
        if not bag_path.is_file():
            continue
        src = _read(bag_path)
        bag = Bag([Conn(**vars(k)) for k in src.conns], [list(r) for r in src.records],
                  src.store)
        c.make(bag)
        out = (bag.write(outdir / f"{name}.bag") if c.storage == "ros1"
               else bag.write_ros2(outdir / name, c.storage))
        if c.written:
            c.written(out)
        cfg = yaml.safe_load(config_path.read_text())
        if c.config:
            c.config(cfg)
        (outdir / f"{name}.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
        written[name] = out
    return written


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit("usage: python tests/hostile_corpus.py OUTDIR [CASE ...]")
    names = sys.argv[2:] or list(CASES)
    if set(names) - set(CASES):
        sys.exit(f"unknown case(s) {sorted(set(names) - set(CASES))}; cases: {', '.join(CASES)}")
    written = generate(Path(sys.argv[1]), names)
    for name in names:
        print(f"{name}: {written[name]}" if name in written else
              f"{name}: skipped, {source_paths(CASES[name].source)[0]} not found")
