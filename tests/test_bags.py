"""estimation.bags.read_stream on small bags written with rosbags (ROS1, ROS2 sqlite3, MCAP) and on
the real bags: decoding of every message type, mounts, GPS -> ENU, ground truth, ordering, the
fast ROS1 decoder against rosbags, and every kind of bad input."""

from __future__ import annotations

import math
import os
import shutil
from collections import Counter
from pathlib import Path

import bagwriter as bw
import numpy as np
import pytest
from ddfuse.estimation import rosmsg
from ddfuse.estimation.bags import BagStream, open_reader, read_stream
from ddfuse.estimation.config import parse_config
from ddfuse.estimation.errors import BagError
from ddfuse.estimation.frames import GRAVITY
from ddfuse.estimation.measurements import (
    ForwardAccel,
    GpsFix,
    GroundTruthPose,
    GyroYawRate,
    Heading,
    LandmarkObservation,
    WheelOdometry,
    WheelSpeeds,
)

# messages here encode their index in a twist or a fix, beyond any robot
pytestmark = pytest.mark.usefixtures("no_plausibility_screen")

gtsam = pytest.importorskip("gtsam")
pymap3d = pytest.importorskip("pymap3d")

T0 = 1_600_000_000.0  # a realistic epoch stamp, s
FMTS = pytest.mark.parametrize("fmt", bw.FORMATS)
# The two decoding paths (the fast ROS1 decoder, rosbags' objects: sqlite3 and MCAP share it),
# for the many bad-message cases whose handling does not depend on the storage.
PATHS = pytest.mark.parametrize("fmt", ["ros1", "mcap"])


def write(tmp_path: Path, fmt: str, records, name: str = "b") -> Path:
    return bw.write_bag(bw.bag_path(tmp_path, name, fmt), fmt, records)


def config(tree: dict, base: Path | None = None):
    return parse_config(tree, base=base)


def of_type(stream, cls) -> list:
    return [m for m in stream.measurements if isinstance(m, cls)]


def rejected_on(stream, topic: str) -> int:
    return sum(n for (tp, _), n in stream.rejected.items() if tp == topic)


def distinct_cov(n: int, **diag_values) -> list[float]:
    """An n x n row-major matrix of distinct junk values (100 + index) with some entries set, so a
    reader that takes the wrong index gets an obviously wrong number."""
    m = [100.0 + k for k in range(n * n)]
    for k, v in diag_values.items():
        m[int(k[1:])] = v
    return m


def rot(q_xyzw) -> np.ndarray:
    x, y, z, w = q_xyzw
    return gtsam.Rot3.Quaternion(w, x, y, z).matrix()


def rpy_rot(r, p, y) -> np.ndarray:
    return gtsam.Rot3.Ypr(y, p, r).matrix()  # Rz(y) Ry(p) Rx(r)


def quat_of(m: np.ndarray):
    q = gtsam.Rot3(m).toQuaternion()
    return (q.x(), q.y(), q.z(), q.w())


def wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


# --------------------------------------------------------------------------------------------
# Decoding, per message type, in every format
# --------------------------------------------------------------------------------------------

@FMTS
def test_odometry_twist_and_variances_from_message(tmp_path, fmt):
    cov = distinct_cov(6, c0=0.001, c35=0.03)
    recs = [("/odom", bw.odometry(T0 + 0.1 * i + 0.012345678, lin=(0.5 + 0.1 * i, 7.0, 8.0),
                                  ang=(5.0, 6.0, -0.2 + 0.05 * i), x=11.0, y=12.0, twist_cov=cov))
            for i in range(5)]
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config({"sensors": {"odometry": [{"topic": "/odom"}]}}))
    odo = of_type(s, WheelOdometry)
    assert len(odo) == 5 and len(s.measurements) == 5 and s.rejected == {}
    for i, m in enumerate(odo):
        assert m.t == pytest.approx(T0 + 0.1 * i + 0.012345678, abs=1e-6)
        assert m.v == pytest.approx(0.5 + 0.1 * i)
        assert m.yaw_rate == pytest.approx(-0.2 + 0.05 * i)
        assert m.v_var == pytest.approx(0.001)
        assert m.yaw_rate_var == pytest.approx(0.03)
        assert m.sensor == "/odom"
    assert s.t0 == pytest.approx(odo[0].t) and s.t1 == pytest.approx(odo[-1].t)
    assert s.source == str(bag)


@FMTS
def test_odometry_config_noise_replaces_message_covariance_and_use_selects(tmp_path, fmt):
    cov = distinct_cov(6, c0=0.001, c35=0.03)
    recs = [("/odom", bw.odometry(T0 + 0.1 * i, 1.0, 0.25, twist_cov=cov)) for i in range(4)]
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config({"sensors": {"odometry": [
        {"topic": "/odom", "noise": {"v": 0.2, "yaw_rate": 0.1}}]}}))
    for m in of_type(s, WheelOdometry):
        assert m.v_var == pytest.approx(0.04) and m.yaw_rate_var == pytest.approx(0.01)
    s = read_stream(bag, config({"sensors": {"odometry": [{"topic": "/odom", "use": ["v"]}]}}))
    for m in of_type(s, WheelOdometry):
        assert m.v == pytest.approx(1.0) and m.yaw_rate is None
        assert m.v_var == pytest.approx(0.001) and math.isnan(m.yaw_rate_var)
    s = read_stream(bag, config({"sensors": {"odometry": [
        {"topic": "/odom", "use": ["yaw_rate"], "name": "wheel"}]}}))
    for m in of_type(s, WheelOdometry):
        assert m.v is None and m.yaw_rate == pytest.approx(0.25)
        assert math.isnan(m.v_var) and m.yaw_rate_var == pytest.approx(0.03)
        assert m.sensor == "wheel"


@PATHS
def test_unused_component_with_zero_covariance_is_not_a_rejection(tmp_path, fmt):
    cov = distinct_cov(6, c0=0.001, c35=0.0)  # yaw-rate variance zero, but yaw rate not used
    bag = write(tmp_path, fmt, [("/odom", bw.odometry(T0 + 0.1 * i, 1.0, 0.1, twist_cov=cov))
                                for i in range(4)])
    s = read_stream(bag, config({"sensors": {"odometry": [{"topic": "/odom", "use": ["v"]}]}}))
    assert len(of_type(s, WheelOdometry)) == 4 and s.rejected == {}


@FMTS
def test_odometry_mount_rotates_twist_and_covariance(tmp_path, fmt):
    # An odometry source mounted backwards (yaw pi): body forward speed is -linear.x.
    cov = [0.0] * 36
    cov[0], cov[7], cov[35], cov[28] = 0.004, 0.009, 0.05, 0.07
    bag = write(tmp_path, fmt, [("/odom", bw.odometry(T0 + 0.1 * i, lin=(0.8, 0.1, 0.0),
                                                      ang=(0.0, 0.0, 0.3), twist_cov=cov))
                                for i in range(3)])
    s = read_stream(bag, config({"sensors": {"odometry": [
        {"topic": "/odom", "mount": {"rpy": [0.0, 0.0, math.pi]}}]}}))
    for m in of_type(s, WheelOdometry):
        assert m.v == pytest.approx(-0.8) and m.yaw_rate == pytest.approx(0.3)
        assert m.v_var == pytest.approx(0.004) and m.yaw_rate_var == pytest.approx(0.05)
    # Mounted with yaw +90 deg: body v = Rz(90)[0] . lin = -lin.y, variance cov[7].
    s = read_stream(bag, config({"sensors": {"odometry": [
        {"topic": "/odom", "mount": {"rpy": [0.0, 0.0, math.pi / 2]}}]}}))
    for m in of_type(s, WheelOdometry):
        assert m.v == pytest.approx(-0.1) and m.v_var == pytest.approx(0.009)


