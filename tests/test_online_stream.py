"""The live path sees the bag reader's stream semantics: stamps checked against the receive time
(LiveConverter), measurements reordered within reorder_window and the late ones dropped
(OnlineSession), so that no estimator is handed a measurement older than one it processed."""

from __future__ import annotations

import copy
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation.bags import UNSET_STAMP, open_reader, open_stream, read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.estimator import Estimate, Estimator
from ddfuse.estimation.live import LiveConverter
from ddfuse.estimation.measurements import GpsFix, WheelOdometry
from ddfuse.estimation.runner import initial_pose, run
from ddfuse.evaluation import estimators as registry
from ddfuse.evaluation.online import OnlineSession, replay

ROOT = Path(__file__).resolve().parents[1]
BAG, CFG = ROOT / "data" / "sample_husky.bag", ROOT / "data" / "sample_husky.yaml"
T0 = 1700000000.0  # the sample bag's first stamp
# the bag reader's reasons (estimation/bag_drops.py: TopicDrops.count_late, .check_sources)
LATE = ("arrived after messages stamped up to more than reorder_window ({:g} s) later had been "
        "passed on; raise reorder_window to keep it")
STAMP = "header stamp more than 1 s off its topic's clock (time went backwards or jumped)"
# 99.99 % of a consistent 2-D position error lies within this Mahalanobis distance
# (sqrt of the chi-square 0.9999 quantile with 2 degrees of freedom, 18.42)
MAHALANOBIS_9999 = math.sqrt(18.42)


