"""ROS messages from a live robot to ddfuse measurements, converted as the bag reader does.

A node's subscriber callback hands each message to ``LiveConverter.convert(topic, msg)`` and
feeds what it returns to ``evaluation.online.OnlineSession.push`` (or an estimator's
``process``)::

    conv = LiveConverter(load_config("robot.yaml"))
    session = OnlineSession.from_config(conv.cfg, ["ekf", "smoother"], stream=conv.stream())

    def on_message(msg, topic="/imu/data"):          # one subscriber per configured topic
        for m in conv.convert(topic, msg):
            session.push(m)

``msg`` is the message object of rclpy (ROS 2), rospy (ROS 1) or rosbags. Its type is read from
the object (rosbags' ``__msgtype__``, rospy's ``_type``, rclpy's class) unless ``msgtype`` is
given; the header stamp from ``sec``/``nanosec`` (ROS 2, rosbags) or ``secs``/``nsecs``
(rospy). The config's topics, types, noise, mounts and datum apply exactly as to a bag (the same
converters, ``estimation.bags.CONVERTERS``): a GPS fix gets its local ENU position in the
config's datum, or in the first fix's with ``frame: {datum: first_fix}``. A message that cannot
be used (NO_FIX, non-finite fields, no covariance and no configured noise) gives no measurement
and is counted in ``rejected`` under its topic and reason, as the bag reader counts it.

Not applied here, because a live robot has no future to look at: the bag reader's reordering
by header stamp and its stamp-jump check. Feed messages in stamp order (the smoother places a
GPS fix or landmark sighting up to its lag late on the right keyframe; the EKFs do not)."""

from __future__ import annotations

from collections import Counter

from estimation import geodesy, rosmsg
from estimation.bags import ACCEPTED_TYPES, CONVERTERS, Reject, configured_topics
from estimation.config import Config, landmark_maps
from estimation.measurements import GpsFix, Stream

__all__ = ["LiveConverter", "message_type"]


def message_type(msg, given: str | None = None) -> str:
    """The ROS type of ``msg`` in rosbags' spelling ('sensor_msgs/msg/Imu'): ``given`` (either
    spelling) or read from the object; ValueError when neither says."""
    t = given or getattr(msg, "__msgtype__", None) or getattr(msg, "_type", None)
    if not t:
        cls = type(msg)
        parts = cls.__module__.split(".")
        if len(parts) >= 2 and parts[1] == "msg":  # rclpy: nav_msgs.msg._odometry.Odometry
            t = f"{parts[0]}/msg/{cls.__name__}"
    if not t:
        raise ValueError(f"cannot tell the ROS type of a {type(msg).__name__} object; pass "
                         "msgtype='package/Type'")
    pkg, _, name = t.replace("/msg/", "/").partition("/")
    return f"{pkg}/msg/{name}"


class LiveConverter:
    """Per configured topic, ROS message -> measurements (module docstring)."""

    def __init__(self, cfg: Config) -> None:
        if cfg.initial_pose == "ground_truth":
            # the EKFs would wait for a truth pose that never comes, without a word
            raise ValueError(f"{cfg.path or 'config'}: initial_pose: ground_truth has no "
                             "meaning on a live robot (no truth is read); give [x, y, yaw] or "
                             "leave it out (heading from the GPS course or a compass)")
        self.cfg = cfg
        self.datum: tuple[float, float, float] | None = (
            cfg.datum if isinstance(cfg.datum, tuple) else None)
        self.rejected: Counter = Counter()  # (topic, reason) -> messages
        self._topics = {topic: (kind, key, CONVERTERS[kind](s, key))
                        for kind, key, s, topic in configured_topics(cfg) if s is not None}

    def stream(self) -> Stream:
        """An empty Stream with what the estimators are built from: the landmark maps of the
        config's landmark sensors and the datum (the config's; with ``first_fix`` none until a
        fix arrives, and the estimators then take the first fix's, as this converter does)."""
        return Stream(measurements=[], datum=self.datum, landmarks=landmark_maps(self.cfg))

    @property
    def topics(self) -> list[str]:
        """The topics the config fuses, each to be subscribed to."""
        return list(self._topics)

    def convert(self, topic: str, msg, msgtype: str | None = None) -> list:
        """The measurements in ``msg`` received on ``topic`` (possibly none: counted in
        ``rejected``). ValueError for a topic the config does not name or a message type its
        sensor cannot read."""
        entry = self._topics.get(topic)
        if entry is None:
            raise ValueError(f"topic {topic} is not in the config (its topics: "
                             f"{', '.join(self._topics) or 'none'})")
        kind, key, convert = entry
        mt = message_type(msg, msgtype)
        if mt not in ACCEPTED_TYPES[kind]:
            need = " or ".join(rosmsg.short_type(t) for t in ACCEPTED_TYPES[kind])
            raise ValueError(f"topic {topic}: a {rosmsg.short_type(mt)} message, but {key} "
                             f"needs {need}")
        try:
            out = convert(rosmsg.EXTRACTORS[mt][1](msg))
        except Reject as e:
            self.rejected[(topic, str(e))] += 1
            return []
        for m in out:
            if type(m) is GpsFix:
                if self.datum is None:
                    self.datum = (m.lat, m.lon, m.alt)
                m.enu = geodesy.geodetic_to_enu(m.lat, m.lon, m.alt, *self.datum)
        return out
