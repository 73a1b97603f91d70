"""The forecast (``ddfuse.estimation.forecast``) removes the gyro's bias as the estimators do.

The audit's case: the yaw rate from a gyro that reads the true rate plus 0.05 rad/s, stated in
the config as ``gyro_bias: 0.05``; driving straight, a 2 s carry turned the pose by 0.100 rad
with a stated yaw sigma of 0.0035 rad (28 sigma), because the carry took the raw reading. With
``gyro_bias: estimate`` the carry removes the estimate's own bias state."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.ekf_baseline.unicycle import UnicycleEkf
from ddfuse.estimation.config import Config, RobotConfig, SensorConfig
from ddfuse.estimation.estimator import Estimate
from ddfuse.estimation.forecast import OdometryTwist, carry
from ddfuse.estimation.measurements import GyroYawRate, Heading, WheelOdometry
from ddfuse.evaluation.online import OnlineSession

BIAS = 0.05  # rad/s, the gyro's true bias
SIG_V, SIG_GYRO, SIG_YAW = 0.02, 0.01, 0.02


def _cfg(gyro_bias) -> Config:
    """Speed from the odometry (no yaw rate), yaw rate from the gyro (and a compass, which
    makes an estimated bias observable)."""
    return Config(sensors=[
        SensorConfig(kind="odometry", topic="/odom", name="odom", use=("v",)),
        SensorConfig(kind="imu", topic="/imu", name="imu", use=("yaw", "yaw_rate"),
                     gyro_bias=gyro_bias)], robot=RobotConfig())


def _straight(t_end: float, v: float = 1.0, seed: int = 1):
    """Driving straight east (yaw 0, true yaw rate 0) at ``v``: 10 Hz odometry, 50 Hz gyro
    reading 0 + BIAS, 10 Hz compass; stamps in order."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(int(round(t_end / 0.02)) + 1):
        t = 0.02 * k
        if k % 5 == 0:
            out.append(WheelOdometry(t, v + rng.normal(0, SIG_V), None, SIG_V**2, 0.0, "odom"))
            out.append(Heading(t, rng.normal(0, SIG_YAW), SIG_YAW**2, "imu", "compass"))
        out.append(GyroYawRate(t, BIAS + rng.normal(0, SIG_GYRO), SIG_GYRO**2, "imu"))
    return out


def _exact(t: float, state=None, cov=None, names=()) -> Estimate:
    return Estimate(t, (0.0, 0.0, 0.0), np.diag([1e-6, 1e-6, 1e-6]), state, cov, names)


def _twist(cfg: Config, t_end: float) -> OdometryTwist:
    tw = OdometryTwist(cfg)
    for m in _straight(t_end):
        tw.push(m)
    return tw


def test_a_configured_constant_bias_is_removed_from_the_carry():
    """gyro_bias: 0.05: the 2 s carry of an exact pose stays straight, yaw within 3 sigma of
    0 (it was 0.100 rad, 28 sigma) and the lateral offset within 3 sigma of 0."""
    tw = _twist(_cfg(BIAS), 3.0)
    assert tw.gyro_bias == BIAS
    e = carry(_exact(1.0), tw.samples, 3.0, tw.q(), tw.scale_cov)
    sd = np.sqrt(np.diag(e.pose_cov))
    assert abs(e.pose[2]) < 3.0 * sd[2]
    assert abs(e.pose[1]) < 3.0 * sd[1]
    assert abs(e.pose[0] - 2.0) < 3.0 * sd[0] + 0.05


@pytest.mark.parametrize("name", ["bg", "bg:imu"])
def test_an_estimated_bias_is_taken_from_the_estimate(name):
    """gyro_bias: estimate: the carry removes the estimate's bias state ('bg' as the unicycle
    EKF and the smoother name it, 'bg:<imu>' as the IGVC EKF does), and that estimate's error,
    one error for the whole carry, adds T^2 var(bg) to the yaw variance (d yaw / d bg = -T)."""
    tw = _twist(_cfg("estimate"), 3.0)
    assert tw.gyro_bias == 0.0 and all(s.raw_gyro == "imu" for s in tw.samples)
    names = ("x", "y", "yaw", name)
    state = np.array([0.0, 0.0, 0.0, BIAS])
    var_b = 0.003**2
    cov = np.diag([1e-6, 1e-6, 1e-6, var_b])
    known = carry(_exact(1.0, state, np.diag([1e-6, 1e-6, 1e-6, 0.0]), names), tw.samples, 3.0,
                  tw.q(), tw.scale_cov)
    e = carry(_exact(1.0, state, cov, names), tw.samples, 3.0, tw.q(), tw.scale_cov)
    assert e.pose == known.pose
    assert abs(e.pose[2]) < 3.0 * math.sqrt(e.pose_cov[2, 2])
    assert e.pose_cov[2, 2] - known.pose_cov[2, 2] == pytest.approx(2.0**2 * var_b, rel=1e-9)


def test_without_a_bias_state_the_raw_rate_is_carried_as_documented():
    """gyro_bias: estimate, but the estimate has no bias state (a carried one, or an estimator
    that does not estimate it): the raw reading is used, bias included (module docstring)."""
    tw = _twist(_cfg("estimate"), 3.0)
    e = carry(_exact(1.0), tw.samples, 3.0, tw.q(), tw.scale_cov)
    assert e.pose[2] == pytest.approx(2.0 * BIAS, abs=0.01)


def test_the_odometry_yaw_rate_has_no_gyro_bias_removed():
    """With the yaw rate from the odometry the gyro's bias is not the twist's: nothing is
    removed (a zero-rate odometry carries straight whatever the IMU's gyro_bias)."""
    cfg = Config(sensors=[
        SensorConfig(kind="odometry", topic="/odom", name="odom", use=("v", "yaw_rate")),
        SensorConfig(kind="imu", topic="/imu", name="imu", use=("yaw_rate",), gyro_bias=BIAS)],
        robot=RobotConfig())
    tw = OdometryTwist(cfg)
    assert tw.gyro_bias == 0.0
    for k in range(31):
        tw.push(WheelOdometry(0.1 * k, 1.0, 0.0, 1e-4, 1e-4, "odom"))
    e = carry(_exact(1.0), tw.samples, 3.0, tw.q(), tw.scale_cov)
    assert e.pose[2] == 0.0


@pytest.mark.parametrize("gyro_bias", [BIAS, "estimate"])
def test_the_online_pose_now_of_a_straight_drive_stays_straight(gyro_bias):
    """End to end: the unicycle EKF in an online session with a 2 s reorder window, 40 s of
    straight driving; the pose "now" (carried 2 s from the EKF's estimate on the odometry
    and gyro since) keeps the yaw within 3 sigma of 0 with the bias configured or estimated."""
    cfg = _cfg(gyro_bias)
    session = OnlineSession({"ekf": UnicycleEkf(cfg, initial_pose=(0.0, 0.0, 0.0))},
                            reorder_window=2.0, twist=OdometryTwist(cfg))
    for m in _straight(40.0):
        session.push(m)
    own = session.estimate("ekf")
    now = session.estimate("ekf", at=40.0)
    assert 40.0 - own.t > 1.9  # carried over the window
    assert now.t == 40.0
    assert abs(now.pose[2]) < 3.0 * math.sqrt(now.pose_cov[2, 2])
    assert abs(now.pose[1]) < 3.0 * math.sqrt(now.pose_cov[1, 1])