class Spy(Estimator):
    """Records the stamp of every measurement it is handed."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list = []

    def process(self, m) -> None:
        self.seen.append(m)

    def estimate(self) -> Estimate | None:
        return None


@pytest.fixture(scope="module")
def data():
    """The sample bag as a robot's callbacks get it: (topic, receive time, message), and the
    truth (t, x, y)."""
    cfg = replace(load_config(CFG), initial_pose=None)
    topics = LiveConverter(cfg).topics
    reader = open_reader(BAG)
    try:
        conns = [c for c in reader.connections if c.topic in topics]
        raw = [(c.topic, rec_ns * 1e-9, reader.deserialize(b, c.msgtype))
               for c, rec_ns, b in reader.messages(connections=conns)]
    finally:
        reader.close()
    gt = read_stream(BAG, load_config(CFG)).ground_truth
    truth = np.array([(g.t, g.x, g.y) for g in gt])
    return cfg, raw, truth


def _stamp(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def _restamped(msg, t: float):
    msg = copy.deepcopy(msg)
    sec = math.floor(t)
    msg.header.stamp.sec, msg.header.stamp.nanosec = int(sec), int(round((t - sec) * 1e9))
    return msg


def _feed(cfg, raw, edit=None, names=("ekf", "smoother"), watch=None):
    """Every message through a LiveConverter into a session of ``names`` and a Spy; ``edit``
    maps (topic, received, msg) to the same, or None to leave the message out; ``watch`` is
    called after each message with (topic, msg, session)."""
    conv = LiveConverter(cfg)
    built = OnlineSession.from_config(cfg, list(names), stream=conv.stream())
    spy = Spy()
    s = OnlineSession({**built.estimators, "spy": spy}, reorder_window=cfg.reorder_window)
    for item in raw:
        item = edit(*item) if edit is not None else item
        if item is None:
            continue
        topic, received, msg = item
        for m in conv.convert(topic, msg, received=received):
            s.push(m)
        if watch is not None:
            watch(topic, msg, s)
    s.flush()
    return conv, s, spy


def _error(e: Estimate, truth: np.ndarray, dt: float = 0.0) -> tuple[float, float]:
    """(position error m, its Mahalanobis distance under the estimate's covariance) against the
    truth sample nearest to ``e.t + dt``."""
    i = int(np.argmin(abs(truth[:, 0] - (e.t + dt))))
    d = np.asarray(e.pose[:2]) - truth[i, 1:]
    return float(np.hypot(*d)), float(math.sqrt(d @ np.linalg.solve(e.pose_cov[:2, :2], d)))


def _stamps_in_order(spy: Spy) -> bool:
    t = [m.t for m in spy.seen]
    return all(a <= b for a, b in zip(t, t[1:], strict=False))


# --- the clock steps back ----------------------------------------------------------------------

@pytest.mark.slow
def test_clock_stepping_back_30_s_mid_feed_is_retimed_not_applied(data):
    """The host clock steps back 30 s at t=60 (NTP): stamps and receive times alike. Before,
    the unicycle EKF was handed the older stamps and ended 527 km off with negative variances;
    then the session dropped 30 s of every topic as late and the track jumped over that motion.
    Now the converter sees the receive time go back in arrival order and re-times what follows
    by the step (estimation/clock_steps.py): nothing is dropped, one warning says so, and the
    estimates end where the clean feed's do."""
    cfg, raw, truth = data

    def step(topic, received, msg):
        t = _stamp(msg)
        if t - T0 <= 60.0:
            return topic, received, msg
        return topic, received - 30.0, _restamped(msg, t - 30.0)

    conv, s, spy = _feed(cfg, raw, step)
    assert _stamps_in_order(spy)  # nothing handed to any estimator out of order
    assert not conv.rejected and not s.rejected
    assert len(spy.seen) == sum(len(conv_out) for conv_out in _converted(cfg, raw))
    [w] = conv.warnings
    assert "stepped back by 30.0" in w or "stepped back by 29.9" in w
    _, clean, _ = _feed(cfg, raw)
    for n in ("ekf", "smoother"):
        e, c = s.estimate(n), clean.estimate(n)
        d = np.diag(e.pose_cov)
        assert np.all(np.isfinite(d)) and np.all(d > 0.0), (n, d)
        assert abs(e.t - c.t) < 0.05
        assert np.hypot(*(np.asarray(e.pose[:2]) - c.pose[:2])) < 0.05, n
        err, _ = _error(e, truth)
        assert err < MAHALANOBIS_9999 * math.sqrt(np.linalg.eigvalsh(e.pose_cov[:2, :2]).max())


def _converted(cfg, raw) -> list[list]:
    conv = LiveConverter(cfg)
    return [conv.convert(topic, msg, received=rt) for topic, rt, msg in raw]


def test_a_sensor_clock_stepping_back_is_caught_by_the_stamp_check(data):
    """The stamps step back 30 s at t=60, the receive clock does not (a driver's own clock):
    each later message is off its topic's offset and is dropped by the stamp check, as the
    bag reader drops it, counted per topic; the estimates stay at t=60, consistent."""
    cfg, raw, truth = data

    def step(topic, received, msg):
        t = _stamp(msg)
        return (topic, received, msg) if t - T0 <= 60.0 else \
            (topic, received, _restamped(msg, t - 30.0))

    conv, s, spy = _feed(cfg, raw, step)
    after = {}
    for topic, _, msg in raw:
        if _stamp(msg) - T0 > 60.0:
            after[topic] = after.get(topic, 0) + 1
    assert dict(conv.rejected) == {(topic, STAMP): n for topic, n in after.items()}
    assert not s.rejected and _stamps_in_order(spy)
    for n in ("ekf", "smoother"):
        e = s.estimate(n)
        assert e.t - T0 < 60.0 and np.all(np.diag(e.pose_cov) > 0.0)
        assert _error(e, truth)[1] < MAHALANOBIS_9999


# --- broken stamps -------------------------------------------------------------------------

def test_a_fix_stamped_5_s_ahead_is_dropped_and_the_next_fixes_are_used(data):
    """Before, it froze the EKFs' time for 5 s (1.19 m error against a 0.26 m sigma) and made
    the smoother drop the next 8 fixes as older than its lag."""
    cfg, raw, truth = data
    k = next(i for i, (tp, _, m) in enumerate(raw) if tp == "/fix" and _stamp(m) - T0 > 60.0)
    future = raw[k][2]
    worst = {"ekf": 0.0, "smoother": 0.0}

    def ahead(topic, received, msg):
        return (topic, received, _restamped(msg, _stamp(msg) + 5.0)) if msg is future else \
            (topic, received, msg)

    def watch(topic, msg, s):
        if topic == "/fix" and 60.0 < _stamp(msg) - T0 < 70.0:
            for n in worst:
                worst[n] = max(worst[n], _error(s.estimate(n), truth)[1])

    conv, s, spy = _feed(cfg, raw, ahead, watch=watch)
    assert dict(conv.rejected) == {("/fix", STAMP): 1}
    fixes = [m.t for m in spy.seen if isinstance(m, GpsFix)]
    n_fixes = sum(1 for tp, _, _ in raw if tp == "/fix")
    assert len(fixes) == n_fixes - 1 and _stamp(future) not in fixes
    assert not any("older than the smoother lag" in r
                   for (_, r) in s.estimators["smoother"].log.rejected)
    # in the 10 s after it, every estimate stays within its own 99.99 % bound
    assert max(worst.values()) < MAHALANOBIS_9999, worst


@pytest.mark.parametrize("which", ["mid-feed", "first of its topic"])
def test_a_zero_stamp_is_dropped(data, which):
    """A zero (unset) header stamp was taken as t=0. Mid-feed the topic's own offset catches it;
    as the first message of a topic, the offset of the topics already heard."""
    cfg, raw, _ = data
    fixes = [i for i, (tp, _, m) in enumerate(raw) if tp == "/fix"]
    k = next(i for i in fixes if _stamp(raw[i][2]) - T0 > 60.0) if which == "mid-feed" \
        else fixes[0]
    zero = raw[k][2]

    def unset(topic, received, msg):
        return (topic, received, _restamped(msg, 0.0)) if msg is zero else \
            (topic, received, msg)

    conv, s, spy = _feed(cfg, raw[:k + 200], unset, names=("ekf",))
    assert dict(conv.rejected) == {("/fix", UNSET_STAMP): 1}  # the bag reader's reason
    assert min(m.t for m in spy.seen) > T0 - 1.0 and _stamps_in_order(spy)


@pytest.mark.parametrize("topic", ["/imu/data", "/odom", "/fix"])
@pytest.mark.parametrize("stamp", [0.0, -5.0, math.nan, math.inf])
def test_a_broken_stamp_on_the_very_first_message_is_dropped(data, stamp, topic):
    """A driver's first message stamped 0 (its clock not yet set): no topic had an offset yet,
    so the live warm-up passed it, the EKF started at t=0 and broke down 1e11 m away on the
    next message, then handed out a pose 3600 km off with sigma 1 m. A stamp that is zero,
    negative or not finite is now dropped and counted like any broken stamp."""
    cfg, raw, truth = data
    raw = raw[next(i for i, (tp, _, _) in enumerate(raw) if tp == topic):]  # it comes first
    first = raw[0][2]

    def unset(topic, received, msg):
        if msg is not first:
            return topic, received, msg
        if math.isfinite(stamp):
            return topic, received, _restamped(msg, stamp)
        msg = copy.deepcopy(msg)
        msg.header.stamp.sec = stamp  # what a broken driver could hand over
        return topic, received, msg

    conv, s, spy = _feed(cfg, raw[:3000], unset, names=("ekf",))
    ((tp, why), n), = conv.rejected.items()
    # a non-finite stamp is the converters' to refuse, under their own reason
    # zero or below: the bag reader's reason (a clock not yet set)
    assert tp == topic and n == 1 and (why == UNSET_STAMP or not math.isfinite(stamp)), why
    assert min(m.t for m in spy.seen) > T0 - 1.0 and _stamps_in_order(spy)
    e = s.estimate("ekf")
    assert s.errors["ekf"] is None and e is not None
    err, _ = _error(e, truth)
    assert err < 2.0, err


def test_received_must_be_a_finite_time(data):
    cfg, raw, _ = data
    topic, _, msg = raw[0]
    with pytest.raises(ValueError, match=rf"topic {topic}: received = nan; expected the "
                                         "receive time in seconds"):
        LiveConverter(cfg).convert(topic, msg, received=math.nan)


# --- the reorder buffer --------------------------------------------------------------------

def _odo(t: float, sensor: str = "/odom") -> WheelOdometry:
    return WheelOdometry(t, 1.0, 0.0, 0.01, 0.01, sensor)


def test_a_message_later_than_the_window_is_dropped_and_counted():
    spy = Spy()
    s = OnlineSession({"spy": spy}, reorder_window=0.5)
    for i in range(11):  # 0.0 .. 1.0: those before 1.0 - 0.5 are passed on
        s.push(_odo(i / 10))
    assert [m.t for m in spy.seen] == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4])
    s.push(_odo(0.35))  # older than 0.4, already passed on: too late
    s.push(_odo(0.45))  # out of order, but within the window: reordered
    assert s.rejected == {("/odom", LATE.format(0.5)): 1} and s.late == {"/odom": 1}
    s.flush()
    assert [m.t for m in spy.seen] == pytest.approx(
        [0.0, 0.1, 0.2, 0.3, 0.4, 0.45, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0])