@FMTS
def test_twist_stamped_needs_config_noise(tmp_path, fmt):
    recs = [("/cmd", bw.twist_stamped(T0 + 0.05 * i, lin=(0.4 + i, 9.0, 9.0),
                                      ang=(9.0, 9.0, -0.3 * i))) for i in range(4)]
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config({"sensors": {"odometry": [
        {"topic": "/cmd", "noise": {"v": 0.3, "yaw_rate": 0.2}}]}}))
    odo = of_type(s, WheelOdometry)
    assert [m.v for m in odo] == pytest.approx([0.4, 1.4, 2.4, 3.4])
    assert [m.yaw_rate for m in odo] == pytest.approx([0.0, -0.3, -0.6, -0.9])
    assert all(m.v_var == pytest.approx(0.09) and m.yaw_rate_var == pytest.approx(0.04)
               for m in odo)
    with pytest.raises(BagError) as e:
        read_stream(bag, config({"sensors": {"odometry": [{"topic": "/cmd"}]}}))
    assert "/cmd" in str(e.value) and "sensors.odometry[0].noise." in str(e.value)
    assert str(bag) in str(e.value)


@FMTS
def test_imu_fields_and_variances(tmp_path, fmt):
    ocov = distinct_cov(3, c8=0.0025)
    wcov = distinct_cov(3, c8=4e-4)
    acov = distinct_cov(3, c0=0.04)
    yaws = [0.7, -2.0, 3.0, 3.5]  # 3.5 rad is reported wrapped
    recs = [("/imu", bw.imu(T0 + 0.02 * i, quat=bw.yaw_quat(y), angvel=(0.11, 0.22, 0.33 + i),
                            accel=(1.5 + i, 2.5, 9.7), ocov=ocov, wcov=wcov, acov=acov))
            for i, y in enumerate(yaws)]
    bag = write(tmp_path, fmt, recs)
    # the covariances' distinct entries are field markers, not a tilt: read the raw x force
    s = read_stream(bag, config({"sensors": {"imu": [{"topic": "/imu",
                                                      "accel_gravity": "level"}]}}))
    hd, gy, ac = of_type(s, Heading), of_type(s, GyroYawRate), of_type(s, ForwardAccel)
    assert len(hd) == len(gy) == len(ac) == 4 and len(s.measurements) == 12
    for i, y in enumerate(yaws):
        assert hd[i].yaw == pytest.approx(wrap(y)) and -math.pi < hd[i].yaw <= math.pi
        assert hd[i].var == pytest.approx(0.0025) and hd[i].source == "imu_orientation"
        assert gy[i].yaw_rate == pytest.approx(0.33 + i) and gy[i].var == pytest.approx(4e-4)
        assert ac[i].accel == pytest.approx(1.5 + i) and ac[i].var == pytest.approx(0.04)
        assert hd[i].t == gy[i].t == ac[i].t == pytest.approx(T0 + 0.02 * i, abs=1e-6)
    s = read_stream(bag, config({"sensors": {"imu": [
        {"topic": "/imu", "noise": {"yaw": 0.1, "yaw_rate": 0.02, "accel": 0.3},
         "accel_gravity": "level"}]}}))
    assert all(m.var == pytest.approx(0.01) for m in of_type(s, Heading))
    assert all(m.var == pytest.approx(4e-4) for m in of_type(s, GyroYawRate))
    assert all(m.var == pytest.approx(0.09) for m in of_type(s, ForwardAccel))
    s = read_stream(bag, config({"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate"]}]}}))
    assert len(s.measurements) == 4 and all(isinstance(m, GyroYawRate) for m in s.measurements)


@FMTS
def test_imu_without_orientation(tmp_path, fmt):
    ocov = [-1.0] + [0.0] * 8  # "orientation not provided"
    recs = [("/imu", bw.imu(T0 + 0.02 * i, quat=(0, 0, 0, 0), angvel=(0, 0, 0.1), ocov=ocov,
                            wcov=bw.diag(1e-4, 1e-4, 1e-4), acov=bw.diag(0.01, 0.01, 0.01)))
            for i in range(5)]
    bag = write(tmp_path, fmt, recs)
    # gravity cannot be taken out without an orientation: the acceleration is not used, the
    # yaw rate is, and the reason names the key that takes the ground as level
    s = read_stream(bag, config({"sensors": {"imu": [
        {"topic": "/imu", "use": ["yaw_rate", "accel"]}]}}))
    assert len(of_type(s, GyroYawRate)) == 5 and not of_type(s, ForwardAccel)
    ((topic, reason), n), = s.rejected.items()
    assert topic == "/imu" and n == 5
    assert reason.startswith("linear_acceleration not used: orientation not provided")
    assert "sensors.imu[0].accel_gravity: level" in reason
    s = read_stream(bag, config({"sensors": {"imu": [
        {"topic": "/imu", "use": ["yaw_rate", "accel"], "accel_gravity": "level"}]}}))
    assert len(of_type(s, GyroYawRate)) == 5 and len(of_type(s, ForwardAccel)) == 5
    assert not of_type(s, Heading) and s.rejected == {}
    with pytest.raises(BagError) as e:
        read_stream(bag, config({"sensors": {"imu": [{"topic": "/imu", "use": ["yaw"],
                                                      "noise": {"yaw": 0.1}}]}}))
    assert "/imu" in str(e.value) and "orientation" in str(e.value)


# --------------------------------------------------------------------------------------------
# IMU mount
# --------------------------------------------------------------------------------------------

@FMTS
@pytest.mark.parametrize("mount", [[math.pi / 2, 0.0, 0.0], [1.5708, 0.0, 0.0]])
def test_husky_like_imu_y_up(tmp_path, fmt, mount):
    """Sensor y axis up: yaw rate is angular_velocity.y, forward accel is linear_acceleration.x,
    and the orientation quaternion (world <- sensor) gives the body yaw."""
    r_bs = rpy_rot(math.pi / 2, 0.0, 0.0)
    assert np.allclose(r_bs @ [0, 1, 0], [0, 0, 1])  # sensor +y is body +z
    psis = [0.3, -1.2, 2.9, -3.1]
    recs = []
    for i, psi in enumerate(psis):
        q = quat_of(rpy_rot(0.0, 0.0, psi) @ r_bs)  # R_ws = R_wb R_bs
        recs.append(("/imu/data", bw.imu(
            T0 + i / 30, quat=q, angvel=(0.05, 0.3 + 0.1 * i, -0.2), accel=(1.2, 9.79, 0.3),
            ocov=bw.diag(0.01, 0.02, 0.03), wcov=bw.diag(1e-4, 4e-4, 9e-4),
            acov=bw.diag(0.04, 0.05, 0.06))))
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config({"sensors": {"imu": [{"topic": "/imu/data",
                                                      "mount": {"rpy": mount}}]}}))
    gy, hd, ac = of_type(s, GyroYawRate), of_type(s, Heading), of_type(s, ForwardAccel)
    assert [m.yaw_rate for m in gy] == pytest.approx([0.3, 0.4, 0.5, 0.6], abs=1e-4)
    assert all(m.var == pytest.approx(4e-4, rel=1e-3) for m in gy)  # the sensor-y variance
    assert [m.accel for m in ac] == pytest.approx([1.2] * 4, abs=1e-3)
    # level: gravity has no share along body x, but the orientation's roll (world x) and pitch
    # (world y) variances tip the forward axis (cos psi, sin psi, 0) by sin psi dx - cos psi dy
    assert [m.var for m in ac] == pytest.approx(
        [0.04 + GRAVITY ** 2 * (math.sin(p) ** 2 * 0.01 + math.cos(p) ** 2 * 0.02)
         for p in psis], rel=1e-3)
    for m, psi in zip(hd, psis, strict=True):
        assert wrap(m.yaw - psi) == pytest.approx(0.0, abs=1e-4)
    # Without the mount the same bag gives angular_velocity.z: the mount is what matters.
    s = read_stream(bag, config({"sensors": {"imu": [{"topic": "/imu/data"}]}}))
    assert [m.yaw_rate for m in of_type(s, GyroYawRate)] == pytest.approx([-0.2] * 4)


