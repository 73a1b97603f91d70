"""Live ROS messages (rosbags, rospy or rclpy objects) become the measurements a bag gives."""

from __future__ import annotations

import math
import sys
from dataclasses import fields, replace
from pathlib import Path
from types import ModuleType, SimpleNamespace

import numpy as np
import pytest
from ddfuse.estimation.bags import open_reader, read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.live import LiveConverter, message_type
from ddfuse.estimation.measurements import GpsFix, WheelOdometry
from ddfuse.evaluation.online import OnlineSession
from readme import python_block

ROOT = Path(__file__).resolve().parents[1]
BAG, CFG = ROOT / "data" / "sample_husky.bag", ROOT / "data" / "sample_husky.yaml"


def _same(a, b) -> bool:
    for f in fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, (float, np.ndarray, tuple)):
            if not np.allclose(x, y, rtol=0, atol=1e-12, equal_nan=True):
                return False
        elif x != y:
            return False
    return True


def _shared_topic(cfg):
    """``cfg`` with a second sensor on the IMU's topic: its yaw rate again, under another name."""
    imu = cfg.of_kind("imu")[0]
    return replace(cfg, sensors=[*cfg.sensors, replace(imu, name="imu_b", use=("yaw_rate",))])


@pytest.fixture(scope="module", params=["sample", "shared topic"])
def live_and_bag(request):
    cfg = replace(load_config(CFG), initial_pose=None)  # sample_husky.yaml: ground_truth
    if request.param == "shared topic":
        cfg = _shared_topic(cfg)
    conv = LiveConverter(cfg)
    return cfg, conv, _converted(conv), read_stream(BAG, cfg)


def _converted(conv: LiveConverter) -> list:
    """The sample bag's messages through ``conv``, in stamp order as a robot's callbacks
    deliver them."""
    reader = open_reader(BAG)
    conns = [c for c in reader.connections if c.topic in conv.topics]
    live = []
    for c, rec_ns, raw in reader.messages(connections=conns):
        # received at the record time: the wall clock of this fast replay is not the stamps'
        live += conv.convert(c.topic, reader.deserialize(raw, c.msgtype),
                             received=rec_ns * 1e-9)
    live.sort(key=lambda m: m.t)
    return live


def test_every_message_converts_as_the_bag_reader_converts_it(live_and_bag):
    """Also with two sensors on one topic: the converter kept only the last one's."""
    cfg, conv, live, stream = live_and_bag
    assert conv.topics == ["/odom", "/imu/data", "/fix"]
    assert len(live) == len(stream.measurements) > 10000 and not conv.rejected
    sensors = {m.sensor for m in live}
    assert sensors == {s.name for s in cfg.sensors} == {m.sensor for m in stream.measurements}
    by_key: dict = {}
    for m in stream.measurements:
        by_key.setdefault((type(m), m.sensor, m.t), []).append(m)
    for m in live:
        assert any(_same(m, r) for r in by_key[(type(m), m.sensor, m.t)]), m
    # the datum is the first fix's, as the bag's first_fix
    assert conv.datum == pytest.approx(stream.datum)


def test_a_live_session_estimates_what_a_bag_run_does(live_and_bag):
    cfg, conv, live, stream = live_and_bag
    t_end = stream.t0 + 30.0
    g = stream.ground_truth[0]  # live, 'ground_truth' means nothing: the pose as [x, y, yaw]
    cfg = replace(cfg, initial_pose=(g.x, g.y, g.yaw))
    session = OnlineSession.from_config(cfg, ["ekf", "smoother"], stream=conv.stream())
    replayed = OnlineSession.from_config(cfg, ["ekf", "smoother"], stream=conv.stream())
    for m in live:
        if m.t <= t_end:
            session.push(m)
    for m in stream.measurements:
        if m.t <= t_end:
            replayed.push(m)
    for name in ("ekf", "smoother"):
        a, b = session.estimate(name), replayed.estimate(name)
        assert a.t == b.t and np.allclose(a.pose, b.pose, atol=1e-9), name


def _rospy_odometry(t: float, v: float, w: float) -> SimpleNamespace:
    """A rospy-style nav_msgs/Odometry: ``_type`` and a Time with secs/nsecs."""
    stamp = SimpleNamespace(secs=int(t), nsecs=round((t - int(t)) * 1e9))
    xyz = lambda x=0.0, y=0.0, z=0.0: SimpleNamespace(x=x, y=y, z=z)  # noqa: E731
    cov = [0.0] * 36
    cov[0], cov[35] = 0.01, 0.04
    return SimpleNamespace(
        _type="nav_msgs/Odometry", header=SimpleNamespace(stamp=stamp),
        pose=SimpleNamespace(pose=SimpleNamespace(position=xyz(),
                                                  orientation=SimpleNamespace(x=0, y=0, z=0,
                                                                              w=1))),
        twist=SimpleNamespace(twist=SimpleNamespace(linear=xyz(v), angular=xyz(z=w)),
                              covariance=cov))


