"""A gate lock-out recovery widens the EKF's covariance but not its odometry scale states (as
the smoother's, ``smoother.gps.GpsFusion.widen``): widened, the scales took up a GPS jump and the
filter broke down."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.ekf_baseline.kalman import KalmanCore
from ddfuse.ekf_baseline.unicycle import UnicycleEkf
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.estimator import EstimatorLog
from ddfuse.estimation.runner import initial_pose, run
from ddfuse.evaluation.simulate import simulate, write_bag


def _core() -> KalmanCore:
    rng = np.random.default_rng(3)
    A = rng.standard_normal((5, 5))
    P = A @ A.T * 0.01 + np.eye(5) * 1e-3
    kf = KalmanCore(np.zeros(5), P, EstimatorLog())
    kf.held_in_recovery = (3, 4)
    for kind in ("position", "x"):  # a streak of rejections, as the gate leaves it
        kf._streak[("gps", kind)] = [5, -2.0, 0]
    return kf


def test_the_held_states_keep_their_covariance_and_the_innovation_becomes_ordinary():
    kf = _core()
    P0 = kf.P.copy()
    H = np.zeros((2, 5))
    H[0, 0] = H[1, 1] = 1.0  # a position fix: it observes none of the held states
    R = np.eye(2) * 0.01
    y = np.array([3.0, -2.0])
    kf._recover(0.0, "gps", "position", y, H, R)
    P = kf.P
    np.testing.assert_array_equal(P[3:, 3:], P0[3:, 3:])
    np.testing.assert_array_equal(P[:3, 3:], P0[:3, 3:])
    alpha = kf.recoveries[-1][2]
    assert alpha > 10.0
    np.testing.assert_allclose(P[:3, :3], alpha * P0[:3, :3], rtol=1e-12)
    assert np.linalg.eigvalsh(P).min() > 0.0
    nis = y @ np.linalg.solve(H @ P @ H.T + R, y)
    assert nis == pytest.approx(2.0, rel=1e-6)


def test_without_held_states_the_whole_covariance_is_scaled():
    kf = _core()
    kf.held_in_recovery = ()
    P0 = kf.P.copy()
    H = np.zeros((1, 5))
    H[0, 0] = 1.0
    kf._recover(0.0, "gps", "x", np.array([2.0]), H, np.eye(1) * 0.01)
    np.testing.assert_allclose(kf.P, kf.recoveries[-1][2] * P0, rtol=1e-12)


def test_a_gps_recovery_leaves_the_yaw_rate_scale_where_the_odometry_puts_it(tmp_path):
    """husky-multipath seed 14: the GPS error starts ~4 m off, the filter locks the GPS out at
    7.9 s and recovers with x6.6e3. When that widened k_w too, k_w went to -0.9 by 10 s and
    -5.7 by 30 s; every turn then locked the odometry's yaw rate out, until P broke at 209 s."""
    sim = simulate("husky-multipath", seed=14, duration=60.0)
    bag, cfg_path, _ = write_bag(sim, tmp_path / "mp14.bag")
    cfg = load_config(cfg_path)
    stream = read_stream(bag, cfg)
    ekf = UnicycleEkf(cfg, initial_pose=initial_pose(cfg.initial_pose, stream))
    result = run(stream, {"ekf": ekf})
    assert result.runs["ekf"].error is None
    assert any("gps" in t and "lock-out" in t for t in ekf.log.messages)  # the case is hit
    e = ekf.estimate()
    k = e.state_names.index("k_w")
    g = sim.scenario.true_geometry
    n = sim.scenario.nominal_geometry
    true_kw = (g.wheel_radius / g.track_width) / (n.wheel_radius / n.track_width)
    assert abs(e.state[k] - true_kw) < 4.0 * math.sqrt(e.state_cov[k, k]) + 0.01
    assert not any("yaw_rate: gate lock-out" in t for t in ekf.log.messages)
