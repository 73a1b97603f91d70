"""The bag reader's input handling found wanting by audit 13: unset (zero or negative) header
stamps, unusable NavSatFix covariances, Null Island fixes, a bad IMU orientation, late and
empty topics. Each test builds the smallest bag that shows the defect."""

from __future__ import annotations

import math
from pathlib import Path

import bagwriter as bw
import numpy as np
import pytest
from ddfuse.estimation.bags import NULL_ISLAND, UNSET_STAMP, BagStream, read_stream
from ddfuse.estimation.config import parse_config
from ddfuse.estimation.errors import BagError
from ddfuse.estimation.measurements import ForwardAccel, GpsFix, GyroYawRate, Heading

# messages here encode their index in a twist or a fix, beyond any robot
pytestmark = pytest.mark.usefixtures("no_plausibility_screen")

T0 = 1_600_000_000.0
PATHS = pytest.mark.parametrize("fmt", ["ros1", "mcap"])
IMU_ONLY = {"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate"]}]}}


def write(tmp_path: Path, fmt: str, records, name: str = "b") -> Path:
    return bw.write_bag(bw.bag_path(tmp_path, name, fmt), fmt, records)


def of_type(stream, cls) -> list:
    return [m for m in stream.measurements if isinstance(m, cls)]


def _imu(t: float, i: int, **kw):
    return bw.imu(t, angvel=(0, 0, float(i)), wcov=bw.diag(1, 1, 1), **kw)


# --------------------------------------------------------------------------------------------
# Unset header stamps
# --------------------------------------------------------------------------------------------

@PATHS
def test_unset_stamps_are_rejected_per_message_even_on_a_two_message_topic(tmp_path, fmt):
    """A zero stamp on a topic of two messages (too few for the stamp check) became the
    stream's t0 = 0; one among IMU messages was caught only by the offset check."""
    stamps = {5: 0.0}
    if fmt != "ros1":  # ROS1 stamps are unsigned: no negative one can be written
        stamps[9] = -3.0
    recs = [("/imu", _imu(stamps.get(i, T0 + 0.1 * i), i), T0 + 0.1 * i) for i in range(30)]
    recs += [("/fix", bw.navsatfix(0.0, 42.0, -71.0), T0 + 0.2),
             ("/fix", bw.navsatfix(T0 + 0.6, 42.0, -71.0), T0 + 0.6)]
    recs.sort(key=lambda r: r[2])
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, parse_config({"sensors": {**IMU_ONLY["sensors"],
                                                   "gps": [{"topic": "/fix"}]}}))
    assert [m.yaw_rate for m in of_type(s, GyroYawRate)] == pytest.approx(
        [float(i) for i in range(30) if i not in stamps])
    assert [f.t for f in of_type(s, GpsFix)] == pytest.approx([T0 + 0.6])
    assert s.t0 == pytest.approx(T0, abs=1e-6)
    assert s.rejected == {("/imu", UNSET_STAMP): len(stamps), ("/fix", UNSET_STAMP): 1}


@PATHS
def test_a_topic_whose_every_stamp_is_unset_is_an_error_naming_it(tmp_path, fmt):
    recs = [("/imu", _imu(0.0, i), T0 + 0.1 * i) for i in range(40)]
    recs += [("/odom", bw.odometry(T0 + 0.1 * i, 1.0, 0.0,
                                   twist_cov=bw.diag(0.01, 1, 1, 1, 1, 0.01)), T0 + 0.1 * i)
             for i in range(40)]
    recs.sort(key=lambda r: r[2])
    bag = write(tmp_path, fmt, recs)
    with pytest.raises(BagError) as e:
        read_stream(bag, parse_config({"sensors": {**IMU_ONLY["sensors"],
                                                   "odometry": [{"topic": "/odom"}]}}))
    msg = str(e.value)
    assert str(bag.name) in msg and "/imu" in msg and "sensors.imu[0]" in msg
    assert "all 40 messages" in msg and "zero" in msg


