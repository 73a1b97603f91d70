"""Errata 000 #40: seed 000 stacks Theta_g and Theta_l from its one magnetometer with a diagonal
R, counting the reading twice. ekf_igvc gives each Heading message one row: Theta_g for a
compass or IMU orientation, Theta_l for a pose yaw; a reading is never fused as both."""

from __future__ import annotations

import pytest
from ddfuse.ekf_baseline.igvc import IgvcEkf
from ddfuse.estimation.config import parse_config_text
from ddfuse.estimation.measurements import Heading, WheelOdometry

CFG = """
sensors:
  odometry: {topic: /odom, use: [v, yaw_rate],
             noise: {v: 0.01, yaw_rate: 0.01}}
  imu: {topic: /imu, use: [yaw], heading_offset: 0.0}
  gps: {topic: /fix, use: [position]}
robot: {track_width: 0.5}
frame: {datum: [45.0, 7.0, 0.0]}
initial_pose: [0.0, 0.0, 0.0]
"""
SIG = 0.001  # rad: well below the start's yaw sigma, so one reading and two differ by 2x


@pytest.mark.parametrize("sensor, source", [("imu", "compass"), ("pose_yaw", "pose")])
def test_one_heading_reading_is_one_row_not_two_errata_000_40(sensor, source):
    """One reading: one logged heading innovation of one row, and the yaw variance falls as
    for one reading of variance SIG^2 (P SIG^2 / (P + SIG^2)), not as for two (P SIG^2 /
    (2 P + SIG^2), what the seed's stacked rows with a diagonal R give)."""
    ekf = IgvcEkf(parse_config_text(CFG))
    ekf.process(WheelOdometry(0.0, 0.0, 0.0, 1e-4, 1e-4, "odometry"))
    p = float(ekf.estimate().pose_cov[2, 2])
    ekf.process(Heading(0.0, 0.001, SIG * SIG, sensor, source))
    rows = [i for i in ekf.innovations if i.kind == "heading"]
    assert len(rows) == 1 and rows[0].residual.shape == (1,) and rows[0].accepted
    post = float(ekf.estimate().pose_cov[2, 2])
    one, two = p * SIG**2 / (p + SIG**2), p * SIG**2 / (2 * p + SIG**2)
    assert one > 1.8 * two
    # Theta_l is psi itself (measured: equal to 1e-3); Theta_g reaches psi through the
    # theta-psi tie, whose small independent part leaves psi 2 % above (9.81e-7 against 9.62e-7;
    # two rows would give 4.9e-7)
    assert post == pytest.approx(one, rel=1e-3 if source == "pose" else 0.05)