@FMTS
def test_imu_general_mount_against_gtsam(tmp_path, fmt):
    rng = np.random.default_rng(7)
    mount = [0.4, -0.7, 2.1]
    r_bs = rpy_rot(*mount)
    a = rng.normal(size=(3, 3))
    wcov = (a @ a.T * 1e-3).ravel().tolist()
    b = rng.normal(size=(3, 3))
    acov = (b @ b.T * 1e-2).ravel().tolist()
    recs, expect = [], []
    for i in range(6):
        psi = rng.uniform(-math.pi, math.pi)
        tilt = rpy_rot(rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), psi)  # R_wb
        w_s, a_s = rng.normal(size=3), rng.normal(size=3) * 3
        recs.append(("/imu", bw.imu(T0 + 0.1 * i, quat=quat_of(tilt @ r_bs), angvel=w_s,
                                    accel=a_s, ocov=bw.diag(1, 1, 1), wcov=wcov, acov=acov)))
        # forward acceleration: body-x specific force less gravity's share, g R_wb[2, 0]
        expect.append((math.atan2(tilt[1, 0], tilt[0, 0]), (r_bs @ w_s)[2],
                       (r_bs @ a_s)[0] - GRAVITY * tilt[2, 0], tilt[0, 0] ** 2 + tilt[1, 0] ** 2))
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config({"sensors": {"imu": [{"topic": "/imu",
                                                      "mount": {"rpy": mount}}]}}))
    hd, gy, ac = of_type(s, Heading), of_type(s, GyroYawRate), of_type(s, ForwardAccel)
    w_var = (r_bs @ np.reshape(wcov, (3, 3)) @ r_bs.T)[2, 2]
    a_var = (r_bs @ np.reshape(acov, (3, 3)) @ r_bs.T)[0, 0]
    for (yaw, wz, ax, tilt_var), h, g, f in zip(expect, hd, gy, ac, strict=True):
        assert wrap(h.yaw - yaw) == pytest.approx(0.0, abs=1e-9)
        assert g.yaw_rate == pytest.approx(wz) and f.accel == pytest.approx(ax)
        # ocov diag(1, 1, 1): the forward axis tips by its horizontal length squared
        assert g.var == pytest.approx(w_var) and f.var == pytest.approx(
            a_var + GRAVITY ** 2 * tilt_var)


# --------------------------------------------------------------------------------------------
# GPS
# --------------------------------------------------------------------------------------------

def _gps_track(n: int = 8):
    lat0, lon0, alt0 = 42.375812, -71.147394, 7.3
    return [(lat0 + 2e-5 * i, lon0 - 3e-5 * i * i, alt0 + 0.1 * i) for i in range(n)]


@FMTS
def test_gps_to_enu_first_fix_datum(tmp_path, fmt):
    track = _gps_track()
    cov = [1.1, 0.2, 0.05, 0.2, 1.3, 0.07, 0.05, 0.07, 4.0]
    # The earliest fix (by header stamp) is recorded second: it is still the datum.
    stamps = [T0 + 0.4 * i for i in range(len(track))]
    order = [1, 0] + list(range(2, len(track)))
    recs = [("/fix", bw.navsatfix(stamps[i], *track[i], cov=cov, status=i % 3),
             stamps[order.index(i)] + 0.05) for i in order]
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config({"sensors": {"gps": [{"topic": "/fix"}]}}))
    fixes = of_type(s, GpsFix)
    assert s.datum == pytest.approx(track[0])
    assert len(fixes) == len(track)
    for i, f in enumerate(fixes):
        lat, lon, alt = track[i]
        assert (f.lat, f.lon, f.alt) == pytest.approx((lat, lon, alt))
        assert f.status == i % 3
        assert np.allclose(f.cov, np.reshape(cov, (3, 3)))
        ref = pymap3d.geodetic2enu(lat, lon, alt, *track[0], deg=True)
        assert np.allclose(f.enu, ref, atol=1e-3)
    assert fixes[0].enu == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)


@FMTS
def test_gps_to_enu_fixed_datum_and_config_noise(tmp_path, fmt):
    track = _gps_track()
    datum = (42.3755, -71.1470, 0.0)
    recs = [("/fix", bw.navsatfix(T0 + 0.4 * i, *track[i], cov=[0.0] * 9, cov_type=0))
            for i in range(len(track))]
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config({"sensors": {"gps": [{"topic": "/fix",
                                                      "noise": {"horizontal": 1.5}}]},
                                 "frame": {"datum": list(datum)}}))
    assert s.datum == pytest.approx(datum)
    for f, (lat, lon, alt) in zip(of_type(s, GpsFix), track, strict=True):
        assert np.allclose(f.enu, pymap3d.geodetic2enu(lat, lon, alt, *datum, deg=True),
                           atol=1e-3)
        assert np.allclose(f.cov, np.diag([2.25, 2.25, 9.0]))
    s = read_stream(bag, config({"sensors": {"gps": [{"topic": "/fix", "noise": {
        "horizontal": 1.5, "vertical": 0.5}}]}}))
    assert all(np.allclose(f.cov, np.diag([2.25, 2.25, 0.25])) for f in of_type(s, GpsFix))


# --------------------------------------------------------------------------------------------
# Wheels and landmarks
# --------------------------------------------------------------------------------------------

@FMTS
def test_joint_state_speeds_by_name(tmp_path, fmt):
    names = ["rear_right", "front_left_wheel", "front_right_wheel", "rear_left"]
    recs = [("/joint_states", bw.joint_state(T0 + 0.02 * i, names, [9.0, 1.0 + i, 2.0 - i, 8.0],
                                             position=[0.0] * 4)) for i in range(5)]
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config({
        "sensors": {"wheels": [{"topic": "/joint_states",
                                "joints": ["front_left_wheel", "front_right_wheel"],
                                "noise": {"speed": 0.1}}]},
        "robot": {"wheel_radius": 0.1, "track_width": 0.5}}))
    ws = of_type(s, WheelSpeeds)
    assert [m.left for m in ws] == pytest.approx([1, 2, 3, 4, 5])
    assert [m.right for m in ws] == pytest.approx([2, 1, 0, -1, -2])
    assert all(m.left_var == pytest.approx(0.01) == m.right_var for m in ws)


@PATHS
def test_joint_state_missing_joint_is_counted(tmp_path, fmt):
    recs = [("/js", bw.joint_state(T0 + 0.02 * i, ["l", "r"] if i != 3 else ["l", "x"],
                                   [1.0, 2.0])) for i in range(6)]
    bag = write(tmp_path, fmt, recs)
    tree = {"sensors": {"wheels": [{"topic": "/js", "joints": ["l", "r"],
                                    "noise": {"speed": 0.1}}]},
            "robot": {"wheel_radius": 0.1, "track_width": 0.5}}
    s = read_stream(bag, config(tree))
    assert len(of_type(s, WheelSpeeds)) == 5 and rejected_on(s, "/js") == 1
    tree["sensors"]["wheels"][0]["joints"] = ["left", "right"]
    with pytest.raises(BagError) as e:
        read_stream(bag, config(tree))
    assert "/js" in str(e.value) and "'left'" in str(e.value)


