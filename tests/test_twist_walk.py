"""``robot.twist_walk``: the twist's own process noise, stated in the config, read by the
unicycle EKF, the smoother's held twist and ekf_igvc, and separate from the robot's
acceleration limits (which stay the glitch screen's)."""

from __future__ import annotations

import pytest
from ddfuse.ekf_baseline.igvc import IgvcEkf
from ddfuse.ekf_baseline.unicycle import UnicycleEkf
from ddfuse.estimation.config import parse_config
from ddfuse.estimation.errors import ConfigError
from ddfuse.estimation.measurements import WheelOdometry
from ddfuse.estimation.smoother.held_twist import HeldTwist
from ddfuse.estimation.smoother.noise import SmootherNoise
from ddfuse.factors.preintegration import WheelGyroPreintegration

ODOM = {"odometry": [{"topic": "/odom", "use": ["v", "yaw_rate"]}]}


def _cfg(robot: dict, sensors: dict | None = None):
    return parse_config({"sensors": sensors or ODOM, "robot": robot,
                         "initial_pose": [0.0, 0.0, 0.0]})


@pytest.mark.parametrize(("twist_walk", "key"), [
    ({"speed": 0.0}, "robot.twist_walk.speed"),
    ({"yaw_rate": -0.1}, "robot.twist_walk.yaw_rate"),
    ({"yaw_rate": "fast"}, "robot.twist_walk.yaw_rate"),
    ({"accel": 0.3}, "robot.twist_walk.accel"),
    (0.3, "robot.twist_walk"),
])
def test_a_bad_twist_walk_is_refused_naming_the_key(twist_walk, key):
    with pytest.raises(ConfigError) as e:
        _cfg({"twist_walk": twist_walk})
    msg = str(e.value)
    assert key in msg and "\n" not in msg


def test_the_ekf_predicts_the_twist_with_the_stated_walk_not_the_acceleration_limits():
    # with both stated, the walk sets the densities; over a prediction of dt the variances of
    # v and w grow by speed^2 dt and yaw_rate^2 dt (ProcessNoise: Qvv = acc^2 dt)
    cfg = _cfg({"max_accel": 0.5, "max_yaw_accel": 0.4,
                "twist_walk": {"speed": 0.3, "yaw_rate": 0.2}})
    assert cfg.robot.twist_walk == {"speed": 0.3, "yaw_rate": 0.2}
    ekf = UnicycleEkf(cfg, reference=True)
    for k in range(20):  # 10 Hz odometry: with the limits alone the densities would follow it
        ekf.process(WheelOdometry(0.1 * k, 1.0, 0.1, 1e-4, 1e-4, sensor="/odom"))
    assert (ekf.noise.acc, ekf.noise.yaw_acc) == (0.3, 0.2)
    P0 = ekf.kf.P.copy()
    ekf._predict_to(ekf.t + 0.5)
    P1 = ekf.kf.P
    assert P1[3, 3] - P0[3, 3] == pytest.approx(0.3 ** 2 * 0.5, rel=1e-9)
    assert P1[4, 4] - P0[4, 4] == pytest.approx(0.2 ** 2 * 0.5, rel=1e-9)
    # one component stated: the other still follows its acceleration limit and sample period
    ekf = UnicycleEkf(_cfg({"max_accel": 0.5, "max_yaw_accel": 0.4,
                            "twist_walk": {"yaw_rate": 0.2}}), reference=True)
    for k in range(20):
        ekf.process(WheelOdometry(0.1 * k, 1.0, 0.1, 1e-4, 1e-4, sensor="/odom"))
    assert ekf.noise.yaw_acc == 0.2
    assert ekf.noise.acc == pytest.approx(0.5 * 0.1 ** 0.5, rel=1e-6)


def test_without_the_key_the_ekf_keeps_its_defaults():
    base = UnicycleEkf(_cfg({}), reference=True).noise
    assert (base.acc, base.yaw_acc) == (1.0, 1.0)


def test_the_smoother_ages_a_held_sample_with_the_stated_walk():
    # an odometry sample held 1 s past its span: as a measurement of v at the end its variance
    # is var + q * 1 s, q the walk's density squared (the limit's a_max^2 T without the key)
    def held_var(robot: dict) -> float:
        tw = HeldTwist(_cfg(robot).robot, SmootherNoise(), WheelGyroPreintegration, 0.0)
        tw.set_odometry(WheelOdometry(0.0, 1.0, 0.1, 1e-4, 1e-4, sensor="/odom"))
        tw.last_t = 0.0
        tw.advance(1.0)
        return tw.frozen().last_var_v

    assert held_var({"max_accel": 0.5, "twist_walk": {"speed": 0.3}}) == \
        pytest.approx(1e-4 + 0.3 ** 2, rel=1e-9)
    assert held_var({"max_accel": 0.5}) == pytest.approx(1e-4 + 0.5 ** 2 * 0.1, rel=1e-9)


def test_ekf_igvc_takes_the_yaw_rate_walk():
    sensors = {**ODOM, "gps": [{"topic": "/fix"}]}
    stated = IgvcEkf(_cfg({"twist_walk": {"yaw_rate": 0.2}}, sensors), reference=True)
    assert stated.noise.yaw_accel_psd == pytest.approx(0.04)
    assert IgvcEkf(_cfg({}, sensors), reference=True).noise.yaw_accel_psd == 0.1
