"""initial_pose: ground_truth starts the estimators at the truth pose of the first measurement's
stamp, interpolated between the truth samples around it (a bag that begins in motion)."""

from __future__ import annotations

import math

import bagwriter as bw
import numpy as np
import pytest
from ddfuse.estimation.bags import BagStream
from ddfuse.estimation.config import parse_config
from ddfuse.estimation.measurements import GroundTruthPose, Stream, WheelOdometry, truth_at_start
from ddfuse.estimation.runner import initial_pose

T0 = 1_600_000_000.0


def test_the_start_pose_is_interpolated_between_dense_truth_samples():
    t = T0 + 0.05 * np.arange(10)
    pose = np.column_stack([1.0 * (t - T0), np.zeros(10), np.full(10, 3.1)])
    pose[3:, 2] = -3.1  # the heading crosses +-pi between samples 2 and 3
    g = truth_at_start(t, pose, T0 + 0.125)  # between samples 2 and 3
    assert (g.t, g.x, g.y) == pytest.approx((T0 + 0.125, 0.125, 0.0))
    assert abs(g.yaw) == pytest.approx(math.pi, abs=1e-9)  # the shorter arc, not 0
    # on a sample, before the first, after the last, or across a gap: the sample itself
    assert truth_at_start(t, pose, T0 + 0.1).x == pytest.approx(0.1)
    assert truth_at_start(t, pose, T0 - 1.0).x == 0.0
    assert truth_at_start(t, pose, T0 + 9.0).x == pytest.approx(0.45)
    sparse = t[::6]
    assert truth_at_start(sparse, pose[::6], T0 + 0.125).x == pytest.approx(0.3)
    assert truth_at_start(np.zeros(0), np.zeros((0, 3)), T0) is None


def test_initial_pose_of_a_stream_and_of_a_bag_that_begins_in_motion(tmp_path):
    """Truth at 20 Hz from T0, the robot at 2 m/s; odometry from T0 + 0.03 s: the start is 6 cm
    along, not the 10 cm of the next truth sample."""
    recs = [("/ground_truth", bw.pose_stamped(T0 + 0.05 * i, 2.0 * 0.05 * i, 0.0, 0.0))
            for i in range(40)]
    recs += [("/odom", bw.odometry(T0 + 0.03 + 0.1 * i, 2.0)) for i in range(15)]
    recs.sort(key=lambda r: r[1].stamp)
    bag = bw.write_bag(bw.bag_path(tmp_path, "moving", "ros1"), "ros1", recs)
    cfg = parse_config({"sensors": {"odometry": [{"topic": "/odom", "use": ["v"],
                                                  "noise": {"v": 0.1}}]},
                        "ground_truth": {"topic": "/ground_truth"},
                        "initial_pose": "ground_truth"})
    bs = BagStream(bag, cfg).prime()
    assert bs.t0 == pytest.approx(T0 + 0.03)
    assert initial_pose(cfg.initial_pose, bs) == pytest.approx((0.06, 0.0, 0.0))
    truth = [GroundTruthPose(T0 + 0.05 * i, 0.1 * i, 0.0, 0.0) for i in range(40)]
    stream = Stream([WheelOdometry(T0 + 0.03, 2.0, None, 0.01, 0.0)], ground_truth=truth,
                    t0=T0 + 0.03)
    assert initial_pose("ground_truth", stream) == pytest.approx((0.06, 0.0, 0.0))
