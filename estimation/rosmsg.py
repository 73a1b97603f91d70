"""Field extraction from ROS messages: a fast path for ROS1 raw bytes, and rosbags' objects.

The ROS1 serialisation of the fixed-layout messages ddfuse reads most (Imu, Odometry, NavSatFix,
TwistStamped, PoseStamped, MagneticField) is a header followed by packed little-endian fields, so
one ``struct.unpack_from`` replaces rosbags' generic deserialiser, too slow for the required rate
(docs/design/performance.md). Every other case (ROS2 CDR, JointState, the landmark message)
goes through ``rosbags``; tests check that both paths give identical tuples on the real bags.

Each extractor returns a plain tuple whose shape depends on the message type (see EXTRACTORS):
floats in SI units, ``stamp`` first as float seconds from the header.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

_HDR = struct.Struct("<IIII")  # seq, stamp.sec, stamp.nanosec, len(frame_id)
_LEN = struct.Struct("<I")
_ODOM = struct.Struct("<7d36d6d36d")  # pose(p3, q4), pose cov, twist(lin3, ang3), twist cov
_IMU = struct.Struct("<4d9d3d9d3d9d")
_FIX = struct.Struct("<bH3d9dB")
_TWIST = struct.Struct("<6d")
_POSE = struct.Struct("<7d")
_MAG = struct.Struct("<3d9d")  # magnetic_field, magnetic_field_covariance

ODOMETRY = "nav_msgs/msg/Odometry"
IMU = "sensor_msgs/msg/Imu"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
JOINT_STATE = "sensor_msgs/msg/JointState"
LANDMARK = "ddfuse_msgs/msg/LandmarkObservation"
MAGNETIC_FIELD = "sensor_msgs/msg/MagneticField"


def _header(raw: bytes) -> tuple[float, int]:
    _, sec, nsec, n = _HDR.unpack_from(raw, 0)
    return sec + nsec * 1e-9, 16 + n


def _odom_raw(raw: bytes) -> tuple:
    t, off = _header(raw)
    (n,) = _LEN.unpack_from(raw, off)  # child_frame_id
    v = _ODOM.unpack_from(raw, off + 4 + n)
    return (t, v[0:3], v[3:7], v[43:46], v[46:49], v[49:85])


def _imu_raw(raw: bytes) -> tuple:
    t, off = _header(raw)
    v = _IMU.unpack_from(raw, off)
    return (t, v[0:4], v[4:13], v[13:16], v[16:25], v[25:28], v[28:37])


def _fix_raw(raw: bytes) -> tuple:
    t, off = _header(raw)
    v = _FIX.unpack_from(raw, off)
    return (t, v[0], v[2], v[3], v[4], v[5:14], v[14])


def _twist_raw(raw: bytes) -> tuple:
    t, off = _header(raw)
    v = _TWIST.unpack_from(raw, off)
    return (t, v[0:3], v[3:6], None)


def _pose_raw(raw: bytes) -> tuple:
    t, off = _header(raw)
    v = _POSE.unpack_from(raw, off)
    return (t, v[0:3], v[3:7])


def _mag_raw(raw: bytes) -> tuple:
    t, off = _header(raw)
    v = _MAG.unpack_from(raw, off)
    return (t, v[0:3], v[3:12])


def _stamp(m) -> float:
    s = m.header.stamp
    sec = getattr(s, "sec", None)
    if sec is None:  # rospy's Time (a live ROS 1 message, ddfuse.estimation.live)
        return s.secs + s.nsecs * 1e-9
    return sec + s.nanosec * 1e-9


def _xyz(v) -> tuple[float, float, float]:
    return (float(v.x), float(v.y), float(v.z))


def _quat(q) -> tuple[float, float, float, float]:
    return (float(q.x), float(q.y), float(q.z), float(q.w))


def _floats(a) -> tuple[float, ...]:
    return tuple(float(x) for x in a)


def _odom_obj(m) -> tuple:
    return (_stamp(m), _xyz(m.pose.pose.position), _quat(m.pose.pose.orientation),
            _xyz(m.twist.twist.linear), _xyz(m.twist.twist.angular), _floats(m.twist.covariance))


def _imu_obj(m) -> tuple:
    return (_stamp(m), _quat(m.orientation), _floats(m.orientation_covariance),
            _xyz(m.angular_velocity), _floats(m.angular_velocity_covariance),
            _xyz(m.linear_acceleration), _floats(m.linear_acceleration_covariance))


def _fix_obj(m) -> tuple:
    return (_stamp(m), int(m.status.status), float(m.latitude), float(m.longitude),
            float(m.altitude), _floats(m.position_covariance), int(m.position_covariance_type))


def _twist_obj(m) -> tuple:
    return (_stamp(m), _xyz(m.twist.linear), _xyz(m.twist.angular), None)


def _pose_obj(m) -> tuple:
    return (_stamp(m), _xyz(m.pose.position), _quat(m.pose.orientation))


def _mag_obj(m) -> tuple:
    return (_stamp(m), _xyz(m.magnetic_field), _floats(m.magnetic_field_covariance))


def _joint_obj(m) -> tuple:
    return (_stamp(m), tuple(m.name), _floats(m.velocity))


def _landmark_obj(m) -> tuple:
    return (_stamp(m), str(m.landmark_id), float(m.range), float(m.bearing),
            float(m.range_variance), float(m.bearing_variance), bool(m.has_bearing))


# msgtype -> (ROS1 raw-bytes extractor or None, rosbags-object extractor)
EXTRACTORS: dict[str, tuple[Callable[[bytes], tuple] | None, Callable[[object], tuple]]] = {
    ODOMETRY: (_odom_raw, _odom_obj),  # (t, position, quat, lin, ang, twist_cov36)
    IMU: (_imu_raw, _imu_obj),  # (t, quat, ocov9, angvel, wcov9, accel, acov9)
    NAVSATFIX: (_fix_raw, _fix_obj),  # (t, status, lat, lon, alt, cov9, cov_type)
    TWIST_STAMPED: (_twist_raw, _twist_obj),  # (t, lin, ang, None)
    POSE_STAMPED: (_pose_raw, _pose_obj),  # (t, position, quat)
    JOINT_STATE: (None, _joint_obj),  # (t, names, velocities)
    LANDMARK: (None, _landmark_obj),  # (t, id, range, bearing, range_var, bearing_var, has_b)
    MAGNETIC_FIELD: (_mag_raw, _mag_obj),  # (t, field3 T, cov9 T^2)
}


def short_type(msgtype: str) -> str:
    """'sensor_msgs/msg/Imu' -> 'sensor_msgs/Imu' (the ROS1 spelling users know)."""
    return msgtype.replace("/msg/", "/")
