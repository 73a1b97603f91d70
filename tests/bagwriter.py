"""Test utility: write small ROS1 .bag, ROS2 sqlite3 and ROS2 MCAP bags with rosbags.

Messages are described independently of the format: a builder (``odometry``, ``imu``, ``navsatfix``,
``joint_state``, ``twist_stamped``, ``pose_stamped``, ``landmark``) returns a ``Msg`` that knows its
type, its header stamp and how to build itself from a typestore (ROS1 and ROS2 headers differ).
``write_bag(path, fmt, records)`` writes ``(topic, Msg)`` or ``(topic, Msg, record_time_s)``
records; the record time defaults to the header stamp, so out-of-order or broken stamps are made
by giving a different record time.

``fmt`` is one of FORMATS: 'ros1' (path is the .bag file), 'sqlite3' and 'mcap' (path is the
bag directory that rosbags creates; the storage file inside is ``<dir>/<dir name>.db3|.mcap``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from ddfuse.evaluation.simulate import LANDMARK_MSGDEF, LANDMARK_MSGTYPE
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

FORMATS = ("ros1", "sqlite3", "mcap")

# ddfuse's own landmark message, as the simulator writes it
LANDMARK_TYPE = LANDMARK_MSGTYPE

ODOMETRY = "nav_msgs/msg/Odometry"
IMU = "sensor_msgs/msg/Imu"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
JOINT_STATE = "sensor_msgs/msg/JointState"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"

Vec3 = Sequence[float]
Quat = Sequence[float]  # (x, y, z, w)


@functools.cache
def typestore(fmt: str):
    """The typestore for the format, with the landmark message type registered (one per format:
    rosbags compiles its serialisers once per typestore)."""
    store = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(LANDMARK_MSGDEF, LANDMARK_TYPE))
    return store


@dataclass
class Msg:
    """A message independent of the bag format."""

    msgtype: str
    stamp: float  # header stamp, s
    build: Callable[[object], object]  # typestore -> message object


# --- field helpers ---------------------------------------------------------------------------

def split_stamp(t: float) -> tuple[int, int]:
    """Float seconds -> (sec, nanosec), nanosec in [0, 1e9)."""
    ns = round(t * 1e9)
    return ns // 1_000_000_000, ns % 1_000_000_000


def _header(store, t: float, frame_id: str):
    sec, nsec = split_stamp(t)
    stamp = store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    header = store.types["std_msgs/msg/Header"]
    if _has_seq(store):
        return header(seq=0, stamp=stamp, frame_id=frame_id)
    return header(stamp=stamp, frame_id=frame_id)


def _has_seq(store) -> bool:
    return any(f[0] == "seq" for f in store.fielddefs["std_msgs/msg/Header"][1])


def _vec3(store, v: Vec3):
    return store.types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _point(store, v: Vec3):
    return store.types["geometry_msgs/msg/Point"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quat(store, q: Quat):
    return store.types["geometry_msgs/msg/Quaternion"](
        x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def _arr(values, n: int) -> np.ndarray:
    a = np.zeros(n, dtype=np.float64) if values is None else np.asarray(values, dtype=np.float64)
    if a.shape != (n,):
        a = a.reshape(n)
    return a


def yaw_quat(yaw: float) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) of a rotation by ``yaw`` about z."""
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def quat_mul(a: Quat, b: Quat) -> tuple[float, float, float, float]:
    """Hamilton product a * b of quaternions given as (x, y, z, w)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


def diag(*values: float) -> list[float]:
    """Row-major n x n matrix with the given diagonal."""
    n = len(values)
    m = [0.0] * (n * n)
    for i, v in enumerate(values):
        m[i * n + i] = float(v)
    return m


# --- message builders ------------------------------------------------------------------------

def odometry(t: float, v: float = 0.0, yaw_rate: float = 0.0, *, x: float = 0.0, y: float = 0.0,
             yaw: float = 0.0, lin: Vec3 | None = None, ang: Vec3 | None = None,
             quat: Quat | None = None, twist_cov=None, pose_cov=None, frame_id: str = "odom",
             child_frame_id: str = "base_link") -> Msg:
    """nav_msgs/Odometry: pose (x, y, yaw or quat) and twist (v, yaw_rate or full lin/ang)."""
    lin = (v, 0.0, 0.0) if lin is None else lin
    ang = (0.0, 0.0, yaw_rate) if ang is None else ang
    quat = yaw_quat(yaw) if quat is None else quat

    def build(s):
        T = s.types
        pose = T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](position=_point(s, (x, y, 0.0)),
                                             orientation=_quat(s, quat)),
            covariance=_arr(pose_cov, 36))
        twist = T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=_vec3(s, lin), angular=_vec3(s, ang)),
            covariance=_arr(twist_cov, 36))
        return T[ODOMETRY](header=_header(s, t, frame_id), child_frame_id=child_frame_id,
                           pose=pose, twist=twist)

    return Msg(ODOMETRY, t, build)


def imu(t: float, *, quat: Quat = (0.0, 0.0, 0.0, 1.0), angvel: Vec3 = (0.0, 0.0, 0.0),
        accel: Vec3 = (0.0, 0.0, 9.80665), ocov=None, wcov=None, acov=None,
        frame_id: str = "imu_link") -> Msg:
    """sensor_msgs/Imu. Covariances are 9-element row-major lists (default zeros)."""

    def build(s):
        return s.types[IMU](header=_header(s, t, frame_id), orientation=_quat(s, quat),
                            orientation_covariance=_arr(ocov, 9),
                            angular_velocity=_vec3(s, angvel),
                            angular_velocity_covariance=_arr(wcov, 9),
                            linear_acceleration=_vec3(s, accel),
                            linear_acceleration_covariance=_arr(acov, 9))

    return Msg(IMU, t, build)


def navsatfix(t: float, lat: float, lon: float, alt: float = 0.0, *, status: int = 0,
              cov=None, cov_type: int = 1, service: int = 1, frame_id: str = "gps") -> Msg:
    """sensor_msgs/NavSatFix; ``cov`` 9-element ENU covariance (default diag(1, 1, 4))."""
    cov = diag(1.0, 1.0, 4.0) if cov is None else cov

    def build(s):
        st = s.types["sensor_msgs/msg/NavSatStatus"](status=status, service=service)
        return s.types[NAVSATFIX](header=_header(s, t, frame_id), status=st, latitude=float(lat),
                                  longitude=float(lon), altitude=float(alt),
                                  position_covariance=_arr(cov, 9),
                                  position_covariance_type=cov_type)

    return Msg(NAVSATFIX, t, build)


def joint_state(t: float, names: Sequence[str], velocity: Sequence[float],
                position: Sequence[float] | None = None, effort: Sequence[float] | None = None,
                frame_id: str = "") -> Msg:
    """sensor_msgs/JointState with the given joint names and velocities (rad/s)."""

    def build(s):
        return s.types[JOINT_STATE](
            header=_header(s, t, frame_id), name=list(names),
            position=np.asarray(position if position is not None else [], dtype=np.float64),
            velocity=np.asarray(velocity, dtype=np.float64),
            effort=np.asarray(effort if effort is not None else [], dtype=np.float64))

    return Msg(JOINT_STATE, t, build)


def twist_stamped(t: float, v: float = 0.0, yaw_rate: float = 0.0, *, lin: Vec3 | None = None,
                  ang: Vec3 | None = None, frame_id: str = "base_link") -> Msg:
    """geometry_msgs/TwistStamped (no covariance)."""
    lin = (v, 0.0, 0.0) if lin is None else lin
    ang = (0.0, 0.0, yaw_rate) if ang is None else ang

    def build(s):
        tw = s.types["geometry_msgs/msg/Twist"](linear=_vec3(s, lin), angular=_vec3(s, ang))
        return s.types[TWIST_STAMPED](header=_header(s, t, frame_id), twist=tw)

    return Msg(TWIST_STAMPED, t, build)


def pose_stamped(t: float, x: float = 0.0, y: float = 0.0, yaw: float = 0.0, *, z: float = 0.0,
                 quat: Quat | None = None, frame_id: str = "map") -> Msg:
    """geometry_msgs/PoseStamped."""
    quat = yaw_quat(yaw) if quat is None else quat

    def build(s):
        pose = s.types["geometry_msgs/msg/Pose"](position=_point(s, (x, y, z)),
                                                  orientation=_quat(s, quat))
        return s.types[POSE_STAMPED](header=_header(s, t, frame_id), pose=pose)

    return Msg(POSE_STAMPED, t, build)


def landmark(t: float, landmark_id: str, rng: float, bearing: float = 0.0, *,
             range_variance: float = 0.01, bearing_variance: float = 0.0025,
             has_bearing: bool = True, frame_id: str = "base_link") -> Msg:
    """ddfuse_msgs/msg/LandmarkObservation."""

    def build(s):
        return s.types[LANDMARK_TYPE](header=_header(s, t, frame_id), landmark_id=landmark_id,
                                      range=float(rng), bearing=float(bearing),
                                      range_variance=float(range_variance),
                                      bearing_variance=float(bearing_variance),
                                      has_bearing=bool(has_bearing))

    return Msg(LANDMARK_TYPE, t, build)


# --- writing ---------------------------------------------------------------------------------

def bag_path(directory: Path, name: str, fmt: str) -> Path:
    """Where ``write_bag`` should write a bag called ``name`` in ``directory``."""
    return Path(directory) / (f"{name}.bag" if fmt == "ros1" else name)


def storage_file(path: Path, fmt: str) -> Path:
    """The file holding the messages: the .bag itself, or the .db3/.mcap inside a ROS2 bag."""
    path = Path(path)
    if fmt == "ros1":
        return path
    return path / f"{path.name}.{'db3' if fmt == 'sqlite3' else 'mcap'}"


def write_bag(path: str | Path, fmt: str, records: Iterable[tuple], *,
              compression: str = "none", chunk_bytes: int | None = None) -> Path:
    """Write ``(topic, Msg)`` / ``(topic, Msg, record_time_s)`` records into a bag at ``path``.

    Records are written in the order given (that is the bag's record order); the record time
    defaults to the message's header stamp. ROS1 only: ``compression`` of the chunks ('none',
    'bz2' or 'lz4') and ``chunk_bytes``, the uncompressed size past which a chunk is written
    (rosbags' default 1 MiB). Returns ``path``."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    if fmt not in FORMATS:
        raise ValueError(f"unknown bag format {fmt!r}; expected one of {FORMATS}")
    path = Path(path)
    store = typestore(fmt)
    if fmt == "ros1":
        writer = Writer1(path)
        if compression != "none":
            writer.set_compression(Writer1.CompressionFormat[compression.upper()])
        if chunk_bytes is not None:
            writer.chunk_threshold = chunk_bytes
        serialize = store.serialize_ros1
    else:
        plugin = StoragePlugin.SQLITE3 if fmt == "sqlite3" else StoragePlugin.MCAP
        writer = Writer2(path, version=9, storage_plugin=plugin)
        serialize = store.serialize_cdr
    conns: dict[str, object] = {}
    types: dict[str, str] = {}
    with writer:
        for rec in records:
            topic, msg = rec[0], rec[1]
            rt = rec[2] if len(rec) > 2 else msg.stamp
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msg.msgtype, typestore=store)
                types[topic] = msg.msgtype
            elif types[topic] != msg.msgtype:
                raise ValueError(f"{topic}: mixed message types {types[topic]}, {msg.msgtype}")
            writer.write(conns[topic], round(rt * 1e9), serialize(msg.build(store), msg.msgtype))
    return path


def bursts_bag(path: str | Path, datum: tuple[float, float, float]) -> Path:
    """A ROS1 bag of 80 s straight east at 1 m/s (/odom, /imu at 10 Hz, /fix at 2.5 Hz about
    ``datum``) whose fixes sit 40 m north for 2 s at 20, 40 and 60 s: three bursts."""
    from ddfuse.estimation import geodesy

    recs = []
    for i in range(800):
        t = 1700000000.0 + 0.1 * i
        recs.append(("/odom", odometry(t, 1.0, 0.0)))
        recs.append(("/imu", imu(t, wcov=diag(1e-4, 1e-4, 1e-4))))
        if i % 4 == 0:
            dn = 40.0 if (i // 10) in (20, 21, 40, 41, 60, 61) else 0.0
            lat, lon, _ = geodesy.enu_to_geodetic(0.1 * i, dn, 0.0, *datum)
            recs.append(("/fix", navsatfix(t, lat, lon, datum[2])))
    return write_bag(path, "ros1", recs)
