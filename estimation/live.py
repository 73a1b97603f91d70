"""ROS messages from a live robot to ddfuse measurements, converted as the bag reader does.

A node's subscriber callback hands each message to ``LiveConverter.convert(topic, msg)`` and
feeds what it returns to ``ddfuse.evaluation.online.OnlineSession.push`` (or an estimator's
``process``)::

    conv = LiveConverter(load_config("robot.yaml"))
    session = OnlineSession.from_config(conv.cfg, ["ekf", "smoother"], stream=conv.stream())

    def on_message(msg, topic="/imu/data"):          # one subscriber per configured topic
        for m in conv.convert(topic, msg):
            session.push(m)

``msg`` is the message object of rclpy (ROS 2), rospy (ROS 1) or rosbags. Its type is read from
the object (rosbags' ``__msgtype__``, rospy's ``_type``, rclpy's class) unless ``msgtype`` is
given; the header stamp from ``sec``/``nanosec`` (ROS 2, rosbags) or ``secs``/``nsecs``
(rospy). The config's topics, types, noise, mounts, landmark maps and datum apply exactly as to
a bag (the same converters, ``ddfuse.estimation.bags.converter``; a sighting of a landmark id not in
the maps is rejected): a GPS fix gets its local ENU position in the config's datum, or in the
first fix's with ``frame: {datum: first_fix}``. A topic that several
configured sensors read gives each one's measurements, in the config's order. A message that
cannot be used (NO_FIX, non-finite fields, no covariance and no configured noise, fields that
do not fit its type) gives no measurement and is counted in ``rejected`` under its topic and
reason, as the bag reader counts it.

Broken stamps. ``convert`` also takes the message's receive time (``received``, s on the clock
of the header stamps; default ``time.time()``; in a replay pass the record time) and applies the
bag reader's per-topic stamp check (``ddfuse.estimation.bags._StampCheck``, tolerance
max(``STAMP_TOLERANCE`` = 1 s, the config's ``reorder_window``)): a stamp that far off its
topic's usual stamp-to-receive offset, a stamp of zero or below, or a non-finite one gives no
measurement and is counted in ``rejected``. Unlike the bag reader, nothing is held back while a
topic's offset is learnt (``_StampCheck.WARMUP_S``). Reordering by stamp is ``OnlineSession``'s.

A receive clock that steps back (arrival order is write order) re-times the messages after the
step (``ddfuse.estimation.clock_steps``), logged when it happens and listed in ``warnings``.
An exact duplicate (the same message delivered twice on a topic: two bridges, a republisher;
same header stamp and content, ``ddfuse.estimation.duplicates``) gives no measurement and is
counted in ``rejected`` and listed in ``warnings``, as the bag reader drops it.

Design notes (the warm-up, clock steps): docs/design/live_input.md, docs/design/bag_faults.md"""

from __future__ import annotations

import logging
import math
import statistics
import time
from collections import Counter

from ddfuse.estimation import geodesy, rosmsg
from ddfuse.estimation.bags import (
    ACCEPTED_TYPES,
    STAMP_TOLERANCE,
    UNSET_STAMP,
    Reject,
    _StampCheck,
    configured_topics,
    converter,
    slope_cells,
)
from ddfuse.estimation.clock_steps import ClockSteps
from ddfuse.estimation.config import Config, landmark_maps
from ddfuse.estimation.duplicates import DUPLICATE, Duplicates
from ddfuse.estimation.gps_watch import GpsWatch
from ddfuse.estimation.measurements import GpsFix, Stream
from ddfuse.estimation.robot_limits import RobotLimits

__all__ = ["LiveConverter", "message_type"]

