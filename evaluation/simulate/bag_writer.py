"""A simulated run as a ROS1 bag, or a ROS 2 bag directory (sqlite3 or MCAP storage).

Messages are the standard ROS types (nav_msgs/Odometry, sensor_msgs/JointState, Imu,
MagneticField, NavSatFix) plus ``ddfuse_msgs/msg/LandmarkObservation``, stamped
``Scenario.t0_ns`` + the sample time, written in stamp order with the record time equal to
the header stamp. The covariances written are the true noise variances (axes a planar robot
does not have get 1e6, as in the MRCLAM bag). Byte-identical output for a given result.
"""

from __future__ import annotations

import heapq
import math
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from ddfuse.evaluation.atomic_files import partial_path
from ddfuse.evaluation.simulate.sidecars import sidecar_paths, write_sidecars
from ddfuse.evaluation.simulate.simulator import SimResult

LANDMARK_MSGTYPE = "ddfuse_msgs/msg/LandmarkObservation"
LANDMARK_MSGDEF = """std_msgs/Header header
string landmark_id
float64 range
float64 bearing
float64 range_variance
float64 bearing_variance
bool has_bearing
"""
UNUSED_VAR = 1e6  # variance written for axes a planar robot does not measure
FORMATS = ("ros1", "ros2", "mcap")
# the file extension of each format's bag (ros1) or of the storage file in its directory (ROS 2)
SUFFIXES = {"ros1": ".bag", "ros2": ".db3", "mcap": ".mcap"}


def make_typestore(fmt: str):
    """rosbags typestore for the format (Noetic for ROS1, Humble for ROS2/MCAP) with the
    LandmarkObservation type registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg(LANDMARK_MSGDEF, LANDMARK_MSGTYPE))
    return ts


class _Msgs:
    """Builds messages of one typestore; hides the ROS1 Header's seq field."""

    def __init__(self, ts, fmt: str, t0_ns: int):
        self.ts = ts
        self.T = ts.types
        self.t0_ns = t0_ns
        self.ros1 = fmt == "ros1"
        self.serialize = ts.serialize_ros1 if self.ros1 else ts.serialize_cdr

    def ns(self, t: float) -> int:
        return self.t0_ns + int(round(t * 1e9))

    def header(self, ns: int, frame: str, seq: int):
        stamp = self.T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        H = self.T["std_msgs/msg/Header"]
        if self.ros1:
            return H(seq=seq, stamp=stamp, frame_id=frame)
        return H(stamp=stamp, frame_id=frame)

    def vec(self, x: float, y: float, z: float):
        return self.T["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))

    def quat(self, x: float, y: float, z: float, w: float):
        return self.T["geometry_msgs/msg/Quaternion"](x=float(x), y=float(y), z=float(z),
                                                     w=float(w))

    def odometry(self, ns, seq, frame, child, px, py, yaw, v, w, pose_cov, twist_cov):
        T = self.T
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(px), y=float(py), z=0.0),
            orientation=self.quat(0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)))
        twist = T["geometry_msgs/msg/Twist"](linear=self.vec(v, 0.0, 0.0),
                                            angular=self.vec(0.0, 0.0, w))
        return T["nav_msgs/msg/Odometry"](
            header=self.header(ns, frame, seq), child_frame_id=child,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=pose_cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=twist_cov))

    def navsatfix(self, ns, seq, frame, lat, lon, alt, cov9, cov_type):
        T = self.T
        st = T["sensor_msgs/msg/NavSatStatus"]
        return T["sensor_msgs/msg/NavSatFix"](
            header=self.header(ns, frame, seq),
            status=st(status=st.STATUS_FIX, service=st.SERVICE_GPS),
            latitude=float(lat), longitude=float(lon), altitude=float(alt),
            position_covariance=cov9, position_covariance_type=cov_type)


def _diag(values: list[float], n: int) -> np.ndarray:
    c = np.zeros((n, n))
    c[np.diag_indices(n)] = values
    return c.ravel()


def _quat_rpy(roll, pitch, yaw) -> tuple[float, float, float, float]:
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


