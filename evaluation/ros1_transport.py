"""ROS 1 transport of ``ddfuse node``: rospy subscribers into ``evaluation.node.NodeCore``, its
output onto rospy publishers. The only module that imports rospy (a ROS 2 transport would be
one more such module over the same core).

rospy comes from the system (Debian's python3-rospy, or a ROS distribution under /opt/ros): it
is pure Python, and the system's folders are appended to ``sys.path`` on import, after the
virtual environment's own, so that numpy and the rest stay the environment's.

Each configured topic is subscribed to as ``rospy.AnyMsg`` (every queue unbounded, so no
message is lost to a slow update) and decoded with the class of the type its publisher
announces: a configured topic already advertised with a type its sensor cannot read is an
error before subscribing (``DdfuseError``, one line naming topic, config key and types); a
publisher of such a type that appears later is refused, logged once and counted in the
diagnostics. A callback never raises into rospy: a message that fails is counted
(``NodeCore.refuse``) and logged once per topic and error. rospy's callback threads only put
each message with its receive time into a queue; the main thread takes them from it in
arrival order into the core (so a long smoother update never delays a receive time, which the
stamp checks compare with the header stamp), publishes the diagnostics on time (a topic that
falls silent is seen within its timeout) and ends the node on Ctrl-C or SIGTERM, never inside
an estimator's update (``interrupts.held_signals``).

Time: ``rospy.get_time()``, the ROS clock, is each message's receive time and the clock of the
publishing rate and the diagnostics; under ``/use_sim_time`` (``rosbag play --clock``) it is
the bag's clock, which is what the stamp checks expect of a bag played faster than real time.
Messages that come before a simulated clock has published its first time (ROS time 0; the
/clock connection may be made after a topic's) are held and taken as received at that first
time.
"""

from __future__ import annotations

import logging
import os
import queue
import sys
from types import SimpleNamespace

from ddfuse.estimation.errors import DdfuseError
from ddfuse.estimation.interrupts import deliver, held_signals, interrupt_name
from ddfuse.evaluation.diagnostics import Status
from ddfuse.evaluation.node import NodeCore, Publish

__all__ = ["Ros1Node", "check_master", "import_ros1"]

log = logging.getLogger(__name__)

SYSTEM_PATHS = ("/usr/lib/python3/dist-packages", "/opt/ros/noetic/lib/python3/dist-packages")
PACKAGES = ("ros-core python3-rospy python3-rosbag python3-nav-msgs python3-sensor-msgs "
            "python3-geometry-msgs python3-diagnostic-msgs python3-tf2-msgs")
POLL_S = 0.05  # s of wall time between the main thread's looks at the clock


def import_ros1() -> SimpleNamespace:
    """rospy and the message classes the node publishes, from the environment or else the
    system's folders (module docstring); DdfuseError in one line when absent."""
    try:
        return _modules()
    except ImportError:
        pass
    for p in SYSTEM_PATHS:
        if os.path.isdir(p) and p not in sys.path:
            sys.path.append(p)
    try:
        return _modules()
    except ImportError as e:
        raise DdfuseError(f"ddfuse node needs ROS 1's rospy and message packages ({e}): "
                          f"apt-get install {PACKAGES}") from None


def _modules() -> SimpleNamespace:
    import rosgraph
    import rospy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import TransformStamped
    from nav_msgs.msg import Odometry
    from roslib.message import get_message_class
    from sensor_msgs.msg import NavSatFix, NavSatStatus
    from tf2_msgs.msg import TFMessage

    return SimpleNamespace(
        rosgraph=rosgraph, rospy=rospy, DiagnosticArray=DiagnosticArray,
        DiagnosticStatus=DiagnosticStatus, KeyValue=KeyValue, TransformStamped=TransformStamped,
        Odometry=Odometry, get_message_class=get_message_class, NavSatFix=NavSatFix,
        NavSatStatus=NavSatStatus, TFMessage=TFMessage)


def check_master(name: str = "ddfuse") -> None:
    """DdfuseError in one line when no ROS master answers at ROS_MASTER_URI (rospy would
    wait for one without a word)."""
    rosgraph = import_ros1().rosgraph
    if not rosgraph.Master(f"/{name}").is_online():
        raise DdfuseError(f"no ROS master answers at ROS_MASTER_URI="
                          f"{rosgraph.get_master_uri()}: start roscore (or set ROS_MASTER_URI)")