def _map(tmp_path: Path) -> Path:
    p = tmp_path / "m.landmarks.yaml"
    p.write_text("landmarks:\n  '7': [1.5, -2.0]\n  L2: [0.0, 3.25]\n")
    return p


@FMTS
def test_landmark_observation(tmp_path, fmt):
    recs = [("/lm", bw.landmark(T0 + 0.3 * i, "7" if i % 2 else "L2", 3.2 + i, -0.4 + 0.1 * i,
                                range_variance=0.02, bearing_variance=0.003,
                                has_bearing=i != 2)) for i in range(4)]
    bag = write(tmp_path, fmt, recs)
    m = _map(tmp_path)
    s = read_stream(bag, config({"sensors": {"landmarks": [{"topic": "/lm", "map": str(m)}]}}))
    lm = of_type(s, LandmarkObservation)
    assert s.landmarks == {"7": (1.5, -2.0), "L2": (0.0, 3.25)}
    assert [o.landmark_id for o in lm] == ["L2", "7", "L2", "7"]
    assert [o.range for o in lm] == pytest.approx([3.2, 4.2, 5.2, 6.2])
    assert [o.has_bearing for o in lm] == [True, True, False, True]
    for i, o in enumerate(lm):
        assert o.range_var == pytest.approx(0.02)
        if i == 2:
            assert math.isnan(o.bearing) and math.isnan(o.bearing_var)
        else:
            assert o.bearing == pytest.approx(-0.4 + 0.1 * i)
            assert o.bearing_var == pytest.approx(0.003)
    s = read_stream(bag, config({"sensors": {"landmarks": [
        {"topic": "/lm", "map": str(m), "noise": {"range": 0.1, "bearing": 0.05}}]}}))
    lm = of_type(s, LandmarkObservation)
    assert all(o.range_var == pytest.approx(0.01) for o in lm)
    assert [o.bearing_var for o in lm if o.has_bearing] == pytest.approx([0.0025] * 3)
    s = read_stream(bag, config({"sensors": {"landmarks": [
        {"topic": "/lm", "map": str(m), "use": ["range"]}]}}))
    assert not any(o.has_bearing for o in of_type(s, LandmarkObservation))


# --------------------------------------------------------------------------------------------
# Ground truth
# --------------------------------------------------------------------------------------------

def _odom_sensor(n: int = 5):
    cov = bw.diag(0.01, 1, 1, 1, 1, 0.02)
    return [("/odom", bw.odometry(T0 + 0.1 * i, 1.0, 0.0, twist_cov=cov)) for i in range(n)]


@FMTS
@pytest.mark.parametrize("kind", ["odometry", "pose"])
def test_ground_truth_pose(tmp_path, fmt, kind):
    poses = [(1.0 + i, -2.0 * i, wrap(0.9 * i)) for i in range(5)]
    if kind == "odometry":
        gt = [("/gt", bw.odometry(T0 + 0.1 * i + 0.01, 9.0, 9.0, x=x, y=y, yaw=yaw))
              for i, (x, y, yaw) in enumerate(poses)]
    else:
        gt = [("/gt", bw.pose_stamped(T0 + 0.1 * i + 0.01, x, y, yaw, z=5.0))
              for i, (x, y, yaw) in enumerate(poses)]
    bag = write(tmp_path, fmt, _odom_sensor() + gt)
    s = read_stream(bag, config({"sensors": {"odometry": [{"topic": "/odom"}]},
                                 "ground_truth": {"topic": "/gt"}}))
    assert len(s.measurements) == 5 and all(isinstance(m, WheelOdometry) for m in s.measurements)
    assert all(isinstance(g, GroundTruthPose) for g in s.ground_truth)
    got = [(g.x, g.y, g.yaw) for g in s.ground_truth]
    assert got == [pytest.approx(p) for p in poses]
    assert [g.t for g in s.ground_truth] == pytest.approx([T0 + 0.1 * i + 0.01 for i in range(5)])


@FMTS
def test_ground_truth_navsatfix_fixed_and_first_fix_datum(tmp_path, fmt):
    track = _gps_track(5)
    gt = [("/gt_fix", bw.navsatfix(T0 + 0.1 * i, *track[i])) for i in range(5)]
    bag = write(tmp_path, fmt, _odom_sensor() + gt)
    datum = (42.3757, -71.1474, 2.0)
    s = read_stream(bag, config({"sensors": {"odometry": [{"topic": "/odom"}]},
                                 "ground_truth": {"topic": "/gt_fix"},
                                 "frame": {"datum": list(datum)}}))
    assert not of_type(s, GpsFix)  # ground truth is not a measurement
    for g, (lat, lon, alt) in zip(s.ground_truth, track, strict=True):
        e, n, _ = pymap3d.geodetic2enu(lat, lon, alt, *datum, deg=True)
        assert (g.x, g.y) == pytest.approx((e, n), abs=1e-3) and math.isnan(g.yaw)
    # Without GPS sensors, first_fix takes the datum from the ground truth itself.
    s = read_stream(bag, config({"sensors": {"odometry": [{"topic": "/odom"}]},
                                 "ground_truth": {"topic": "/gt_fix"}}))
    assert s.datum == pytest.approx(track[0])
    for g, (lat, lon, alt) in zip(s.ground_truth, track, strict=True):
        e, n, _ = pymap3d.geodetic2enu(lat, lon, alt, *track[0], deg=True)
        assert (g.x, g.y) == pytest.approx((e, n), abs=1e-3)


@FMTS
def test_ground_truth_navsatfix_uses_the_gps_datum(tmp_path, fmt):
    track = _gps_track(6)
    recs = [("/fix", bw.navsatfix(T0 + 0.1 * i, *track[i])) for i in range(3, 6)]
    recs += [("/gt_fix", bw.navsatfix(T0 + 0.1 * i - 0.05, *track[i])) for i in range(6)]
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config({"sensors": {"gps": [{"topic": "/fix"}]},
                                 "ground_truth": {"topic": "/gt_fix"}}))
    assert s.datum == pytest.approx(track[3])  # the first GPS measurement, as documented
    fixes = of_type(s, GpsFix)
    assert (s.ground_truth[3].x, s.ground_truth[3].y) == pytest.approx(fixes[0].enu[:2],
                                                                       abs=1e-6)


@FMTS
def test_two_sources_on_one_topic(tmp_path, fmt):
    """An odometry topic used both as a sensor and as ground truth: each message feeds both."""
    cov = bw.diag(0.01, 1, 1, 1, 1, 0.02)
    recs = [("/odom", bw.odometry(T0 + 0.1 * i, 0.1 * i, -0.1 * i, x=float(i), y=2.0 * i,
                                  yaw=0.1 * i, twist_cov=cov)) for i in range(20)]
    recs += [("/imu", bw.imu(T0 + 0.1 * i + 0.05, angvel=(0, 0, 0.5),
                             wcov=bw.diag(1, 1, 1))) for i in range(20)]
    bag = write(tmp_path, fmt, sorted(recs, key=lambda r: r[1].stamp))
    s = read_stream(bag, config({"sensors": {"odometry": [{"topic": "/odom"}],
                                             "imu": [{"topic": "/imu", "use": ["yaw_rate"]}]},
                                 "ground_truth": {"topic": "/odom"}}))
    odo = of_type(s, WheelOdometry)
    assert [m.v for m in odo] == pytest.approx([0.1 * i for i in range(20)])
    assert [(g.x, g.y, g.yaw) for g in s.ground_truth] == [
        pytest.approx((float(i), 2.0 * i, 0.1 * i)) for i in range(20)]