@PATHS
def test_unset_stamps_in_a_topics_warm_up_do_not_poison_its_clock(tmp_path, fmt):
    """The first 10 of 60 IMU stamps zero: the warm-up's median offset was the zero stamps',
    so the 50 good ones were all 'jumps' and the topic an error."""
    recs = [("/imu", _imu(0.0 if i < 10 else T0 + 0.05 * i, i), T0 + 0.05 * i)
            for i in range(60)]
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, parse_config(IMU_ONLY))
    assert [m.yaw_rate for m in s.measurements] == pytest.approx([float(i)
                                                                  for i in range(10, 60)])
    assert s.rejected == {("/imu", UNSET_STAMP): 10}


# --------------------------------------------------------------------------------------------
# NavSatFix: the covariance the estimators invert, Null Island
# --------------------------------------------------------------------------------------------

GOOD_COV = [1.0, 0.3, 0.0, 0.3, 1.2, 0.0, 0.0, 0.0, 4.0]
BAD_COVS = {
    "indefinite": [1.0, 3.0, 0.0, 3.0, 1.0, 0.0, 0.0, 0.0, 4.0],  # eigenvalues 4 and -2
    "asymmetric": [1.0, 0.9, 0.0, -0.9, 1.0, 0.0, 0.0, 0.0, 4.0],
}


@PATHS
@pytest.mark.parametrize("case", sorted(BAD_COVS))
def test_a_fix_whose_covariance_is_not_positive_definite_is_rejected(tmp_path, fmt, case):
    """Positive E/N variances with an indefinite or asymmetric block passed; the EKFs then
    found every innovation covariance singular and used no GPS at all."""
    bad = {2, 5}
    recs = [("/fix", bw.navsatfix(T0 + 0.4 * i, 42.0 + 1e-5 * i, -71.0, cov_type=3,
                                  cov=BAD_COVS[case] if i in bad else GOOD_COV))
            for i in range(8)]
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, parse_config({"sensors": {"gps": [{"topic": "/fix"}]}}))
    fixes = of_type(s, GpsFix)
    assert [round((f.lat - 42.0) / 1e-5) for f in fixes] == [i for i in range(8) if i not in bad]
    for f in fixes:
        assert np.all(np.linalg.eigvalsh(f.cov[:2, :2]) > 0)
    ((topic, reason), n), = s.rejected.items()
    assert topic == "/fix" and n == len(bad)
    assert "not symmetric positive definite" in reason
    assert "sensors.gps[0].noise.horizontal" in reason


@PATHS
def test_a_fix_with_only_its_unused_vertical_variance_negative_is_kept(tmp_path, fmt):
    """The estimators weigh a fix by its east/north block alone."""
    cov = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0]
    recs = [("/fix", bw.navsatfix(T0 + 0.4 * i, 42.0, -71.0, cov_type=2, cov=cov))
            for i in range(3)]
    s = read_stream(write(tmp_path, fmt, recs),
                    parse_config({"sensors": {"gps": [{"topic": "/fix"}]}}))
    assert len(of_type(s, GpsFix)) == 3 and not s.rejected


@PATHS
def test_a_null_island_fix_is_no_fix_and_no_datum(tmp_path, fmt):
    """A receiver's (0, 0) placeholder first became the first_fix datum: every later fix
    5000 km away. Rejected, counted, for the GPS sensor and the ground truth alike."""
    track = [(42.0 + 2e-5 * i, -71.0 + 3e-5 * i) for i in range(6)]
    recs = [("/fix", bw.navsatfix(T0 + 0.4 * i, *((0.0, 0.0) if i in (0, 3) else track[i])))
            for i in range(6)]
    recs += [("/truth", bw.navsatfix(T0 + 0.4 * i + 0.1, *((0.0, 0.0) if i == 0 else track[i])))
             for i in range(6)]
    recs.sort(key=lambda r: r[1].stamp)
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, parse_config({"sensors": {"gps": [{"topic": "/fix"}]},
                                       "ground_truth": {"topic": "/truth"},
                                       "frame": {"datum": "first_fix"}}))
    assert s.datum[:2] == pytest.approx(track[1])
    assert len(of_type(s, GpsFix)) == 4
    assert max(abs(f.enu[0]) + abs(f.enu[1]) for f in of_type(s, GpsFix)) < 100.0
    assert len(s.ground_truth) == 5
    assert s.rejected == {("/fix", NULL_ISLAND): 2, ("/truth", NULL_ISLAND): 1}


