"""An IMU's forward acceleration has gravity's share removed with its own orientation
(errata 000 #24): the specific force on a slope is not the robot's acceleration."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from ddfuse.estimation.config import ConfigError, parse_config_text
from ddfuse.estimation.frames import GRAVITY, body_x_tilt, rpy_matrix
from ddfuse.estimation.live import LiveConverter
from ddfuse.estimation.measurements import ForwardAccel, GyroYawRate
from scipy.spatial.transform import Rotation

ACCEL_STD, TILT_STD = 0.05, 0.01


def _converter(use="[yaw_rate, accel]", extra="", mount=None) -> LiveConverter:
    m = f"\n    mount: {{rpy: {list(mount)}}}" if mount is not None else ""
    text = f"""
sensors:
  odometry: [{{topic: /odom}}]
  imu:
  - topic: /imu
    use: {use}
    noise: {{yaw_rate: 0.01, accel: {ACCEL_STD}}}{m}{extra}
"""
    return LiveConverter(parse_config_text(text, "test.yaml"))


def _imu(q, f_sensor, ocov0=TILT_STD ** 2) -> SimpleNamespace:
    """A sensor_msgs/Imu at rest: orientation q (x, y, z, w, world <- sensor), specific force
    ``f_sensor`` in the sensor frame; roll/pitch variance ``ocov0`` (-1: no orientation)."""
    xyz = ("x", "y", "z")
    ocov = [ocov0, 0, 0, 0, TILT_STD ** 2, 0, 0, 0, 0.01] if ocov0 != -1 else [-1.0] + [0.0] * 8
    return SimpleNamespace(
        __msgtype__="sensor_msgs/msg/Imu",
        header=SimpleNamespace(stamp=SimpleNamespace(sec=1700000000, nanosec=0)),
        orientation=SimpleNamespace(**dict(zip(("x", "y", "z", "w"), q, strict=True))),
        orientation_covariance=ocov,
        angular_velocity=SimpleNamespace(**dict.fromkeys(xyz, 0.0)),
        angular_velocity_covariance=[0.0] * 9,
        linear_acceleration=SimpleNamespace(**dict(zip(xyz, f_sensor, strict=True))),
        linear_acceleration_covariance=[ACCEL_STD ** 2, 0, 0, 0, 1, 0, 0, 0, 1])


def _at_rest(r_world_body: Rotation, mount_rpy=(0.0, 0.0, 0.0)) -> tuple:
    """The orientation and specific force an IMU mounted at ``mount_rpy`` reads on a body
    standing still at attitude ``r_world_body``: f = R_wb^T (0, 0, g), in the sensor frame."""
    r_bs = Rotation.from_matrix(np.array(rpy_matrix(*mount_rpy)))
    r_ws = r_world_body * r_bs
    f_sensor = r_ws.inv().apply([0.0, 0.0, GRAVITY])
    return tuple(r_ws.as_quat()), tuple(f_sensor)


def _accel(conv: LiveConverter, msg) -> ForwardAccel:
    (a,) = [m for m in conv.convert("/imu", msg) if isinstance(m, ForwardAccel)]
    return a


@pytest.mark.parametrize("mount", [(0.0, 0.0, 0.0), (math.pi / 2, 0.0, 0.0),
                                   (0.3, -1.1, 2.5)])
def test_a_climb_at_rest_reads_zero_forward_acceleration(mount):
    # 5 deg nose up (ROS pitch is about +y, nose down positive), heading 40 deg, a little roll
    r_wb = Rotation.from_euler("ZYX", [0.7, -math.radians(5.0), 0.03])
    q, f = _at_rest(r_wb, mount)
    a = _accel(_converter(mount=mount), _imu(q, f))
    assert abs(a.accel) < 1e-9
    raw = _accel(_converter(mount=mount, extra="\n    accel_gravity: level"), _imu(q, f))
    # the seed's a = a reads the climb's g sin(5 deg) as an acceleration
    # (roll, applied last, does not tip the forward axis)
    assert raw.accel == pytest.approx(GRAVITY * math.sin(math.radians(5.0)),
                                      rel=1e-9)
    assert raw.var == pytest.approx(ACCEL_STD ** 2)


def test_forward_acceleration_on_a_slope_is_recovered():
    r_wb = Rotation.from_euler("ZYX", [-2.0, math.radians(8.0), -0.05])  # nose down
    q, f = _at_rest(r_wb)
    accel = 0.4  # m/s^2 along body x: the specific force gains it
    a = _accel(_converter(), _imu(q, (f[0] + accel, f[1], f[2])))
    assert a.accel == pytest.approx(accel, abs=1e-9)


def test_the_tilt_variance_is_added():
    # level, heading along world y: body x = (0, 1, 0), so only a roll error (about world x)
    # tips it: var(u_z) = ocov[0]
    q, f = _at_rest(Rotation.from_euler("Z", math.pi / 2))
    a = _accel(_converter(), _imu(q, f, ocov0=0.02 ** 2))
    assert a.var == pytest.approx(ACCEL_STD ** 2 + GRAVITY ** 2 * 0.02 ** 2, rel=1e-9)
    # and along world x only pitch counts
    q, f = _at_rest(Rotation.identity())
    a = _accel(_converter(), _imu(q, f, ocov0=0.02 ** 2))
    assert a.var == pytest.approx(ACCEL_STD ** 2 + GRAVITY ** 2 * TILT_STD ** 2, rel=1e-9)


@pytest.mark.slow
def test_the_tilt_variance_matches_sampled_orientation_errors():
    rng = np.random.default_rng(3)
    q = tuple(Rotation.from_euler("ZYX", [0.9, 0.15, -0.1]).as_quat())
    cov = np.array([[4e-4, 1e-4, 0], [1e-4, 2.5e-4, 0], [0, 0, 1e-2]])
    mount = rpy_matrix(0.2, 0.1, -0.4)
    u0, var = body_x_tilt(q, mount, tuple(cov.ravel()))
    d = rng.multivariate_normal(np.zeros(3), cov, 40000)
    u = [body_x_tilt(tuple((Rotation.from_rotvec(di) * Rotation.from_quat(q)).as_quat()),
                     mount)[0] for di in d]
    # 40 000 samples: the sample variance is within ~1.5 % (2 sigma) of the true one
    assert np.var(u) == pytest.approx(var, rel=0.03)
    assert np.mean(u) == pytest.approx(u0, abs=3 * math.sqrt(var / len(u)) + 1e-4)


def test_no_orientation_rejects_the_acceleration_naming_the_key():
    q, f = _at_rest(Rotation.identity())
    conv = _converter()
    # the yaw rate is still used
    assert {type(m) for m in conv.convert("/imu", _imu(q, f, ocov0=-1))} == {GyroYawRate}
    (reason,) = [r for (topic, r) in conv.rejected if topic == "/imu"]
    assert reason.startswith("linear_acceleration not used: orientation not provided")
    assert "sensors.imu[0].accel_gravity: level" in reason
    # level ground asked for: the acceleration and the yaw rate come through
    out = _converter(extra="\n    accel_gravity: level").convert("/imu", _imu(q, f, ocov0=-1))
    assert {type(m) for m in out} == {ForwardAccel, GyroYawRate}


def test_a_bad_accel_gravity_names_the_key():
    with pytest.raises(ConfigError, match=r"sensors\.imu\[0\]\.accel_gravity.*orientation, "
                                          r"level.*'tilt'"):
        _converter(extra="\n    accel_gravity: tilt")
