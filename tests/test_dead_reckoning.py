"""Dead reckoning (the ``dr`` estimator): exact integration of the odometry twist."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.estimation.config import parse_config
from ddfuse.estimation.dead_reckoning import DeadReckoning, odometry_source
from ddfuse.estimation.measurements import GpsFix, GyroYawRate, WheelOdometry, WheelSpeeds
from ddfuse.factors.kinematics import se2_step


def _cfg(**robot):
    return parse_config({
        "sensors": {"odometry": [{"topic": "/odom"}],
                    "wheels": [{"topic": "/js", "joints": ["l", "r"], "noise": {"speed": 0.1}}],
                    "imu": [{"topic": "/imu", "use": ["yaw_rate"]}]},
        "robot": robot or {"wheel_radius": 0.2, "track_width": 0.5},
    })


def test_constant_twist_is_integrated_exactly_and_other_sensors_ignored():
    dr = DeadReckoning(_cfg(), initial_pose=(1.0, 2.0, 3.0))
    assert dr.estimate() is None
    for k in range(51):  # 10 Hz for 5 s; the first sample only starts the clock
        t = 0.1 * k
        dr.process(WheelOdometry(t, 0.8, 0.6, 0.01, 0.01, "/odom"))
        dr.process(GyroYawRate(t, 5.0, 1e-4, "/imu"))  # not odometry: ignored
        dr.process(GpsFix(t, 0.0, 0.0, 0.0, np.eye(3), 0, "/fix", (99.0, 99.0, 0.0)))
    x, y, yaw = se2_step(1.0, 2.0, 3.0, 0.8, 0.6, 5.0)
    e = dr.estimate()
    assert e.t == pytest.approx(5.0)
    assert e.pose[:2] == pytest.approx((x, y), abs=1e-9)
    assert e.pose[2] == pytest.approx((yaw + math.pi) % (2 * math.pi) - math.pi, abs=1e-9)
    assert np.isnan(e.pose_cov).all()


def test_wheel_speeds_through_the_nominal_geometry():
    cfg = parse_config({"sensors": {"wheels": [{"topic": "/js", "joints": ["l", "r"],
                                                "noise": {"speed": 0.1}}]},
                        "robot": {"wheel_radius": 0.2, "track_width": 0.5}})
    assert odometry_source(cfg) == "/js"
    dr = DeadReckoning(cfg)
    for k in range(11):
        dr.process(WheelSpeeds(0.1 * k, 4.0, 6.0, 0.01, 0.01, "/js"))
    # v = 0.2 (4 + 6) / 2 = 1 m/s, w = 0.2 (6 - 4) / 0.5 = 0.8 rad/s over 1 s
    x, y, yaw = se2_step(0.0, 0.0, 0.0, 1.0, 0.8, 1.0)
    assert dr.estimate().pose == pytest.approx((x, y, yaw), abs=1e-12)


def test_needs_a_full_twist():
    cfg = parse_config({"sensors": {"odometry": [{"topic": "/odom", "use": ["v"]}]}})
    assert odometry_source(cfg) is None
    with pytest.raises(ValueError, match="odometry"):
        DeadReckoning(cfg)


def test_matches_the_simulators_dead_reckoning():
    """On a simulated husky drive, the stream-based dead reckoning equals
    evaluation.plot_sim.dead_reckoning (the same odometry integrated from the same start; that
    one applies the first sample over the interval before it, whose opening is given here as a
    sample of its own: the stream filter only starts its clock at the first sample)."""
    from ddfuse.evaluation.plot_sim import dead_reckoning
    from ddfuse.evaluation.simulate import simulate

    res = simulate("husky", seed=3, duration=60.0)
    enc = res.encoders
    dr = DeadReckoning(parse_config({"sensors": {"odometry": [{"topic": "/odom"}]}}),
                       initial_pose=res.scenario.trajectory.start)
    period = 1.0 / res.scenario.encoders.rate
    dr.process(WheelOdometry(float(enc.t[0]) - period, 0.0, 0.0, 0.01, 0.01, "/odom"))
    for k in range(len(enc.t)):
        dr.process(WheelOdometry(float(enc.t[k]), float(enc.v[k]), float(enc.yaw_rate[k]),
                                 0.01, 0.01, "/odom"))
    _, xs, ys, yaws = dead_reckoning(res)
    e = dr.estimate()
    assert math.hypot(e.pose[0] - xs[-1], e.pose[1] - ys[-1]) < 1e-9
    assert abs((e.pose[2] - yaws[-1] + math.pi) % (2 * math.pi) - math.pi) < 1e-9