def _topic_messages(res: SimResult, mk: _Msgs) -> list[tuple[str, str, Iterator]]:
    """(topic, msgtype, iterator of (stamp ns, message)) for every topic of the result."""
    sc = res.scenario
    T = mk.T
    noise = res.noise()
    out: list[tuple[str, str, Iterator]] = []
    enc = res.encoders

    if sc.encoders.odometry_topic:
        n = noise["odometry"]
        pose_cov = _diag([UNUSED_VAR] * 6, 6)
        twist_cov = _diag([n["v"] ** 2, UNUSED_VAR, UNUSED_VAR, UNUSED_VAR, UNUSED_VAR,
                           n["yaw_rate"] ** 2], 6)

        def odom():
            for k in range(len(enc.t)):
                yield mk.ns(enc.t[k]), mk.odometry(
                    mk.ns(enc.t[k]), k, "odom", "base_link", enc.x[k], enc.y[k], enc.yaw[k],
                    enc.v[k], enc.yaw_rate[k], pose_cov, twist_cov)

        out.append((sc.encoders.odometry_topic, "nav_msgs/msg/Odometry", odom()))

    if sc.encoders.joint_topic:
        names = list(sc.encoders.joints)

        def joints():
            J = T["sensor_msgs/msg/JointState"]
            for k in range(len(enc.t)):
                ns = mk.ns(enc.t[k])
                yield ns, J(header=mk.header(ns, "base_link", k), name=names,
                            position=np.array([enc.counts_left[k], enc.counts_right[k]],
                                              dtype=float) * enc.tick,
                            velocity=np.array([enc.left[k], enc.right[k]]),
                            effort=np.zeros(0))

        out.append((sc.encoders.joint_topic, "sensor_msgs/msg/JointState", joints()))

    if res.imu is not None:
        imu, spec = res.imu, sc.imu
        ocov = _diag([spec.tilt_std**2, spec.tilt_std**2, spec.heading_std**2], 3)
        wcov = _diag([spec.gyro_std**2] * 3, 3)
        acov = _diag([spec.accel_std**2] * 3, 3)

        def imus():
            Imu = T["sensor_msgs/msg/Imu"]
            for k in range(len(imu.t)):
                ns = mk.ns(imu.t[k])
                yield ns, Imu(
                    header=mk.header(ns, "imu_link", k),
                    orientation=mk.quat(*_quat_rpy(imu.roll[k], imu.pitch[k], imu.yaw[k])),
                    orientation_covariance=ocov,
                    angular_velocity=mk.vec(imu.gyro_xy[k, 0], imu.gyro_xy[k, 1],
                                            imu.yaw_rate[k]),
                    angular_velocity_covariance=wcov,
                    linear_acceleration=mk.vec(*imu.accel[k]),
                    linear_acceleration_covariance=acov)

        out.append((spec.topic, "sensor_msgs/msg/Imu", imus()))

    if res.magnetometer is not None:
        mag, spec = res.magnetometer, sc.magnetometer
        mcov = _diag([spec.noise_std**2] * 3, 3)

        def fields():
            M = T["sensor_msgs/msg/MagneticField"]
            for k in range(len(mag.t)):
                ns = mk.ns(mag.t[k])
                yield ns, M(header=mk.header(ns, "imu_link", k),
                            magnetic_field=mk.vec(*mag.field[k]),
                            magnetic_field_covariance=mcov)

        out.append((spec.topic, "sensor_msgs/msg/MagneticField", fields()))

    if res.gps is not None:
        gps, spec = res.gps, sc.gps
        cov = _diag([spec.horizontal_std**2, spec.horizontal_std**2, spec.vertical_std**2], 3)
        diag_known = T["sensor_msgs/msg/NavSatFix"].COVARIANCE_TYPE_DIAGONAL_KNOWN

        def fixes():
            for k in range(len(gps.t)):
                ns = mk.ns(gps.t[k])
                yield ns, mk.navsatfix(ns, k, "gps", gps.lat[k], gps.lon[k], gps.alt[k], cov,
                                       diag_known)

        out.append((spec.topic, "sensor_msgs/msg/NavSatFix", fixes()))

    if res.landmarks is not None:
        lm, spec = res.landmarks, sc.landmarks
        rv, bv = spec.range_std**2, spec.bearing_std**2

        def sightings():
            L = T[LANDMARK_MSGTYPE]
            for k in range(len(lm.t)):
                ns = mk.ns(lm.t[k])
                yield ns, L(header=mk.header(ns, "base_link", k),
                            landmark_id=lm.ids[lm.index[k]], range=float(lm.range[k]),
                            bearing=float(lm.bearing[k]), range_variance=rv,
                            bearing_variance=bv, has_bearing=True)

        out.append((spec.topic, LANDMARK_MSGTYPE, sightings()))

    gt = res.ground_truth
    zero36 = np.zeros(36)

    def truth():
        for k in range(len(gt.t)):
            ns = mk.ns(gt.t[k])
            yield ns, mk.odometry(ns, k, "map", "base_link", gt.x[k], gt.y[k], gt.yaw[k],
                                  gt.v[k], gt.w[k], zero36, zero36)

    out.append((sc.truth_topic, "nav_msgs/msg/Odometry", truth()))

    if len(gt.fix_t):
        known = T["sensor_msgs/msg/NavSatFix"].COVARIANCE_TYPE_KNOWN
        zero9 = np.zeros(9)

        def truth_fixes():
            for k in range(len(gt.fix_t)):
                ns = mk.ns(gt.fix_t[k])
                yield ns, mk.navsatfix(ns, k, "base_link", gt.fix_lat[k], gt.fix_lon[k],
                                       gt.fix_alt[k], zero9, known)

        out.append((sc.truth_fix_topic, "sensor_msgs/msg/NavSatFix", truth_fixes()))
    return out