def test_rospy_and_rclpy_messages(tmp_path):
    cfg = replace(load_config(CFG), initial_pose=None)
    conv = LiveConverter(cfg)
    msg = _rospy_odometry(1700000012.25, 0.8, -0.1)
    (m,) = conv.convert("/odom", msg)
    assert isinstance(m, WheelOdometry)
    assert m.t == pytest.approx(1700000012.25, abs=1e-6) and (m.v, m.yaw_rate) == (0.8, -0.1)
    # the config's noise (sample_husky.yaml states v and yaw_rate) replaces the message's
    s = cfg.sensors[0]
    assert (m.v_var, m.yaw_rate_var) == pytest.approx((s.noise["v"] ** 2, s.noise["yaw_rate"] ** 2))
    # an rclpy message: its type is its class's package/msg/Name
    mod = ModuleType("nav_msgs.msg._odometry")
    rclpy_cls = type("Odometry", (), {"__module__": mod.__name__})
    assert message_type(rclpy_cls()) == "nav_msgs/msg/Odometry"
    assert message_type(object(), "sensor_msgs/Imu") == "sensor_msgs/msg/Imu"
    with pytest.raises(ValueError, match="cannot tell the ROS type of a object"):
        message_type(object())
    assert "nav_msgs.msg._odometry" not in sys.modules


def test_bad_topics_types_and_fixes():
    with pytest.raises(ValueError, match="initial_pose: ground_truth has no meaning on a live "
                                         "robot"):
        LiveConverter(load_config(CFG))  # the EKFs would wait for a truth pose for ever
    cfg = replace(load_config(CFG), datum="first_fix", initial_pose=None)
    conv = LiveConverter(cfg)
    odo = _rospy_odometry(1700000000.0, 1.0, 0.0)
    with pytest.raises(ValueError, match=r"topic /cmd_vel is not in the config \(its topics: "
                                         r"/odom, /imu/data, /fix\)"):
        conv.convert("/cmd_vel", odo)
    with pytest.raises(ValueError, match=r"topic /fix: a nav_msgs/Odometry message, but "
                                         r"sensors.gps\[0\] needs sensor_msgs/NavSatFix"):
        conv.convert("/fix", odo)
    stamp = SimpleNamespace(sec=1700000001, nanosec=0)

    def fix(lat, lon, status=0):
        return SimpleNamespace(__msgtype__="sensor_msgs/msg/NavSatFix",
                               header=SimpleNamespace(stamp=stamp),
                               status=SimpleNamespace(status=status), latitude=lat,
                               longitude=lon, altitude=math.nan,
                               position_covariance=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 4.0],
                               position_covariance_type=1)

    assert conv.convert("/fix", fix(47.0, 8.0, status=-1)) == []
    assert conv.rejected[("/fix", "status NO_FIX")] == 1
    (f0,) = conv.convert("/fix", fix(47.0, 8.0))
    (f1,) = conv.convert("/fix", fix(47.0 + 1e-5, 8.0))  # ~1.11 m north
    assert isinstance(f0, GpsFix) and np.allclose(f0.enu[:2], 0.0)
    assert f1.enu[1] == pytest.approx(1.112, abs=0.01) and abs(f1.enu[0]) < 1e-6
    # a message that cannot be read as its stated type is counted as the bag reader counts it
    # (it was a bare AttributeError out of the subscriber's callback)
    assert conv.convert("/odom", fix(47.0, 8.0), msgtype="nav_msgs/Odometry") == []
    ((why, n),) = [(r, n) for (tp, r), n in conv.rejected.items() if tp == "/odom"]
    assert n == 1 and why.startswith("cannot decode message: AttributeError")


def _readme_live_block() -> str:
    return python_block(r"On a live robot, `ddfuse.estimation.live.LiveConverter`",
                        "LiveConverter(cfg)")


def test_the_readmes_live_example_handles_no_estimate_yet(monkeypatch):
    """The example read `.t, .pose` off session.estimate(...), which is None before any data
    and, for the smoother, until it has a heading: copied code crashed with AttributeError."""
    import ddfuse.estimation.config
    import ddfuse.estimation.live


    cfg = replace(load_config(CFG), initial_pose=None)
    monkeypatch.setattr(ddfuse.estimation.config, "load_config", lambda path: cfg)
    clock = [0.0]  # received: the record time, as a robot's wall clock would give it
    monkeypatch.setattr(ddfuse.estimation.live, "time", SimpleNamespace(time=lambda: clock[0]))
    ns: dict = {}
    exec(compile(_readme_live_block(), "README.md", "exec"), ns)  # noqa: S102
    pose_now = ns["pose_now"]
    assert pose_now() is None  # before any data
    reader = open_reader(BAG)
    poses = []  # pose_now() every 200 messages over the first 30 s
    try:
        conns = [c for c in reader.connections if c.topic in ns["conv"].topics]
        for k, (c, rec_ns, raw) in enumerate(reader.messages(connections=conns)):
            clock[0] = rec_ns * 1e-9
            if clock[0] - 1700000000.0 > 30.0:
                break
            ns["callback"](reader.deserialize(raw, c.msgtype), c.topic)
            if k % 200 == 0:
                poses.append(pose_now())
    finally:
        reader.close()
    assert poses[0] is None  # the smoother has no heading yet: no crash
    assert len(poses[-1]) == 3 and np.all(np.isfinite(poses[-1]))


