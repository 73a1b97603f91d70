"""ROS 2 message objects (rosbags' typestore, ROS 2 Humble definitions) from the transport-free
fields of ``ddfuse.estimation.estimate_msgs``: each function only copies fields, so that any
transport serialising with rosbags (``estimates.mcap``; a CDR channel of a live view) writes
what the node publishes. ``typestore().serialize_cdr(msg, msg.__msgtype__)`` gives the bytes.

Stamps: the fields' float seconds split into ``builtin_interfaces/Time`` (``stamp_ns``).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cache

import numpy as np
from ddfuse.estimation.estimate_msgs import FixOut, OdometryOut, TransformOut

__all__ = ["navsatfix_msg", "odometry_msg", "stamp_ns", "tf_msg", "typestore"]


@cache
def typestore():
    """rosbags' ROS 2 Humble typestore (nav_msgs, sensor_msgs, tf2_msgs, geometry_msgs)."""
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_HUMBLE)


def stamp_ns(t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(sec int32, nanosec uint32, their total ns int64) of ``t`` (N,) s. Split before scaling:
    a Unix time in ns (~1.7e18) is past float64's exact integers."""
    t = np.asarray(t, dtype=float).reshape(-1)
    sec = np.floor(t)
    nsec = np.rint((t - sec) * 1e9).astype(np.int64)
    sec = sec.astype(np.int64) + nsec // 1_000_000_000
    nsec %= 1_000_000_000
    return sec.astype(np.int32), nsec.astype(np.uint32), sec * 1_000_000_000 + nsec


def _header(stamp: float, frame_id: str):
    t = typestore().types
    sec, nsec, _ = stamp_ns(stamp)
    return t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=int(sec[0]), nanosec=int(nsec[0])),
        frame_id=frame_id)


def _xyz(kind: str, v):
    return typestore().types[f"geometry_msgs/msg/{kind}"](*(float(x) for x in v))


def odometry_msg(o: OdometryOut):
    """``nav_msgs/msg/Odometry`` with ``o``'s fields."""
    t = typestore().types
    pose = t["geometry_msgs/msg/Pose"](_xyz("Point", o.position),
                                       _xyz("Quaternion", o.orientation))
    twist = t["geometry_msgs/msg/Twist"](_xyz("Vector3", o.linear), _xyz("Vector3", o.angular))
    return t["nav_msgs/msg/Odometry"](
        _header(o.stamp, o.frame_id), o.child_frame_id,
        t["geometry_msgs/msg/PoseWithCovariance"](pose, np.array(o.pose_covariance, float)),
        t["geometry_msgs/msg/TwistWithCovariance"](twist, np.array(o.twist_covariance, float)))


def navsatfix_msg(f: FixOut, status: int = 0):
    """``sensor_msgs/msg/NavSatFix`` with ``f``'s fields; ``status`` NavSatStatus.status (-1 no
    fix, 0 fix, 1 SBAS, 2 GBAS), service 0 (not recorded)."""
    t = typestore().types
    return t["sensor_msgs/msg/NavSatFix"](
        _header(f.stamp, f.frame_id), t["sensor_msgs/msg/NavSatStatus"](int(status), 0),
        float(f.latitude), float(f.longitude), float(f.altitude),
        np.array(f.position_covariance, float), int(f.position_covariance_type))


def tf_msg(transforms: Sequence[TransformOut]):
    """``tf2_msgs/msg/TFMessage`` carrying ``transforms``."""
    t = typestore().types
    return t["tf2_msgs/msg/TFMessage"]([
        t["geometry_msgs/msg/TransformStamped"](
            _header(x.stamp, x.frame_id), x.child_frame_id,
            t["geometry_msgs/msg/Transform"](_xyz("Vector3", x.translation),
                                             _xyz("Quaternion", x.rotation)))
        for x in transforms])