def storage_file(path: str | Path, fmt: str = "ros1") -> Path:
    """The file holding the messages of the bag ``write_bag(res, path, fmt)`` writes: the
    ros1 bag itself; for ros2 and mcap, the file in the bag directory ``path``, named after it
    without the extension the file carries: ``h.mcap`` -> ``h.mcap/h.mcap``, ``run`` ->
    ``run/run.mcap``, ``x.db3`` -> ``x.db3/x.db3``."""
    p = Path(path)
    if fmt == "ros1":
        return p
    suffix = SUFFIXES[fmt]
    name = p.name[:-len(suffix)] if p.name.endswith(suffix) and p.name != suffix else p.name
    return p / (name + suffix)


def check_bag_path(path: str | Path, fmt: str) -> Path:
    """The bag path, after checking the format name, that the path's extension (if it has one
    of .bag, .db3, .mcap) is the format's (another would name a bag that is read as that
    format: an mcap directory called x.bag is taken for a ROS 1 bag), and that nothing would
    be overwritten."""
    p = Path(path)
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    other = {v: k for k, v in SUFFIXES.items()}.get(p.suffix, fmt)
    if other != fmt:
        raise ValueError(f"{p}: a name ending in {p.suffix} says {other} (and is read as "
                         f"one); a {fmt} bag's name ends in {SUFFIXES[fmt]} or has no "
                         "extension")
    if p.exists():
        raise FileExistsError(f"{p} exists; remove it first (bags are never overwritten)")
    # the config and map go beside the bag: another bag of the same stem (h.bag and h.mcap)
    # has its own there, and a bag left beside another run's config would be read with it
    for side in sidecar_paths(p):
        if side.exists():
            raise FileExistsError(f"{side} exists (the config or landmark map of another "
                                  f"bag named like {p.name}); remove it or choose another name")
    return p


def _tagged(i: int, it: Iterator) -> Iterator[tuple[int, int, object]]:
    """(stamp ns, topic index, message): a function, so each generator keeps its own index."""
    for ns, msg in it:
        yield ns, i, msg


def write_bag(res: SimResult, path: str | Path, fmt: str = "ros1", compress: bool = True
              ) -> tuple[Path, Path, Path | None]:
    """Write the bag (ROS1 file, or ROS2 directory with sqlite3 or MCAP storage: the file in it
    is ``storage_file(path, fmt)``), then the config YAML and landmark map YAML next to it
    (``sidecar_paths``). Messages are written in stamp order with the record time equal to the
    header stamp. ``compress``: LZ4 chunks for ROS1 (no effect on ROS2).

    Returns (bag path, config path, landmark map path or None)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    p = check_bag_path(path, fmt)
    ts = make_typestore(fmt)
    mk = _Msgs(ts, fmt, res.scenario.t0_ns)
    topics = _topic_messages(res, mk)
    if fmt == "ros1":
        # written beside ``p`` and renamed to it: complete, or not at all
        made = partial_path(p)
        try:
            writer = Writer1(made)
            if compress:
                writer.set_compression(Writer1.CompressionFormat.LZ4)
            _write_messages(writer, topics, ts, mk)
            os.replace(made, p)
        except BaseException:
            made.unlink(missing_ok=True)
            raise
    else:
        # rosbags names the storage file after the directory it makes (<dir>/<dir name>.mcap):
        # the bag is made as a directory named like the file's stem in a temporary directory
        # beside ``p``, then renamed to ``p`` (complete, or not at all).
        plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
        p.parent.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{p.name}.", dir=p.parent))
        try:
            made = stage / storage_file(p, fmt).stem
            _write_messages(Writer2(made, version=9, storage_plugin=plugin), topics, ts, mk)
            if p.exists():  # made meanwhile by someone else
                raise FileExistsError(f"{p} exists; remove it first (bags are never "
                                      "overwritten)")
            os.rename(made, p)
        finally:
            shutil.rmtree(stage, ignore_errors=True)
    cfg_path, map_path = write_sidecars(res, p, fmt)
    return p, cfg_path, map_path


def _write_messages(writer, topics, ts, mk: _Msgs) -> None:
    """Every message of ``topics`` (``_topic_messages``) into the opened-on-entry ``writer``."""
    with writer:
        conns = [writer.add_connection(topic, msgtype, typestore=ts)
                 for topic, msgtype, _ in topics]
        # Merge the per-topic streams by stamp; ties keep topic order, so output is reproducible.
        merged = heapq.merge(*[_tagged(i, it) for i, (_, _, it) in enumerate(topics)],
                             key=lambda item: (item[0], item[1]))
        for ns, i, msg in merged:
            writer.write(conns[i], ns, mk.serialize(msg, topics[i][1]))