# --------------------------------------------------------------------------------------------
# Ordering and stamps
# --------------------------------------------------------------------------------------------

@FMTS
def test_messages_recorded_out_of_stamp_order_come_out_sorted(tmp_path, fmt):
    rng = np.random.default_rng(3)
    imu_stamps = [T0 + 0.02 * i for i in range(100)]
    # Record order: stamps shuffled within blocks of 5 (0.1 s); record times increase.
    order = []
    for k in range(0, 100, 5):
        order += list(rng.permutation(range(k, k + 5)))
    recs = [("/imu", bw.imu(imu_stamps[i], angvel=(0, 0, i), wcov=bw.diag(1, 1, 1)), T0 + 0.02 * j)
            for j, i in enumerate(order)]
    # Odometry whose stamps lag its record times by 0.3 s (a slow driver): interleaved.
    cov = bw.diag(0.01, 1, 1, 1, 1, 0.02)
    recs += [("/odom", bw.odometry(T0 + 0.1 * i, float(i), 0.0, twist_cov=cov),
              T0 + 0.1 * i + 0.3) for i in range(20)]
    recs.sort(key=lambda r: r[2])
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config({"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate"]}],
                                             "odometry": [{"topic": "/odom"}]}}))
    t = [m.t for m in s.measurements]
    assert t == sorted(t)
    assert s.rejected == {}
    assert [m.yaw_rate for m in of_type(s, GyroYawRate)] == pytest.approx(list(range(100)))
    assert [m.v for m in of_type(s, WheelOdometry)] == pytest.approx(list(range(20)))
    assert s.t0 == pytest.approx(T0, abs=1e-6) and s.t1 == pytest.approx(imu_stamps[-1], abs=1e-6)


@FMTS
@pytest.mark.parametrize("broken", ["zero", "future"])
def test_single_broken_stamp_is_dropped_and_counted(tmp_path, fmt, broken):
    n, bad = 30, 15
    recs = []
    for i in range(n):
        t = T0 + 0.1 * i
        stamp = t if i != bad else (0.0 if broken == "zero" else t + 1e5)
        recs.append(("/imu", bw.imu(stamp, angvel=(0, 0, i), wcov=bw.diag(1, 1, 1)), t))
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config({"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate"]}]}}))
    got = [m.yaw_rate for m in s.measurements]
    assert got == pytest.approx([float(i) for i in range(n) if i != bad])
    assert rejected_on(s, "/imu") == 1
    assert s.t0 == pytest.approx(T0, abs=1e-6)
    assert s.t1 == pytest.approx(T0 + 0.1 * (n - 1), abs=1e-6)


@PATHS
def test_a_broken_stamp_counts_once_per_message_as_live(tmp_path, fmt):
    """An IMU message gives three measurements (yaw rate, yaw, acceleration). Its broken stamp
    was counted three times by the bag reader, once by ``LiveConverter``; now once by both,
    with all three dropped."""
    from ddfuse.estimation.live import LiveConverter

    n, bad = 30, 15
    recs = []
    for i in range(n):
        t = T0 + 0.1 * i
        recs.append(("/imu", bw.imu(t if i != bad else t + 1e5, angvel=(0, 0, i),
                                    wcov=bw.diag(1, 1, 1), ocov=bw.diag(0.01, 0.01, 0.01),
                                    acov=bw.diag(0.01, 0.01, 0.01)), t))
    bag = write(tmp_path, fmt, recs)
    cfg = config({"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate", "yaw", "accel"]}]}})
    s = read_stream(bag, cfg)
    assert rejected_on(s, "/imu") == 1
    for cls in (GyroYawRate, Heading, ForwardAccel):
        assert len(of_type(s, cls)) == n - 1
    assert [m.yaw_rate for m in of_type(s, GyroYawRate)] == pytest.approx(
        [float(i) for i in range(n) if i != bad])
    conv = LiveConverter(cfg)
    reader = open_reader(bag)
    try:
        for c, rec_ns, b in reader.messages(connections=reader.connections):
            conv.convert(c.topic, reader.deserialize(b, c.msgtype), c.msgtype,
                         received=rec_ns * 1e-9)
    finally:
        reader.close()
    assert sum(conv.rejected.values()) == 1


@FMTS
def test_time_going_backwards_for_many_messages_is_an_error(tmp_path, fmt):
    recs = []
    for i in range(40):
        t = T0 + 0.1 * i
        recs.append(("/imu", bw.imu(t - (5.0 if i >= 28 else 0.0), wcov=bw.diag(1, 1, 1)), t))
    bag = write(tmp_path, fmt, recs)
    with pytest.raises(BagError) as e:
        read_stream(bag, config({"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate"]}]}}))
    assert "/imu" in str(e.value) and "sensors.imu[0]" in str(e.value)


def test_time_going_backwards_error_names_the_bag(tmp_path):
    recs = [("/imu", bw.imu(T0 + 0.1 * i - (5.0 if i >= 28 else 0.0), wcov=bw.diag(1, 1, 1)),
             T0 + 0.1 * i) for i in range(40)]
    bag = write(tmp_path, "ros1", recs)
    with pytest.raises(BagError) as e:
        read_stream(bag, config({"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate"]}]}}))
    assert str(bag) in str(e.value)


@PATHS
def test_reorder_window_widens_the_stamp_tolerance(tmp_path, fmt):
    # 2 of 40 stamps 3 s late: dropped with the default window, kept with reorder_window 5.
    recs = [("/imu", bw.imu(T0 + 0.1 * i + (3.0 if i in (10, 30) else 0.0),
                            wcov=bw.diag(1, 1, 1)), T0 + 0.1 * i) for i in range(40)]
    bag = write(tmp_path, fmt, recs)
    tree = {"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate"]}]}}
    assert len(read_stream(bag, config(tree)).measurements) == 38
    s = read_stream(bag, config({**tree, "reorder_window": 5.0}))
    assert len(s.measurements) == 40 and s.rejected == {}
    assert [m.t for m in s.measurements] == sorted(m.t for m in s.measurements)


# --------------------------------------------------------------------------------------------
# Single bad messages: NaN / Inf, NO_FIX, zero covariance
# --------------------------------------------------------------------------------------------

def _bad_value_case(kind: str, i: int, bad: bool, value: float):
    t = T0 + 0.1 * i
    v = value if bad else 1.0
    if kind == "odometry":
        return "/odom", bw.odometry(t, v, 0.1, twist_cov=bw.diag(0.01, 1, 1, 1, 1, 0.02))
    if kind == "imu":
        return "/imu", bw.imu(t, angvel=(0.0, 0.0, v), wcov=bw.diag(1, 1, 1))
    if kind == "gps":
        return "/fix", bw.navsatfix(t, 42.0 if not bad else value, -71.0)
    if kind == "wheels":
        return "/js", bw.joint_state(t, ["l", "r"], [v, 1.0])
    if kind == "landmarks":
        return "/lm", bw.landmark(t, "7", v, 0.1)
    raise AssertionError(kind)


BAD_TREES = {
    "odometry": {"sensors": {"odometry": [{"topic": "/odom"}]}},
    "imu": {"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate"]}]}},
    "gps": {"sensors": {"gps": [{"topic": "/fix"}]}},
    "wheels": {"sensors": {"wheels": [{"topic": "/js", "joints": ["l", "r"],
                                       "noise": {"speed": 0.1}}]},
               "robot": {"wheel_radius": 0.1, "track_width": 0.5}},
    "landmarks": {"sensors": {"landmarks": [{"topic": "/lm", "map": "MAP"}]}},
}