# --------------------------------------------------------------------------------------------
# What a run must be told: a topic mostly late, a topic without messages
# --------------------------------------------------------------------------------------------

def _late_gps_bag(tmp_path: Path, fmt: str, late: float, which=range(40)) -> Path:
    """IMU at 20 Hz recorded at its stamps; 40 fixes every 0.5 s, those numbered in ``which``
    recorded ``late`` s after their stamp (the others at it)."""
    recs = [("/imu", _imu(T0 + 0.05 * i, i), T0 + 0.05 * i) for i in range(400)]
    recs += [("/fix", bw.navsatfix(T0 + 0.5 * k, 42.0 + 1e-6 * k, -71.0),
              T0 + 0.5 * k + (late if k in which else 0.0)) for k in range(40)]
    recs.sort(key=lambda r: r[2])
    return write(tmp_path, fmt, recs)


GPS_IMU = {"sensors": {**IMU_ONLY["sensors"], "gps": [{"topic": "/fix"}]}}


@PATHS
def test_a_topic_mostly_dropped_as_late_is_a_warning_with_the_window_it_needs(tmp_path, fmt):
    """Fixes recorded 1.5 s after their stamp: nearly all dropped as late, and only the
    rejected count said so (the command line shows no log)."""
    bag = _late_gps_bag(tmp_path, fmt, 1.5)
    bs = BagStream(bag, parse_config(GPS_IMU))
    fixes = [m for m in bs if isinstance(m, GpsFix)]
    assert bs.late["/fix"] > 0.1 * 40 and len(fixes) == 40 - bs.late["/fix"]
    (w,) = bs.warnings
    assert str(bag) in w and "/fix" in w and f"{bs.late['/fix']} of 40" in w
    need = float(w.split("reorder_window to at least ")[1].split(" s")[0])
    assert 1.4 <= need <= 1.6
    # the window it names keeps every fix
    bs = BagStream(bag, parse_config(GPS_IMU), reorder_window=need)
    assert sum(isinstance(m, GpsFix) for m in bs) == 40
    assert not bs.late and bs.warnings == []


@PATHS
def test_a_few_late_messages_are_counted_without_a_warning(tmp_path, fmt):
    # 2 of 40 recorded 0.9 s late: within the stamp check's 1 s, beyond the 0.5 s window
    bag = _late_gps_bag(tmp_path, fmt, 0.9, which=(10, 30))
    bs = BagStream(bag, parse_config(GPS_IMU))
    assert sum(isinstance(m, GpsFix) for m in bs) == 38 and bs.late["/fix"] == 2
    assert bs.warnings == []