log = logging.getLogger(__name__)


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
    """Per configured topic, ROS message -> measurements (of every sensor the config reads from
    that topic, in the config's order), each topic's stamps checked against their receive
    times (module docstring). ``reorder_window`` (s, default the config's) sets
    the stamp tolerance as for the bag reader: max(``STAMP_TOLERANCE``, reorder_window). The
    config's landmark maps are loaded here (ConfigError naming the map file if one cannot be
    used, as for a bag) and kept in ``landmarks``."""

    def __init__(self, cfg: Config, *, reorder_window: float | None = None) -> None:
        if cfg.initial_pose == "ground_truth":
            # the EKFs would wait for a truth pose that never comes, without a word
            raise ValueError(f"{cfg.path or 'config'}: initial_pose: ground_truth has no "
                             "meaning on a live robot (no truth is read); give [x, y, yaw] or "
                             "leave it out (heading from the GPS course or a compass)")
        window = cfg.reorder_window if reorder_window is None else float(reorder_window)
        if not (window >= 0.0 and math.isfinite(window)):
            raise ValueError(f"reorder_window: expected seconds >= 0, got {reorder_window!r}")
        self.cfg = cfg
        self.tolerance = max(STAMP_TOLERANCE, window)
        self.datum: tuple[float, float, float] | None = (
            cfg.datum if isinstance(cfg.datum, tuple) else None)
        self.rejected: Counter = Counter()  # (topic, reason) -> messages
        # the landmark sensors' maps, merged: a sighting of an id not in them is rejected as
        # the bag reader rejects it (ddfuse.estimation.config.LANDMARK_NOT_IN_MAP)
        self.landmarks = landmark_maps(cfg)
        # topic -> (kind, key, converter) of every sensor on it, in the config's order: two
        # sensors may read one topic (an IMU's yaw rate twice, under two names), as in a bag
        self._topics: dict[str, list[tuple]] = {}
        slopes = slope_cells(cfg)  # an odometry's `slope`: its IMU's climb, shared
        for kind, key, s, topic in configured_topics(cfg):
            if s is not None:
                self._topics.setdefault(topic, []).append(
                    (kind, key, converter(kind, s, key, self.landmarks, slopes=slopes)))
        self._checks: dict[str, _StampCheck] = {}  # topic -> its stamp check
        # the receive clock stepping back, seen in arrival order (``_retime``); what it did is
        # in ``warnings``
        self._steps = ClockSteps(self.tolerance)
        self.duplicates = Duplicates(ros1=False)
        self.seen: Counter = Counter()  # topic -> messages handed to ``convert``
        self.screen = RobotLimits(cfg, self.rejected)  # what the robot cannot do: rejected
        self.watch = GpsWatch(cfg)  # GPS against the odometry: disagreements logged
        # a stated datum far from the first fix (``geodesy.far_datum``): logged when it comes
        self._datum_checked = not isinstance(cfg.datum, tuple)
        self._far_datum: str | None = None
        self._stamp_reason = (f"header stamp more than {self.tolerance:g} s off its topic's "
                              "clock (time went backwards or jumped)")  # the bag reader's text

    def stream(self) -> Stream:
        """An empty Stream with what the estimators are built from: the landmark maps of the
        config's landmark sensors and the datum (the config's; with ``first_fix`` none until a
        fix arrives: each fix carries this converter's datum in ``GpsFix.datum``, which an
        estimator built without one takes, even when the session dropped the first fix)."""
        return Stream(measurements=[], datum=self.datum, landmarks=dict(self.landmarks))

    @property
    def topics(self) -> list[str]:
        """The topics the config fuses, each to be subscribed to."""
        return list(self._topics)

    def convert(self, topic: str, msg, msgtype: str | None = None, *,
                received: float | None = None) -> list:
        """The measurements in ``msg`` received on ``topic`` at ``received`` (s, the clock of
        the header stamps; default ``time.time()``), possibly none: an unusable message or a
        broken stamp is counted in ``rejected``. ValueError for a topic the config does not
        name, a message type its sensor cannot read, or a non-finite ``received``."""
        entries = self._topics.get(topic)
        if entries is None:
            raise ValueError(f"topic {topic} is not in the config (its topics: "
                             f"{', '.join(self._topics) or 'none'})")
        mt = message_type(msg, msgtype)
        for kind, key, _ in entries:
            if mt not in ACCEPTED_TYPES[kind]:
                need = " or ".join(rosmsg.short_type(t) for t in ACCEPTED_TYPES[kind])
                raise ValueError(f"topic {topic}: a {rosmsg.short_type(mt)} message, but {key} "
                                 f"needs {need}")
        rt = time.time() if received is None else float(received)
        if not math.isfinite(rt):
            raise ValueError(f"topic {topic}: received = {received!r}; expected the receive "
                             "time in seconds on the clock of the header stamps")
        try:
            rec = rosmsg.EXTRACTORS[mt][1](msg)
        except Exception as e:  # as the bag reader counts a message it cannot decode
            self.rejected[(topic, f"cannot decode message: {type(e).__name__}: {e}")] += 1
            return []
        self.seen[topic] += 1
        if self.duplicates.record_seen_before(topic, topic, rec):
            self.rejected[(topic, DUPLICATE)] += 1
            if self.duplicates.count[topic] == 1:
                log.warning("%s: an exact duplicate of a message received just before (same "
                            "header stamp and content); dropped, each fused once", topic)
            return []
        rec, rt = self._retime(topic, rec, rt)
        out: list = []
        for _, _, convert in entries:
            try:
                out += convert(rec)
            except Reject as e:
                self.rejected[(topic, str(e))] += 1
                out += e.kept
        if not out or not self._stamp_ok(topic, out[0].t, rt):
            return []
        for m in out:
            if type(m) is GpsFix:
                if self.datum is None:
                    self.datum = (m.lat, m.lon, m.alt)
                m.enu = geodesy.geodetic_to_enu(m.lat, m.lon, m.alt, *self.datum)
                m.datum = self.datum
                if not self._datum_checked:
                    self._datum_checked = True
                    self._far_datum = geodesy.far_datum(m, self.datum, topic)
                    if self._far_datum:
                        log.warning("%s", self._far_datum)
        return [m for m in out if self._plausible(m)]

    def _plausible(self, m) -> bool:
        ok = self.screen.admit(m)
        self.watch.feed(m, ok)
        return ok

    @property
    def warnings(self) -> list[str]:
        """What the input did that a user must know, one line each: the receive clock stepped
        back (the messages after it re-timed), a stated datum far from the first fix, samples
        beyond the robot's limits (rejected), GPS disagreeing with the odometry, exact
        duplicates (dropped). The clock's, the datum's and a topic's first duplicate are also
        logged when they happen."""
        line = self._steps.warning("live input", None)
        return (([line] if line else []) + ([self._far_datum] if self._far_datum else [])
                + self.duplicates.warnings("live input", self.seen)
                + self.screen.warnings() + self.watch.warnings())

    def _retime(self, topic: str, rec: tuple, rt: float) -> tuple:
        """(extracted record, receive time s) re-timed for the receive clock's backward steps
        so far (``ClockSteps``, arrival order being write order)."""
        t = rec[0]
        if not t > 0.0:  # an unset or non-finite stamp: the stamp check rejects it as it is
            return rec, rt
        steps = len(self._steps.steps)
        t_new, rt = self._steps.retime(topic, t, rt)
        if len(self._steps.steps) > steps:
            log.warning("%s: the receive clock stepped back by %.3f s; what follows is re-timed "
                        "by that much", topic, self._steps.steps[-1][1])
        return ((t_new, *rec[1:]) if t_new != t else rec), rt

    def _stamp_ok(self, topic: str, t: float, rt: float) -> bool:
        """The stamp check of one message (stamp ``t``, received at ``rt``) on ``topic``: the
        bag reader's once its warm-up is over, the live warm-up before (module docstring)."""
        chk = self._checks.get(topic)
        if chk is None:
            chk = self._checks[topic] = _StampCheck()
            chk.first_rt = rt
        tol = self.tolerance
        if not (t > 0.0 and math.isfinite(t)):
            # an unset (zero), negative or non-finite stamp is broken whatever the topic's
            # offset: checked before the warm-up, which passes a topic's first message
            # unchecked when no clock is known yet, and kept out of the offsets it learns
            chk.bad += 1
            # the bag reader's reasons: zero or below is a clock not yet set; non-finite is
            # what the converters and the session call it
            why = UNSET_STAMP if math.isfinite(t) else "non-finite stamp"
            self.rejected[(topic, why)] += 1
            if chk.bad == 1:
                log.warning("%s: a header stamp of %r s (zero, negative or not finite: a "
                            "clock not yet set); dropped and counted", topic, t)
            return False
        chk.n += 1
        if chk.pending is None:
            dev = t - rt - chk.ref
            good = chk.ok(t, rt, tol)  # counts a bad one in chk.bad
        else:
            chk.pending.append((t, rt, None))
            offsets = [s - r for s, r, _ in chk.pending]
            if len(offsets) >= 3:
                ref = statistics.median(offsets)
            else:  # the topic's first two: against the other topics' clocks, if one is known
                refs = [_reference(c) for tp, c in self._checks.items() if tp != topic]
                refs = [r for r in refs if r is not None]
                ref = statistics.median(refs) if refs else None
            dev = 0.0 if ref is None else t - rt - ref
            good = abs(dev) <= tol
            if not good:
                chk.bad += 1
            if len(offsets) >= 3 and (len(offsets) >= _StampCheck.WARMUP
                                      or rt - chk.first_rt > _StampCheck.WARMUP_S):
                bad = chk.bad  # end_warmup counts the warm-up's outliers again: decided above
                chk.end_warmup(tol)
                chk.bad = bad
        if not good:
            self.rejected[(topic, self._stamp_reason)] += 1
            if chk.bad == 1:
                log.warning("%s: a header stamp %+.3f s off the topic's usual offset to the "
                            "receive time (tolerance %g s); dropped and counted", topic, dev,
                            tol)
        return good


def _reference(chk: _StampCheck) -> float | None:
    """A topic's usual stamp-to-receive offset, once 3 messages have given it; else None."""
    if chk.pending is None:
        return chk.ref
    if len(chk.pending) >= 3:
        return statistics.median(s - r for s, r, _ in chk.pending)
    return None