def _tree(kind: str, tmp_path: Path) -> dict:
    import copy

    tree = copy.deepcopy(BAD_TREES[kind])
    if kind == "landmarks":
        tree["sensors"]["landmarks"][0]["map"] = str(_map(tmp_path))
    return tree


@PATHS
@pytest.mark.parametrize("kind", list(BAD_TREES))
def test_non_finite_fields_are_rejected_and_counted(tmp_path, fmt, kind):
    bad = {2: math.nan, 5: math.inf, 7: -math.inf}
    recs = [_bad_value_case(kind, i, i in bad, bad.get(i, 0.0)) for i in range(10)]
    topic = recs[0][0]
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config(_tree(kind, tmp_path)))
    assert len(s.measurements) == 7
    assert rejected_on(s, topic) == 3
    assert [m.t for m in s.measurements] == pytest.approx(
        [T0 + 0.1 * i for i in range(10) if i not in bad], abs=1e-6)


@PATHS
def test_non_finite_ground_truth_is_rejected(tmp_path, fmt):
    gt = [("/gt", bw.pose_stamped(T0 + 0.1 * i, math.nan if i == 1 else 1.0, 2.0))
          for i in range(5)]
    bag = write(tmp_path, fmt, _odom_sensor() + gt)
    s = read_stream(bag, config({"sensors": {"odometry": [{"topic": "/odom"}]},
                                 "ground_truth": {"topic": "/gt"}}))
    assert len(s.ground_truth) == 4 and rejected_on(s, "/gt") == 1


@PATHS
def test_nan_in_an_unused_field_keeps_the_message(tmp_path, fmt):
    recs = [("/imu", bw.imu(T0 + 0.1 * i, quat=(math.nan,) * 4, accel=(math.nan,) * 3,
                            angvel=(0, 0, 0.2), wcov=bw.diag(1, 1, 1))) for i in range(4)]
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config({"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate"]}]}}))
    assert len(s.measurements) == 4 and s.rejected == {}


@FMTS
def test_navsatfix_no_fix_is_rejected_and_counted(tmp_path, fmt):
    track = _gps_track(6)
    recs = [("/fix", bw.navsatfix(T0 + 0.4 * i, *track[i], status=-1 if i in (0, 4) else 0))
            for i in range(6)]
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, config({"sensors": {"gps": [{"topic": "/fix"}]}}))
    fixes = of_type(s, GpsFix)
    assert [f.lat for f in fixes] == pytest.approx([track[i][0] for i in (1, 2, 3, 5)])
    assert s.datum == pytest.approx(track[1])  # a NO_FIX message is no datum
    assert rejected_on(s, "/fix") == 2
    assert any("NO_FIX" in reason for (_, reason) in s.rejected)


# (kind, builder of one message with a zero variance field, field named in the error, noise)
def _zero_cov_msg(case: str, t: float, zero: bool):
    z = 0.0 if zero else 0.01
    if case == "odometry_v":
        return "/odom", bw.odometry(t, 1.0, 0.1, twist_cov=bw.diag(z, 1, 1, 1, 1, 0.02))
    if case == "odometry_yaw_rate":
        return "/odom", bw.odometry(t, 1.0, 0.1, twist_cov=bw.diag(0.01, 1, 1, 1, 1, z))
    if case == "imu_yaw":
        return "/imu", bw.imu(t, ocov=bw.diag(1, 1, z), wcov=bw.diag(1, 1, 1),
                              acov=bw.diag(1, 1, 1))
    if case == "imu_yaw_rate":
        return "/imu", bw.imu(t, ocov=bw.diag(1, 1, 1), wcov=bw.diag(1, 1, z),
                              acov=bw.diag(1, 1, 1))
    if case == "imu_accel":
        return "/imu", bw.imu(t, ocov=bw.diag(1, 1, 1), wcov=bw.diag(1, 1, 1),
                              acov=bw.diag(z, 1, 1))
    if case == "landmark_range":
        return "/lm", bw.landmark(t, "7", 2.0, 0.1, range_variance=z)
    if case == "landmark_bearing":
        return "/lm", bw.landmark(t, "7", 2.0, 0.1, bearing_variance=z)
    if case == "gps":  # a usable variance above the floor a plain fix may claim (0.5 m)^2
        v = 0.0 if zero else 1.0
        return "/fix", bw.navsatfix(t, 42.0, -71.0, cov=bw.diag(v, v, v))
    if case == "gps_unknown_type":
        return "/fix", bw.navsatfix(t, 42.0, -71.0, cov=bw.diag(1, 1, 1),
                                    cov_type=1 if not zero else 0)
    raise AssertionError(case)


ZERO_COV = {  # case -> (sensor kind, field the error names, noise key)
    "odometry_v": ("odometry", "twist.covariance[0]", "v"),
    "odometry_yaw_rate": ("odometry", "twist.covariance[35]", "yaw_rate"),
    "imu_yaw": ("imu", "orientation_covariance", "yaw"),
    "imu_yaw_rate": ("imu", "angular_velocity_covariance", "yaw_rate"),
    "imu_accel": ("imu", "linear_acceleration_covariance", "accel"),
    "landmark_range": ("landmarks", "range_variance", "range"),
    "landmark_bearing": ("landmarks", "bearing_variance", "bearing"),
    "gps": ("gps", "position_covariance", "horizontal"),
    "gps_unknown_type": ("gps", "position_covariance_type", "horizontal"),
}


def _zero_cov_tree(case: str, topic: str, tmp_path: Path, noise: bool) -> dict:
    kind, _, key = ZERO_COV[case]
    s = {"topic": topic}
    if kind == "landmarks":
        s["map"] = str(_map(tmp_path))
    if noise:
        s["noise"] = {key: 0.5}
    return {"sensors": {kind: [s]}}


@PATHS
@pytest.mark.parametrize("case", list(ZERO_COV))
def test_zero_covariance_without_noise(tmp_path, fmt, case):
    kind, field, key = ZERO_COV[case]
    # Some messages with a zero variance: those are rejected and counted, the rest kept.
    recs = [_zero_cov_msg(case, T0 + 0.1 * i, i in (1, 2)) for i in range(6)]
    topic = recs[0][0]
    bag = write(tmp_path, fmt, recs, "some")
    s = read_stream(bag, config(_zero_cov_tree(case, topic, tmp_path, noise=False)))
    assert len({m.t for m in s.measurements}) == 4
    assert rejected_on(s, topic) == 2
    assert any(field in reason for (_, reason) in s.rejected)
    # A configured noise makes the message covariance irrelevant.
    s = read_stream(bag, config(_zero_cov_tree(case, topic, tmp_path, noise=True)))
    assert len({m.t for m in s.measurements}) == 6 and s.rejected == {}
    # All messages with a zero variance: the topic is unusable, and the error says why.
    recs = [_zero_cov_msg(case, T0 + 0.1 * i, True) for i in range(6)]
    bag = write(tmp_path, fmt, recs, "all")
    with pytest.raises(BagError) as e:
        read_stream(bag, config(_zero_cov_tree(case, topic, tmp_path, noise=False)))
    msg = str(e.value)
    assert topic in msg and field in msg and f"sensors.{kind}[0].noise.{key}" in msg
    assert str(bag) in msg


# --------------------------------------------------------------------------------------------
# Bags and topics that cannot be used
# --------------------------------------------------------------------------------------------

IMU_TREE = {"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate"]}]}}