def _bag_with_empty_topics(tmp_path: Path, fmt: str, records, empty: dict[str, str]) -> Path:
    """A bag with ``records`` and a connection without messages for each topic: msgtype of
    ``empty`` (what a recorder leaves for a sensor that never published)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    path = bw.bag_path(tmp_path, "b", fmt)
    store = bw.typestore(fmt)
    if fmt == "ros1":
        writer, serialize = Writer1(path), store.serialize_ros1
    else:
        writer = Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP)
        serialize = store.serialize_cdr
    with writer:
        for topic, msgtype in empty.items():
            writer.add_connection(topic, msgtype, typestore=store)
        conns: dict = {}
        for topic, msg in records:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msg.msgtype, typestore=store)
            writer.write(conns[topic], round(msg.stamp * 1e9),
                         serialize(msg.build(store), msg.msgtype))
    return path


@PATHS
def test_a_configured_topic_without_messages_is_a_warning(tmp_path, fmt):
    recs = [("/imu", _imu(T0 + 0.05 * i, i)) for i in range(40)]
    bag = _bag_with_empty_topics(tmp_path, fmt, recs, {"/fix": bw.NAVSATFIX})
    bs = BagStream(bag, parse_config(GPS_IMU))
    assert sum(isinstance(m, GyroYawRate) for m in bs) == 40
    (w,) = bs.warnings
    assert str(bag) in w and "/fix" in w and "sensors.gps[0]" in w and "no messages" in w


@PATHS
def test_a_bag_where_no_configured_sensor_has_a_message_is_an_error(tmp_path, fmt):
    """empty_conns.bag of the audit ran every estimator on nothing and exited 0."""
    recs = [("/other", _imu(T0 + 0.05 * i, i)) for i in range(5)]
    bag = _bag_with_empty_topics(tmp_path, fmt, recs, {"/fix": bw.NAVSATFIX, "/imu": bw.IMU})
    with pytest.raises(BagError) as e:
        read_stream(bag, parse_config(GPS_IMU))
    msg = str(e.value)
    assert str(bag) in msg and "/fix (sensors.gps[0])" in msg and "/imu (sensors.imu[0])" in msg


# --------------------------------------------------------------------------------------------
# A bad orientation costs the yaw (and the acceleration it levels), not the gyro
# --------------------------------------------------------------------------------------------

def _imu_bag(tmp_path: Path, fmt: str, bad: set, n: int = 30) -> Path:
    """IMU messages whose yaw rate is their index; those in ``bad`` with a zero quaternion."""
    recs = [("/imu", bw.imu(T0 + 0.05 * i, quat=(0, 0, 0, 0) if i in bad else bw.yaw_quat(0.3),
                            angvel=(0, 0, float(i)), accel=(0.5, 0.0, 9.80665),
                            wcov=bw.diag(1e-4, 1e-4, 1e-4), acov=bw.diag(0.01, 0.01, 0.01),
                            ocov=bw.diag(0.01, 0.01, 0.01)))
            for i in range(n)]
    return write(tmp_path, fmt, recs)


def _imu_cfg(**fields):
    return parse_config({"sensors": {"imu": [{"topic": "/imu", **fields}]}})


@PATHS
@pytest.mark.parametrize("gravity", ["orientation", "level"])
def test_a_bad_orientation_keeps_the_gyro_of_its_message(tmp_path, fmt, gravity):
    """imu_quat_zero_some.bag lost 360 yaw rates with its 360 bad quaternions."""
    bad = {4, 5, 17}
    s = read_stream(_imu_bag(tmp_path, fmt, bad), _imu_cfg(accel_gravity=gravity))
    good = [i for i in range(30) if i not in bad]
    assert [m.yaw_rate for m in of_type(s, GyroYawRate)] == pytest.approx(range(30))
    assert [round((m.t - T0) / 0.05) for m in of_type(s, Heading)] == good
    accel = [round((m.t - T0) / 0.05) for m in of_type(s, ForwardAccel)]
    ((topic, reason), n), = s.rejected.items()
    assert topic == "/imu" and n == len(bad)
    assert reason.startswith("orientation is not a finite unit quaternion: yaw not used")
    if gravity == "level":  # the acceleration needs no orientation
        assert accel == list(range(30)) and "linear_acceleration" not in reason
    else:
        assert accel == good
        assert "linear_acceleration" in reason and "sensors.imu[0].accel_gravity" in reason


@PATHS
def test_an_imu_that_never_gives_its_orientation_is_a_warning(tmp_path, fmt):
    """The messages were rejected whole, an error; now their gyro is used, so the compass
    that is never used must still be said on the terminal."""
    bs = BagStream(_imu_bag(tmp_path, fmt, set(range(30))), _imu_cfg())
    assert sum(isinstance(m, GyroYawRate) for m in bs) == 30
    (w,) = bs.warnings
    assert "/imu" in w and "30 of 30 messages" in w and "yaw not used" in w


@PATHS
def test_a_nan_in_the_unused_odometry_speed_keeps_the_yaw_rate(tmp_path, fmt):
    cov = bw.diag(0.01, 1, 1, 1, 1, 0.02)
    recs = [("/odom", bw.odometry(T0 + 0.1 * i, math.nan if i % 3 == 0 else 1.0, 0.1 * i,
                                  twist_cov=cov)) for i in range(12)]
    bag = write(tmp_path, fmt, recs)
    s = read_stream(bag, parse_config({"sensors": {"odometry": [{"topic": "/odom",
                                                                 "use": ["yaw_rate"]}]}}))
    assert [m.yaw_rate for m in s.measurements] == pytest.approx([0.1 * i for i in range(12)])
    assert not s.rejected
    s = read_stream(bag, parse_config({"sensors": {"odometry": [{"topic": "/odom"}]}}))
    assert len(s.measurements) == 8 and sum(s.rejected.values()) == 4
