"""The local heading Theta_l of seed 000 (a yaw in the robot's start frame, no north reference):
its config key, one heading row per reading (errata 000 #40), read from a simulated bag, and
the estimate it improves (docs/design/sensors.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.ekf_baseline.igvc import IgvcEkf
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import ConfigError, parse_config_text
from ddfuse.estimation.errors import BagError
from ddfuse.estimation.measurements import Heading
from ddfuse.evaluation.simulate import simulate, write_bag
from sensor_runs import errors, sim_bag, variant

pytest.importorskip("gtsam")

BASE = """
sensors:
  odometry: [{topic: /odom}]
  imu: [{topic: /imu/data, use: [yaw, yaw_rate], noise: {yaw: 0.02, yaw_rate: 0.01}}]
"""


def test_one_orientation_is_one_heading_row_not_theta_g_and_theta_l():
    """The IMU's yaw as the global heading and again as a local heading would fuse one reading
    twice with independent errors (seed 000's Theta_g and Theta_l from one magnetometer):
    refused, naming both sensors and the errata entry. From the IMU's gyro alone it is fine."""
    twice = BASE + "  local_heading: [{topic: /imu/data, name: imu_yaw, noise: {yaw: 0.02}}]\n"
    with pytest.raises(ConfigError, match=r"/imu/data gives a heading to '/imu/data' and again "
                                          r"to 'imu_yaw'.*errata 000 #40"):
        parse_config_text(twice, "h.yaml")
    once = parse_config_text(twice.replace("use: [yaw, yaw_rate]", "use: [yaw_rate]"), "h.yaml")
    (s,) = once.of_kind("local_heading")
    # the start frame's offset to ENU is the robot's unknown start yaw
    assert s.heading_offset == "estimate" and once.heading_sensors() == [s]


def test_an_odometry_pose_beside_its_own_yaw_rate_is_refused():
    """The odometry's pose yaw is its yaw rate integrated: fusing both counts the same
    encoder errors twice (as errata 000 #40 for one magnetometer)."""
    text = BASE.replace("use: [yaw, yaw_rate]", "use: [yaw_rate]") + \
        "  local_heading: [{topic: /odom, name: odom_yaw, noise: {yaw: 0.05}}]\n"
    with pytest.raises(ConfigError, match=r"sensors.local_heading: /odom's pose yaw is the "
                                          r"integral of the yaw rate '/odom' already fuses"):
        parse_config_text(text, "h.yaml")


def test_an_odometry_pose_is_read_as_a_local_heading(tmp_path):
    """The /odom pose's orientation (the encoders' dead-reckoned yaw in the odom frame) as a
    Heading of source 'pose', equal to the simulator's (the odometry fusing only its speed);
    without noise.yaw (an Odometry's pose covariance is not read) every message is dropped:
    the bag error names the key to set."""
    res = simulate("husky", seed=2, duration=20.0)
    bag, _, _ = write_bag(res, tmp_path / "h.bag")
    text = BASE.replace("use: [yaw, yaw_rate]", "use: [yaw_rate]").replace(
        "{topic: /odom}", "{topic: /odom, use: [v]}") + \
        "  local_heading: [{topic: /odom, name: odom_yaw, noise: {yaw: 0.05}}]\n"
    st = read_stream(bag, parse_config_text(text, "h.yaml"))
    h = [m for m in st.measurements if isinstance(m, Heading) and m.sensor == "odom_yaw"]
    assert len(h) == len(res.encoders.t) and {m.source for m in h} == {"pose"}
    assert np.allclose([m.yaw for m in h], res.encoders.yaw, atol=1e-9)
    with pytest.raises(BagError, match=r"topic /odom \(sensors.local_heading\[0\]\): all "
                                       r"\d+ messages rejected: .*set sensors.local_heading"
                                       r"\[0\].noise.yaw"):
        read_stream(bag, parse_config_text(text.replace(", noise: {yaw: 0.05}", ""), "h.yaml"))


def test_ekf_igvc_takes_a_local_heading_as_theta_l_on_psi(tmp_path):
    """In ekf_igvc the local heading is seed 000's Theta_l row, psi + offset, with its own
    offset state (hoff:<name>), not the compass row on theta."""
    res = simulate("husky", seed=1, duration=30.0)
    bag, cfg_path, _ = write_bag(res, tmp_path / "h.bag")
    text = cfg_path.read_text()
    cfg = parse_config_text(text, str(cfg_path))
    cfg.sensors = [s for s in cfg.sensors if s.kind != "imu"]
    loc = parse_config_text("""
sensors:
  local_heading: [{topic: /imu/data, name: imu_yaw, noise: {yaw: 0.02}}]
""", "l.yaml").sensors
    cfg.sensors += loc
    ekf = IgvcEkf(cfg, datum=cfg.datum)
    assert "hoff:imu_yaw" in ekf.state_names


@pytest.mark.slow
def test_a_local_heading_improves_the_estimate_without_a_gyro(tmp_path):
    """The same husky bags (90 s, three seeds), odometry and GPS, with and without the IMU's
    orientation as a local heading (its yaw offset unknown, estimated): the heading RMSE of
    the unicycle EKF, ekf_igvc and the smoother falls by at least a fifth on every seed, and
    the position RMSE with it. Measured (seeds 0, 1, 2): ekf 4.2/2.6/4.4 -> 2.0/1.7/1.9 deg,
    ekf_igvc 5.4/4.4/7.3 -> 2.1/1.3/2.3, smoother 4.3/2.8/4.1 -> 2.1/1.9/2.0; positions
    0.21-0.48 m -> 0.20-0.33 m. With the IMU's gyro present too the gain is small (3.4 -> 3.3
    deg): a local heading carries what a gyro does, heading changes, not the start heading."""
    names = ["ekf", "ekf_igvc", "smoother"]
    for seed in (0, 1, 2):
        bag, cfg = sim_bag(tmp_path, "husky", seed, 90.0)
        base = variant(cfg, imu=None)
        a = errors(bag, base, names)
        b = errors(bag, variant(base, local_heading=[{"topic": "/imu/data", "name": "imu_yaw",
                                                      "noise": {"yaw": 0.02}}]), names)
        for name in names:
            assert b[name].yaw_rmse < 0.8 * a[name].yaw_rmse, (seed, name, a[name], b[name])
            assert b[name].pos_rmse < a[name].pos_rmse, (seed, name, a[name], b[name])
            assert b[name].n > 800 and math.isfinite(b[name].nees)