def test_a_zero_window_passes_straight_through_and_still_drops_older_ones():
    spy = Spy()
    s = OnlineSession({"spy": spy})  # reorder_window 0: no latency
    s.push(_odo(1.0))
    assert [m.t for m in spy.seen] == [1.0]
    s.push(_odo(2.0))
    s.push(_odo(1.5))  # older than what was passed on
    s.push(_odo(2.0))  # an equal stamp is not older
    assert [m.t for m in spy.seen] == [1.0, 2.0, 2.0]
    assert s.rejected == {("/odom", LATE.format(0.0)): 1} and s.pending == 0


def test_equal_stamps_leave_in_the_config_sensor_order():
    spy = Spy()
    s = OnlineSession({"spy": spy}, reorder_window=0.5, order={"/imu": 0, "/odom": 1})
    s.push(_odo(1.0, "/odom"))
    s.push(_odo(1.0, "/imu"))
    s.push(_odo(2.0, "/odom"))
    s.finish()
    assert [(m.t, m.sensor) for m in spy.seen] == [(1.0, "/imu"), (1.0, "/odom"),
                                                   (2.0, "/odom")]


@pytest.mark.slow
def test_replay_does_not_buffer_twice_and_ends_where_run_ends():
    """replay reads through BagStream, which reorders: its session passes straight on, and its
    final estimates are run()'s."""
    cfg = load_config(CFG)
    names = ["ekf", "smoother"]
    session = replay(BAG, cfg, names=names)
    assert session.reorder_window == 0.0 and not session.rejected
    stream = open_stream(BAG, cfg)
    pose = initial_pose(cfg.initial_pose, stream)
    result = run(stream, {n: registry.SPECS[n].build(cfg, stream, pose, cfg.smoother.lag)
                          for n in names})
    for n in names:
        e, tr = session.estimate(n), result.runs[n].trajectory
        assert e.t == tr.t[-1] and np.allclose(e.pose, tr.pose[-1], rtol=0, atol=1e-9), n