class Ros1Node:
    """``core`` on ROS 1 as node ``name`` (module docstring). DdfuseError when no ROS master
    answers at ROS_MASTER_URI, or a configured topic is advertised with a type its sensor
    cannot read."""

    def __init__(self, core: NodeCore, name: str = "ddfuse") -> None:
        ros = self.ros = import_ros1()
        check_master(name)
        self.core = core
        self._queue: queue.SimpleQueue = queue.SimpleQueue()  # (receive time, topic, msg)
        self._classes: dict[str, type] = {}
        self._checked: set[tuple[str, str]] = set()
        self._publishers: dict[str, object] = {}
        self._early: list[tuple] = []  # queued before the clock's first time
        # Ctrl-C and SIGTERM stay Python's (KeyboardInterrupt in the main thread: spin ends)
        ros.rospy.init_node(name, disable_signals=True)
        for topic, msgtype in ros.rospy.get_published_topics():
            if topic in core.topics:
                problem = core.type_problem(topic, msgtype)
                if problem:
                    raise DdfuseError(problem)
        self._subscribers = [ros.rospy.Subscriber(topic, ros.rospy.AnyMsg, self._callback,
                                                  callback_args=topic, queue_size=None)
                             for topic in core.topics]

    def _callback(self, msg, topic: str) -> None:
        """rospy's thread: the message with its receive time into the queue the main thread
        drains (nothing slow here, so that the receive time is the arrival's)."""
        self._queue.put((self.ros.rospy.get_time(), topic, msg))

    def _take(self, rt: float, topic: str, msg) -> None:
        """One message into the core, what is due published. Never raises (module
        docstring)."""
        try:
            msgtype = msg._connection_header["type"]
            if (topic, msgtype) not in self._checked:
                problem = self.core.type_problem(topic, msgtype)
                if problem:
                    self.core.refuse(topic, problem)
                    return
                self._checked.add((topic, msgtype))
            cls = self._classes.get(msgtype)
            if cls is None:
                cls = self._classes[msgtype] = self.ros.get_message_class(msgtype)
            decoded = cls().deserialize(msg._buff)
            self._publish(self.core.receive(topic, decoded, rt, msgtype))
        except Exception as e:
            self.core.refuse(topic, f"{type(e).__name__}: {e}")

    def spin(self) -> str:
        """Run until Ctrl-C, SIGTERM or ROS shuts the node down; then end the session and
        publish what is left. Returns what ended it."""
        rospy = self.ros.rospy
        why = "ROS shut the node down"
        try:
            while not rospy.is_shutdown():
                try:
                    item = self._queue.get(timeout=POLL_S)
                except queue.Empty:
                    item = None
                now = rospy.get_time()
                if now <= 0.0:
                    if item is not None:
                        self._early.append(item)
                    continue
                # a signal waits for the message in hand: an estimator is never cut off
                # inside its update
                with held_signals() as held:
                    for rt, topic, msg in [*self._early, *([item] if item else [])]:
                        # before the clock's first time: taken as received then
                        self._take(rt if rt > 0.0 else now, topic, msg)
                    self._early = []
                    d = self.core.diagnostics(now)
                    if d is not None:
                        self._publish([d])
                deliver(held)
        except KeyboardInterrupt as e:
            why = f"interrupted ({interrupt_name(e)})"
        for sub in self._subscribers:
            sub.unregister()
        # what had arrived before the end is taken too: it was seen
        with held_signals():
            while True:
                try:
                    rt, topic, msg = self._queue.get_nowait()
                except queue.Empty:
                    break
                self._take(rt if rt > 0.0 else rospy.get_time(), topic, msg)
        self._publish(self.core.finish())
        self._publish([self.core.diagnostics(rospy.get_time(), force=True)])
        return why

    def close(self, why: str = "ddfuse node ended") -> None:
        self.ros.rospy.signal_shutdown(why)

    # --- publishing ------------------------------------------------------------------------

    def _publish(self, items: list[Publish]) -> None:
        for p in items:
            msg = self._message(p.fields)
            pub = self._publishers.get(p.topic)
            if pub is None:
                pub = self._publishers[p.topic] = self.ros.rospy.Publisher(
                    p.topic, type(msg), queue_size=1000)
            pub.publish(msg)

    def _message(self, f):
        """The rospy message of ``f`` (a ``Publish``'s fields), field by field."""
        ros = self.ros
        if isinstance(f, tuple):  # diagnostics statuses
            m = ros.DiagnosticArray()
            m.header.stamp = ros.rospy.Time.from_sec(max(ros.rospy.get_time(), 0.0))
            m.status = [self._status(s) for s in f]
            return m
        stamp = ros.rospy.Time.from_sec(f.stamp)
        if hasattr(f, "translation"):  # a TransformOut
            t = ros.TransformStamped()
            t.header.stamp, t.header.frame_id, t.child_frame_id = stamp, f.frame_id, \
                f.child_frame_id
            tr, q = t.transform.translation, t.transform.rotation
            tr.x, tr.y, tr.z = f.translation
            q.x, q.y, q.z, q.w = f.rotation
            return ros.TFMessage(transforms=[t])
        if hasattr(f, "latitude"):  # a FixOut
            m = ros.NavSatFix()
            m.header.stamp, m.header.frame_id = stamp, f.frame_id
            m.status.status, m.status.service = (ros.NavSatStatus.STATUS_FIX,
                                                 ros.NavSatStatus.SERVICE_GPS)
            m.latitude, m.longitude, m.altitude = f.latitude, f.longitude, f.altitude
            m.position_covariance = list(f.position_covariance)
            m.position_covariance_type = f.position_covariance_type
            return m
        m = ros.Odometry()  # an OdometryOut
        m.header.stamp, m.header.frame_id, m.child_frame_id = stamp, f.frame_id, \
            f.child_frame_id
        p, q = m.pose.pose.position, m.pose.pose.orientation
        p.x, p.y, p.z = f.position
        q.x, q.y, q.z, q.w = f.orientation
        m.pose.covariance = list(f.pose_covariance)
        lin, ang = m.twist.twist.linear, m.twist.twist.angular
        lin.x, lin.y, lin.z = f.linear
        ang.x, ang.y, ang.z = f.angular
        m.twist.covariance = list(f.twist_covariance)
        return m

    def _status(self, s: Status):
        ros = self.ros
        return ros.DiagnosticStatus(level=s.level, name=s.name, message=s.message,
                                    hardware_id=s.hardware_id,
                                    values=[ros.KeyValue(key=k, value=v) for k, v in s.values])