def _imu_bag(tmp_path: Path, fmt: str, n: int = 3000, name: str = "b") -> Path:
    return write(tmp_path, fmt, [("/imu", bw.imu(T0 + 0.01 * i, wcov=bw.diag(1, 1, 1)))
                                 for i in range(n)], name)


def _copy(bag: Path, fmt: str, dest: Path) -> tuple[Path, Path]:
    """Copy a bag; returns (the path to read, its storage file)."""
    if fmt == "ros1":
        shutil.copy(bag, dest)
        return dest, dest
    shutil.copytree(bag, dest)
    return dest, dest / bw.storage_file(bag, fmt).name


@pytest.mark.parametrize("name", ["missing.bag", "missing_dir", "missing.mcap", "missing.db3"])
def test_missing_file(tmp_path, name):
    p = tmp_path / name
    with pytest.raises(BagError) as e:
        read_stream(p, parse_config(IMU_TREE))
    assert str(p) in str(e.value)


@pytest.mark.parametrize("content", [b"", b"#ROSBAG V2.0\n" + b"\x00" * 100,
                                     bytes(range(256)) * 40, b"just some text\n" * 50])
def test_garbage_bag_file(tmp_path, content):
    p = tmp_path / "garbage.bag"
    p.write_bytes(content)
    with pytest.raises(BagError) as e:
        read_stream(p, parse_config(IMU_TREE))
    assert str(p) in str(e.value)


@pytest.mark.parametrize("case", ["empty_dir", "dir_garbage_db3", "bad_metadata",
                                  "mcap_alone", "db3_alone", "text_file"])