def test_ekf_igvc_keeps_the_converters_datum_when_the_first_fix_is_dropped():
    """With ``datum: first_fix`` the converter's datum is the first fix it converts. A session
    that drops that fix (late, beyond the reorder window) handed ekf_igvc, built before any fix
    with no datum, the next fix as its own datum: its whole track was shifted by the distance
    between the two fixes, against every other estimator's frame."""
    cfg = replace(load_config(CFG), initial_pose=None, datum="first_fix")
    conv = LiveConverter(cfg)
    live = _converted(conv)
    first = next(i for i, m in enumerate(live) if isinstance(m, GpsFix))
    nxt = next(m for m in live[first + 1:] if isinstance(m, GpsFix))
    assert np.hypot(*nxt.enu[:2]) > 0.2  # the two datums are apart: the test can fail
    fed = [m for i, m in enumerate(live) if i != first and m.t <= live[0].t + 60.0]
    live_session = OnlineSession.from_config(cfg, ["ekf_igvc"], stream=replace(
        conv.stream(), datum=None))  # as built before any fix arrived
    known = OnlineSession.from_config(cfg, ["ekf_igvc"], stream=conv.stream())
    for m in fed:
        live_session.push(m)
        known.push(m)
    a, b = live_session.estimate("ekf_igvc"), known.estimate("ekf_igvc")
    assert a.t == b.t and np.allclose(a.pose, b.pose, atol=1e-6)


def test_an_exact_duplicate_message_is_dropped_counted_and_warned_about(caplog):
    """The same message delivered twice (two bridges, a republisher) is fused once: dropped,
    counted under its topic and listed in the warnings; the same stamp with other content is
    not a duplicate."""
    from types import SimpleNamespace as NS

    from ddfuse.estimation.config import parse_config_text
    from ddfuse.estimation.duplicates import DUPLICATE
    from ddfuse.estimation.live import LiveConverter

    cfg = parse_config_text("""
sensors:
  odometry:
  - topic: /odom
    use: [v, yaw_rate]
    noise: {v: 0.1, yaw_rate: 0.05}
""", "dup.yaml")

    def odom(v, sec):
        vec = NS
        return NS(__msgtype__="nav_msgs/msg/Odometry",
                  header=NS(stamp=NS(sec=sec, nanosec=0)),
                  pose=NS(pose=NS(position=vec(x=0.0, y=0.0, z=0.0),
                                  orientation=vec(x=0.0, y=0.0, z=0.0, w=1.0)),
                          covariance=[0.0] * 36),
                  twist=NS(twist=NS(linear=vec(x=v, y=0.0, z=0.0),
                                    angular=vec(x=0.0, y=0.0, z=0.1)),
                           covariance=[0.0] * 36))

    conv = LiveConverter(cfg)
    t0 = 1_700_000_000
    got = [conv.convert("/odom", odom(v, t0 + k), received=t0 + k)
           for k, v in [(0, 1.0), (1, 1.0), (1, 1.0), (1, 1.1), (2, 1.0), (2, 1.0)]]
    assert [len(g) for g in got] == [1, 1, 0, 1, 1, 0]
    assert conv.rejected[("/odom", DUPLICATE)] == 2
    assert conv.warnings == ["live input: topic /odom: 2 of 6 messages are exact duplicates of "
                             "one read just before (same header stamp and content); dropped, "
                             "each fused once"]
    assert sum("exact duplicate" in r.getMessage() for r in caplog.records) == 1


def test_a_stated_datum_far_from_the_first_fix_is_logged_and_listed(caplog):
    """The live converter says, when the first fix comes, what the bag reader says at the end:
    a stated frame.datum hundreds of km from the robot (geodesy.far_datum); near, nothing."""
    near = LiveConverter(replace(load_config(CFG), initial_pose=None))
    _converted(near)
    assert not any("frame.datum" in w for w in near.warnings)
    lat, _, alt = load_config(CFG).datum
    far = LiveConverter(replace(load_config(CFG), initial_pose=None, datum=(lat, 0.0001, alt)))
    with caplog.at_level("WARNING", logger="ddfuse.estimation.live"):
        _converted(far)
    (w,) = [w for w in far.warnings if "frame.datum" in w]
    assert w.startswith("topic /fix: the first fix (") and " km from frame.datum (" in w
    assert [r.getMessage() for r in caplog.records if "frame.datum" in r.getMessage()] == [w]
