"""The accelerometer on a bag: the husky scenario's IMU writes the specific force of its motion
(forward acceleration, centripetal v w, gravity), the reader removes gravity with the message's
own orientation (errata 000 #24, tests/test_bags_accel_gravity.py), and ekf_igvc, the
estimator that models an acceleration state (seed 000's a), is better with it
(docs/design/sensors.md)."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import parse_config_text
from ddfuse.estimation.measurements import ForwardAccel
from ddfuse.evaluation.simulate import simulate, write_bag
from sensor_runs import errors, sim_bag


def test_the_husky_accelerometer_reads_the_true_forward_acceleration(tmp_path):
    """ForwardAccel from the bag against the simulator's true dv/dt at the same instants:
    unbiased (within 4 standard errors) and its spread what the stated variance says (the
    accelerometer's 0.05 m/s^2 and the orientation's 5 mrad pitch noise times g, which the
    gravity removal carries in): within 15 %."""
    res = simulate("husky", seed=4, duration=60.0)
    bag, cfg_path, _ = write_bag(res, tmp_path / "a.bag")
    st = read_stream(bag, parse_config_text(cfg_path.read_text(), str(cfg_path)))
    acc = [m for m in st.measurements if isinstance(m, ForwardAccel)]
    assert len(acc) == len(res.imu.t)
    t0 = res.t0
    true = np.interp([m.t - t0 for m in acc], res.imu.t, res.imu.true_accel[:, 0])
    e = np.array([m.accel for m in acc]) - true
    sd = math.sqrt(np.mean([m.var for m in acc]))
    assert abs(e.mean()) < 4.0 * e.std() / math.sqrt(len(e))
    assert 0.85 < e.std() / sd < 1.15, (e.std(), sd)
    assert np.ptp(true) > 0.5  # the drive accelerates and brakes: there is something to read


@pytest.mark.slow
def test_the_accelerometer_improves_ekf_igvc(tmp_path):
    """The same husky bags (90 s, four seeds), ekf_igvc with the IMU's use [yaw, yaw_rate,
    accel] against [yaw, yaw_rate]: the position RMSE over the seeds falls by more than 15 %,
    on at least three of four seeds, and the mean pose NEES with it. Measured (seeds 0-3):
    0.177/0.172/0.185/0.090 m -> 0.089/0.130/0.145/0.109 m (seed 3 worse), NEES 3.8/3.8/4.9/1.9
    -> 2.3/2.8/3.6/2.3; on seeds 4-11 all eight improve, 0.156 -> 0.114 m on average. The
    heading is unchanged (0.19-0.33 deg either way): the acceleration informs the speed."""
    without, with_ = [], []
    for seed in range(4):
        bag, cfg = sim_bag(tmp_path, "husky", seed, 90.0)
        no = copy.deepcopy(cfg)
        no["sensors"]["imu"][0]["use"] = ["yaw", "yaw_rate"]
        without.append(errors(bag, no, ["ekf_igvc"])["ekf_igvc"])
        with_.append(errors(bag, cfg, ["ekf_igvc"])["ekf_igvc"])
    assert sum(b.pos_rmse for b in with_) < 0.85 * sum(a.pos_rmse for a in without)
    assert sum(b.pos_rmse < a.pos_rmse for a, b in zip(without, with_, strict=True)) >= 3
    assert sum(b.nees for b in with_) < sum(a.nees for a in without)