def test_garbage_ros2_bag(tmp_path, case):
    d = tmp_path / "bag"
    d.mkdir()
    p = d
    if case == "dir_garbage_db3":
        (d / "bag.db3").write_bytes(os.urandom(4096))
    elif case == "bad_metadata":
        (d / "bag.db3").write_bytes(os.urandom(4096))
        (d / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    elif case == "mcap_alone":
        p = d / "x.mcap"
        p.write_bytes(os.urandom(4096))
    elif case == "db3_alone":
        p = d / "x.db3"
        p.write_bytes(os.urandom(4096))
    elif case == "text_file":
        p = tmp_path / "notes.txt"
        p.write_text("not a bag\n")
    with pytest.raises(BagError) as e:
        read_stream(p, parse_config(IMU_TREE))
    assert str(p) in str(e.value)
    if case in ("empty_dir", "dir_garbage_db3"):  # says what a bag directory lacks
        assert "not a ROS2 bag (no metadata.yaml in it)" in str(e.value)


@FMTS
@pytest.mark.parametrize("frac", [0.05, 0.5, 0.97])
def test_truncated_bag(tmp_path, fmt, frac):
    bag = _imu_bag(tmp_path, fmt)
    cut, storage = _copy(bag, fmt, bw.bag_path(tmp_path, "cut", fmt))
    size = storage.stat().st_size
    with open(storage, "r+b") as f:
        f.truncate(int(size * frac))
    with pytest.raises(BagError) as e:
        read_stream(cut, parse_config(IMU_TREE))
    assert str(cut) in str(e.value)


@pytest.mark.parametrize("fmt", ["sqlite3", "mcap"])
def test_a_ros2_storage_file_can_be_given_directly(tmp_path, fmt):
    bag = _imu_bag(tmp_path, fmt, n=10)
    s = read_stream(bw.storage_file(bag, fmt), parse_config(IMU_TREE))
    assert len(s.measurements) == 10




def _damage(tmp_path: Path, fmt: str, where: float, pattern: bytes) -> Path:
    """A 3000-message IMU bag with 5000 bytes overwritten at ``where`` of its storage file."""
    bag = _imu_bag(tmp_path, fmt)
    bad, storage = _copy(bag, fmt, bw.bag_path(tmp_path, "bad", fmt))
    size = storage.stat().st_size
    with open(storage, "r+b") as f:
        f.seek(int(size * where))
        f.write(pattern * 5000)
    return bad


@pytest.mark.parametrize("fmt", [
    "ros1",
    "sqlite3",
    "mcap",
])
def test_bag_damaged_in_the_middle(tmp_path, fmt):
    """0xff bytes written over the middle of the file (a disk error, a bad copy): BagError, or
    (a ROS1 bag, read past its damaged chunk) a warning naming the file and byte, the messages
    lost counted."""
    bad = _damage(tmp_path, fmt, 0.5, b"\xff")
    if fmt == "ros1":
        bs = BagStream(bad, parse_config(IMU_TREE))
        got = len(list(bs))
        assert any(str(bad) in w and "damaged record at byte" in w for w in bs.warnings)
        assert 0 < got < 3000 and got + sum(bs.rejected.values()) == 3000
        return
    with pytest.raises(BagError) as e:
        read_stream(bad, parse_config(IMU_TREE))
    assert str(bad) in str(e.value)


def test_damaged_mcap_does_not_lose_messages_silently(tmp_path):
    bad = _damage(tmp_path, "mcap", 0.3, b"\x00")
    try:
        s = read_stream(bad, parse_config(IMU_TREE))
    except BagError:
        return
    assert len(s.measurements) + sum(s.rejected.values()) == 3000


@FMTS
def test_configured_topic_absent(tmp_path, fmt):
    bag = _imu_bag(tmp_path, fmt, n=5)
    with pytest.raises(BagError) as e:
        read_stream(bag, parse_config({"sensors": {"imu": [{"topic": "/imu"}],
                                                   "gps": [{"topic": "/gps/fix"}]}}))
    msg = str(e.value)
    assert str(bag) in msg and "/gps/fix" in msg and "sensors.gps[0].topic" in msg
    assert "/imu" in msg  # the topics that are there
    with pytest.raises(BagError) as e:
        read_stream(bag, parse_config({**IMU_TREE, "ground_truth": {"topic": "/truth"}}))
    assert "/truth" in str(e.value) and "ground_truth.topic" in str(e.value)
    with pytest.raises(BagError) as e:
        read_stream(bag, parse_config({"sensors": {"imu": [
            {"topic": "/imu", "name": "a"}, {"topic": "/imu2", "name": "b"}]}}))
    assert "/imu2" in str(e.value) and "sensors.imu[1].topic" in str(e.value)


@FMTS
def test_wrong_message_type(tmp_path, fmt):
    bag = write(tmp_path, fmt, _odom_sensor() + [
        ("/imu", bw.imu(T0 + 0.1 * i, wcov=bw.diag(1, 1, 1))) for i in range(5)])
    with pytest.raises(BagError) as e:
        read_stream(bag, parse_config({"sensors": {"imu": [{"topic": "/odom"}]}}))
    msg = str(e.value)
    assert "/odom" in msg and "nav_msgs/Odometry" in msg and "sensor_msgs/Imu" in msg
    assert "sensors.imu[0]" in msg and str(bag) in msg
    with pytest.raises(BagError) as e:
        read_stream(bag, parse_config({"sensors": {"odometry": [{"topic": "/imu"}]}}))
    msg = str(e.value)
    assert "sensor_msgs/Imu" in msg and "nav_msgs/Odometry" in msg
    assert "geometry_msgs/TwistStamped" in msg
    with pytest.raises(BagError) as e:
        read_stream(bag, parse_config({"sensors": {"odometry": [{"topic": "/odom"}]},
                                       "ground_truth": {"topic": "/imu"}}))
    msg = str(e.value)
    assert "/imu" in msg and "ground_truth" in msg
    assert all(t in msg for t in ("nav_msgs/Odometry", "geometry_msgs/PoseStamped",
                                  "sensor_msgs/NavSatFix"))
    with pytest.raises(BagError) as e:
        read_stream(bag, parse_config({"sensors": {"gps": [{"topic": "/odom"}]}}))
    assert "sensor_msgs/NavSatFix" in str(e.value) and "sensors.gps[0]" in str(e.value)


# A regression test: the decode cache was once keyed by id(raw), which CPython reuses once the
# previous message is freed, so ROS1 sightings interleaved with odometry came out stale.
@FMTS
def test_landmarks_interleaved_with_odometry_are_each_decoded(tmp_path, fmt):
    """Every sighting comes out once, with its own values, whatever the interleaving."""
    m = _map(tmp_path)
    cov = bw.diag(0.01, 1, 1, 1, 1, 0.02)
    wrong = {}
    for every in (1, 2, 3, 5, 8, 16):
        recs, n = [], 0
        for i in range(400):
            t = T0 + 0.02 * i
            recs.append(("/odom", bw.odometry(t, 1.0, 0.0, twist_cov=cov)))
            if i % every == 0:
                recs.append(("/lm", bw.landmark(t + 0.001, "7", 1.0 + n, 0.0)))
                n += 1
        bag = write(tmp_path, fmt, recs, f"every{every}")
        s = read_stream(bag, config({"sensors": {
            "odometry": [{"topic": "/odom"}],
            "landmarks": [{"topic": "/lm", "map": str(m)}]}, "reorder_window": 1e6}))
        got = [o.range for o in of_type(s, LandmarkObservation)]
        wrong[every] = sum(abs(g - (1.0 + k)) > 1e-9 for k, g in enumerate(got))
        assert len(got) == n
    assert wrong == dict.fromkeys(wrong, 0)


@pytest.mark.slow
def test_mrclam_landmarks_with_odometry_match_rosbags(mrclam_bag):
    """Every sighting of the real MRCLAM bag, read together with /odom, equals rosbags' own
    decoding (with the id(raw) cache, 3933 of 4771 came out as copies of earlier ones)."""
    reader = open_reader(mrclam_bag)
    try:
        conns = [c for c in reader.connections if c.topic == "/landmarks"]
        ref = sorted(rosmsg.EXTRACTORS[rosmsg.LANDMARK][1](reader.deserialize(raw, c.msgtype))[:4]
                     for c, _, raw in reader.messages(connections=conns))
    finally:
        reader.close()
    cfg = config({"sensors": {"odometry": [{"topic": "/odom"}], "landmarks": [
        {"topic": "/landmarks", "map": str(mrclam_bag.with_suffix(".landmarks.yaml"))}]},
        "reorder_window": 1e5})
    s = read_stream(mrclam_bag, cfg)
    got = sorted((o.t, o.landmark_id, o.range, o.bearing)
                 for o in of_type(s, LandmarkObservation))
    assert len(got) == len(ref) == 4771
    assert got == ref


# --------------------------------------------------------------------------------------------
# The fast ROS1 decoder equals rosbags' deserialisation
# --------------------------------------------------------------------------------------------

def _same(a, b) -> bool:
    """Tuples equal, element by element, with NaN equal to NaN."""
    if isinstance(a, tuple | list) and isinstance(b, tuple | list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return type(a) is type(b) and a == b


def _compare_fast_path(bag: Path) -> Counter:
    reader = open_reader(bag)
    counts: Counter = Counter()
    try:
        conns = [c for c in reader.connections
                 if c.msgtype in rosmsg.EXTRACTORS and rosmsg.EXTRACTORS[c.msgtype][0]]
        for c, _, raw in reader.messages(connections=conns):
            fast, slow = rosmsg.EXTRACTORS[c.msgtype]
            a, b = fast(raw), slow(reader.deserialize(raw, c.msgtype))
            assert _same(a, b), f"{bag} {c.topic} message {counts[c.topic]}: {a} != {b}"
            counts[c.topic] += 1
    finally:
        reader.close()
    return counts


def test_fast_ros1_path_on_synthetic_messages(tmp_path):
    recs = []
    for i in range(8):
        t = T0 + 0.1 * i + 1e-9 * (i * 123457)
        fid = "f" * i  # frame_id lengths 0..7 shift every field's alignment
        recs += [
            ("/odom", bw.odometry(t, 0.1 * i, -0.2 * i, x=i, y=-i, yaw=0.3 * i,
                                  twist_cov=[i + k / 7 for k in range(36)],
                                  pose_cov=[-k for k in range(36)], frame_id=fid,
                                  child_frame_id="c" * (7 - i))),
            ("/imu", bw.imu(t, quat=(0.1, 0.2, 0.3, 0.9), angvel=(i, math.nan, -i),
                            accel=(math.inf, 2.0, 3.0 * i), ocov=[k * 0.5 for k in range(9)],
                            wcov=[-1.0] + [k for k in range(8)], acov=[1e-9] * 9,
                            frame_id=fid)),
            ("/fix", bw.navsatfix(t, 42.0 + i * 1e-6, -71.0 - i * 1e-6, math.nan if i == 3
                                  else 7.0, status=i % 4 - 1, cov=[k * 0.1 for k in range(9)],
                                  cov_type=i % 4, frame_id=fid)),
            ("/twist", bw.twist_stamped(t, lin=(1.0, 2.0, 3.0 * i), ang=(4.0, 5.0, -6.0),
                                        frame_id=fid)),
            ("/pose", bw.pose_stamped(t, 1.5 * i, -2.5, quat=(0.5, 0.5, -0.5, 0.5), z=3.0,
                                      frame_id=fid)),
        ]
    bag = write(tmp_path, "ros1", recs)
    counts = _compare_fast_path(bag)
    assert counts == {"/odom": 8, "/imu": 8, "/fix": 8, "/twist": 8, "/pose": 8}
    # and the fast decoder reads the values that were written
    reader = open_reader(bag)
    try:
        c = next(c for c in reader.connections if c.topic == "/fix")
        raw = [r for _, _, r in reader.messages(connections=[c])]
    finally:
        reader.close()
    t, status, lat, lon, alt, cov, ctype = rosmsg.EXTRACTORS[rosmsg.NAVSATFIX][0](raw[5])
    assert t == pytest.approx(T0 + 0.5 + 1e-9 * 5 * 123457, abs=1e-6)
    assert (status, lat, lon, alt, ctype) == (0, pytest.approx(42.000005),
                                              pytest.approx(-71.000005), 7.0, 1)
    assert cov == pytest.approx([k * 0.1 for k in range(9)])


@pytest.mark.slow
@pytest.mark.parametrize("name", ["husky", "jackal"])
def test_fast_ros1_path_equals_rosbags_on_real_bags(request, name):
    bag = request.getfixturevalue(f"{name}_bag")
    counts = _compare_fast_path(bag)
    expected = {"husky": {"/husky_velocity_controller/odom": 3952, "/imu/data": 11865,
                          "/fix": 989},
                "jackal": {"/jackal_velocity_controller/odom": 3060, "/imu/data": 3061}}[name]
    assert counts == expected


@pytest.mark.slow
def test_fast_ros1_path_equals_rosbags_on_mrclam(mrclam_bag):
    assert _compare_fast_path(mrclam_bag) == {"/odom": 75000, "/ground_truth": 75000}


def test_a_fix_with_a_nan_stamp_is_named_for_its_stamp_not_its_position():
    import math

    from ddfuse.estimation.bags import Reject, _gps_fix

    cov = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 4.0)
    with pytest.raises(Reject, match="non-finite stamp"):
        _gps_fix((math.nan, 0, 47.0, 8.0, 400.0, cov, 2), "/fix")
    with pytest.raises(Reject, match="latitude/longitude not finite"):
        _gps_fix((1.0, 0, math.nan, 8.0, 400.0, cov, 2), "/fix")
