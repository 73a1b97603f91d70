"""Trajectory metrics against hand-computed cases (ddfuse.evaluation.metrics)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.estimation.runner import Trajectory
from ddfuse.evaluation import metrics


def traj(t, x, y, yaw, cov=None) -> Trajectory:
    t = np.asarray(t, float)
    n = len(t)
    pose = np.column_stack([np.broadcast_to(x, n), np.broadcast_to(y, n),
                            np.broadcast_to(yaw, n)]).astype(float)
    c = np.full((n, 3, 3), np.nan) if cov is None else np.broadcast_to(cov, (n, 3, 3)).copy()
    return Trajectory(t, pose, c)


def test_stats_of_two_values():
    s = metrics.Stats.of([3.0, 4.0])
    assert (s.rmse, s.mean, s.median, s.std, s.min, s.max, s.n) == pytest.approx(
        (math.sqrt(12.5), 3.5, 3.5, 0.5, 3.0, 4.0, 2))
    assert s.scaled(2.0).rmse == pytest.approx(2 * math.sqrt(12.5))
    assert metrics.Stats.of([]).n == 0 and math.isnan(metrics.Stats.of([]).rmse)


def test_associate_nearest_within_max_diff_from_the_shorter():
    # estimate shorter: each estimate stamp takes its nearest reference stamp, if near enough
    i, j = metrics.associate(np.array([0.0, 1.0, 2.04]), np.array([0.02, 1.1, 2.0, 2.05]), 0.05)
    assert i.tolist() == [0, 2] and j.tolist() == [0, 3]
    # an exact tie goes to the earlier sample
    i, j = metrics.associate(np.array([1.0]), np.array([0.9, 1.1]), 0.2)
    assert (i.tolist(), j.tolist()) == ([0], [0])
    # reference shorter: each reference stamp takes its nearest estimate
    i, j = metrics.associate(np.arange(0, 1.0, 0.1), np.array([0.12, 0.5, 3.0]), 0.05)
    assert i.tolist() == [1, 5] and j.tolist() == [0, 1]
    assert [len(a) for a in metrics.associate(np.zeros(0), np.ones(3), 1.0)] == [0, 0]


def _line(n=11):
    k = np.arange(n, dtype=float)
    return traj(k, k, 0.0, 0.0)


def test_ate_constant_offset_and_the_three_alignments():
    ref = _line()
    k = ref.t
    est = traj(k, k + 3.0, 4.0, 0.1)
    a = metrics.ape(est, ref, 0.01)
    assert a.position.rmse == pytest.approx(5.0) and a.position.std == pytest.approx(0.0)
    assert a.heading.mean == pytest.approx(0.1)
    # SE(2): a pure translation is removed; the heading error stays (positions fix rotation 0)
    s = metrics.ape(est, ref, 0.01, "se2")
    assert s.position.max == pytest.approx(0.0, abs=1e-9)
    assert s.heading.mean == pytest.approx(0.1)
    # origin: the first estimate pose is moved onto the first reference pose (yaw included), so
    # the estimate turns by -0.1 rad about its start: the error at step k is k * 2 sin(0.05)
    o = metrics.ape(est, ref, 0.01, "origin")
    np.testing.assert_allclose(o.errors.position, k * 2 * math.sin(0.05), atol=1e-12)
    assert o.heading.max == pytest.approx(0.0, abs=1e-12)


def test_se2_alignment_undoes_a_rigid_motion():
    rng = np.random.default_rng(0)
    xy = rng.normal(0, 10, (50, 2))
    ref = traj(np.arange(50.0), xy[:, 0], xy[:, 1], rng.uniform(-3, 3, 50))
    a = 2.5
    r = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    moved = xy @ r.T + [7.0, -2.0]
    est = traj(ref.t, moved[:, 0], moved[:, 1], metrics.wrap(ref.pose[:, 2] + a))
    assert metrics.ate(est, ref, 0.01).rmse > 5
    s = metrics.ape(est, ref, 0.01, "se2")
    assert s.position.max == pytest.approx(0.0, abs=1e-9)
    assert s.heading.max == pytest.approx(0.0, abs=1e-9)


def test_alignment_errors():
    with pytest.raises(ValueError, match="two distinct"):
        metrics.umeyama_se2(np.ones((5, 2)), np.zeros((5, 2)))
    ref = traj([0.0, 1.0], [0.0, 1.0], 0.0, np.nan)
    with pytest.raises(ValueError, match="heading"):
        metrics.ape(ref, ref, 0.01, "origin")
    with pytest.raises(ValueError, match="alignment must be"):
        metrics.ape(_line(), _line(), 0.01, "sim3")


def test_rpe_time_delta_on_a_scaled_line():
    ref = _line()
    k = ref.t
    est = traj(k, 1.1 * k, 0.0, 0.01 * k)  # 10% too fast, heading drifting 0.01 rad/s
    trans, yaw = metrics.rpe(est, ref, 1.0, 0.01)
    # 1 s pairs (0,1), (1,2), ... (9,10): the estimate's relative motion, in its own rotated
    # frame, against (1, 0): |(1.1 cos 0.01k' ...)| computed below from the definition.
    assert trans.n == 10 and yaw.n == 10
    assert yaw.mean == pytest.approx(0.01)
    a = np.arange(10)
    c, s = np.cos(0.01 * a), np.sin(0.01 * a)
    expect = np.hypot(c * 1.1 - 1.0, -s * 1.1)
    np.testing.assert_allclose(trans.rmse, np.sqrt(np.mean(expect ** 2)))
    # consecutive 2 s pairs: (0,2), (2,4), ..., (8,10); all pairs: (0,2), (1,3), ..., (8,10)
    assert metrics.rpe(est, ref, 2.0, 0.01)[1].n == 5
    assert metrics.rpe(est, ref, 2.0, 0.01, all_pairs=True)[1].n == 9
    assert metrics.rpe(est, ref, 2.0, 0.01)[1].mean == pytest.approx(0.02)


def test_rpe_path_delta_pairs_from_estimate_or_reference():
    ref = _line()
    est = traj(ref.t, 1.1 * ref.t, 0.0, 0.0)
    # path steps: estimate 1.1 m, reference 1 m; delta 2.1 m picks every 2nd estimate sample
    # (2.2 >= 2.1) but every 3rd reference sample (3 >= 2.1).
    a, b = metrics.rpe_pairs(est.t, est.pose[:, :2], 2.1, "m")
    assert a.tolist() == [0, 2, 4, 6, 8] and b.tolist() == [2, 4, 6, 8, 10]
    trans, _ = metrics.rpe(est, ref, 2.1, 0.01, unit="m")
    assert trans.n == 5 and trans.mean == pytest.approx(0.2)
    trans, _ = metrics.rpe(est, ref, 2.1, 0.01, unit="m", pairs_from_reference=True)
    assert trans.n == 3 and trans.mean == pytest.approx(0.3)
    with pytest.raises(ValueError):
        metrics.rpe_pairs(est.t, est.pose[:, :2], 1.0, "frames")


def test_rpe_all_pairs_path_delta_picks_the_first_of_a_stop():
    # cumulative path 0, 1, 1, 1, 3: from sample 0 the path 1 m is reached first at sample 1
    t = np.arange(5.0)
    x = np.array([0.0, 1.0, 1.0, 1.0, 3.0])
    a, b = metrics.rpe_pairs(t, np.column_stack([x, np.zeros(5)]), 1.05, "m", all_pairs=True)
    assert (a[0], b[0]) == (0, 1)


def test_nees_hand_computed_and_without_reference_heading():
    cov = np.diag([1.0, 4.0, 0.01])
    ref = _line(5)
    est = traj(ref.t, ref.t + 1.0, 2.0, 0.1, cov)
    ns = metrics.nees_series(est, ref, 0.01)
    np.testing.assert_allclose(ns.value, 3.0)
    assert ns.dof.tolist() == [3] * 5
    ref_noyaw = traj(ref.t, ref.t, 0.0, np.nan)
    ns = metrics.nees_series(est, ref_noyaw, 0.01)
    np.testing.assert_allclose(ns.value, 2.0)
    assert set(ns.dof.tolist()) == {2}
    # missing and non-positive-definite covariances are left out
    est.cov[1] = np.nan
    est.cov[2] = -np.eye(3)
    assert len(metrics.nees(est, ref, 0.01)) == 3


def test_holdout_errors_and_path_length():
    est = _line()
    e = metrics.holdout_errors(est, np.array([2.5, 20.0]), np.array([[2.5, 3.0], [0.0, 0.0]]))
    assert e.tolist() == pytest.approx([3.0])  # the stamp outside the estimate is dropped
    assert metrics.path_length(np.array([[0, 0], [3, 4], [3, 0]])) == pytest.approx(9.0)


def test_gps_outages_from_gaps_and_the_end():
    t = np.concatenate([np.arange(0, 40, 0.4), np.arange(70, 100, 0.4)])
    out = metrics.gps_outages(t, 130.0)
    assert [(round(o.t0, 1), o.t1) for o in out] == [(39.6, 70.0), (99.6, 130.0)]
    assert metrics.gps_outages(np.arange(0, 100, 0.4), 100.2) == []  # 0.6 s to the end: none
    assert metrics.gps_outages(np.array([1.0]), 100.0) == []


def test_outage_drift_is_error_growth_per_metre():
    ref = traj(np.arange(0, 40, 0.1), np.arange(0, 40, 0.1), 0.0, 0.0)  # 1 m/s along x
    err = np.where(ref.t >= 10, 0.2 + 0.05 * (ref.t - 10), 0.2)  # 5 cm per metre after 10 s
    est = traj(ref.t, ref.pose[:, 0], err, 0.0)
    d = metrics.outage_drift(est, metrics.Outage(10.0, 30.0), ref.t, ref.pose[:, :2], "truth")
    assert d.samples == 200
    assert d.distance_m == pytest.approx(19.9)
    assert d.error_start_m == pytest.approx(0.2) and d.error_end_m == pytest.approx(1.195)
    assert d.drift_per_m == pytest.approx(0.05)
    # standing still: no drift per metre; no reference samples: None
    still = traj(ref.t, 0.0, err, 0.0)
    d = metrics.outage_drift(still, metrics.Outage(10.0, 30.0), ref.t, np.zeros((400, 2)), "x")
    assert d.drift_per_m is None and d.error_max_m == pytest.approx(1.195)
    assert metrics.outage_drift(est, metrics.Outage(50, 60), ref.t, ref.pose[:, :2], "x") is None


def test_nees_in_se2_exponential_coordinates():
    """pose_error='se2': the error is xi = Log(X_est^-1 X_ref) and its covariance A^-1 cov A^-T
    (cov the first-order world image A P_xi A^T): a reference at X_est Exp(xi) scores exactly
    xi^T P_xi^-1 xi, whatever the heading; 'world' scores the plain difference."""
    from scipy.linalg import expm

    rng = np.random.default_rng(2)
    n = 40
    est_pose = np.column_stack([rng.uniform(-9, 9, n), rng.uniform(-9, 9, n),
                                rng.uniform(-math.pi, math.pi, n)])
    xi = rng.normal(0.0, 1.0, (n, 3)) * (1.0, 0.5, 0.8)
    L = np.array([[0.3, 0.0, 0.0], [0.1, 0.2, 0.0], [0.05, -0.02, 0.1]])
    P_xi = L @ L.T
    ref_pose = np.zeros((n, 3))
    cov = np.zeros((n, 3, 3))
    want = np.zeros(n)
    for i in range(n):
        x, y, p = est_pose[i]
        X = np.array([[math.cos(p), -math.sin(p), x], [math.sin(p), math.cos(p), y], [0, 0, 1]])
        r, s, th = xi[i]
        Y = X @ expm(np.array([[0, -th, r], [th, 0, s], [0, 0, 0]]))
        ref_pose[i] = (Y[0, 2], Y[1, 2], math.atan2(Y[1, 0], Y[0, 0]))
        A = np.eye(3)
        A[:2, :2] = [[math.cos(p), -math.sin(p)], [math.sin(p), math.cos(p)]]
        cov[i] = A @ P_xi @ A.T
        want[i] = xi[i] @ np.linalg.solve(P_xi, xi[i])
    t = np.arange(n, dtype=float)
    est = Trajectory(t, est_pose, cov)
    ref = Trajectory(t, ref_pose, np.full((n, 3, 3), np.nan))
    np.testing.assert_allclose(metrics.se2_log_errors(est_pose, ref_pose), xi, atol=1e-9)
    np.testing.assert_allclose(metrics.nees(est, ref, 1e-9, pose_error="se2"), want, rtol=1e-8)
    e = np.column_stack([est_pose[:, :2] - ref_pose[:, :2],
                         metrics.wrap(est_pose[:, 2] - ref_pose[:, 2])])
    world = [e[i] @ np.linalg.solve(cov[i], e[i]) for i in range(n)]
    np.testing.assert_allclose(metrics.nees(est, ref, 1e-9, pose_error="world"), world,
                               rtol=1e-8)
    with pytest.raises(ValueError, match="pose_error must be"):
        metrics.nees(est, ref, 1e-9, pose_error="body")


def _gauss_markov(rng, n: int, dt: float, tau: float) -> np.ndarray:
    """(n, 2) first-order Gauss-Markov samples, unit variance, correlation exp(-lag / tau)."""
    a = math.exp(-dt / tau)
    x = np.zeros((n, 2))
    x[0] = rng.normal(size=2)
    for i in range(1, n):
        x[i] = a * x[i - 1] + math.sqrt(1.0 - a * a) * rng.normal(size=2)
    return x


@pytest.mark.parametrize("tau", [2.0, 5.0, 20.0])
def test_correlation_time_recovers_a_gauss_markov_time_constant(tau):
    # the 1/e time of exp(-lag / tau) is tau; 4000 fixes at 0.4 s give it to ~15 %
    rng = np.random.default_rng(int(tau))
    t = np.arange(4000) * 0.4
    x = _gauss_markov(rng, len(t), 0.4, tau)
    assert metrics.correlation_time(t, x) == pytest.approx(tau, rel=0.2)
    # every 5th fix withheld and a 60 s outage: gaps pair nothing at the wrong lag
    keep = (np.arange(len(t)) % 5 != 4) & ((t < 300.0) | (t >= 360.0))
    assert metrics.correlation_time(t[keep], x[keep]) == pytest.approx(tau, rel=0.2)


def test_correlation_time_white_noise_and_too_few_samples():
    rng = np.random.default_rng(0)
    t = np.arange(1000) * 0.4
    assert metrics.correlation_time(t, rng.normal(size=(1000, 2))) == 0.0
    assert metrics.correlation_time(t[:10], rng.normal(size=(10, 2))) is None
    assert metrics.correlation_time(np.zeros(0), np.zeros((0, 2))) is None
    # a constant offset (a datum error) is not correlation: the residuals are demeaned
    assert metrics.correlation_time(t, rng.normal(size=(1000, 2)) + 5.0) == 0.0
    # a random walk never decorrelates within the lags looked at
    walk = np.cumsum(rng.normal(size=(1000, 2)), axis=0)
    assert metrics.correlation_time(t, walk, max_lag=20.0) is None


def test_interpolation_errors_of_withheld_fixes():
    t = np.arange(10.0)
    xy = np.column_stack([2.0 * t, np.zeros(10)])  # 2 m/s east, exact
    xy[5, 1] = 0.3  # the withheld fix 5 is 0.3 m north of the line
    used = np.arange(10) != 5
    e = metrics.interpolation_errors(t[used], xy[used], t[~used], xy[~used])
    assert e == pytest.approx([0.3])
    # outside the used fixes' span: not scored (no extrapolation)
    assert len(metrics.interpolation_errors(t[1:], xy[1:], t[:1], xy[:1])) == 0


def test_association_error_is_what_nearest_time_pairing_alone_costs():
    # truth at 10 Hz moving east at 0.5 m/s; an exact estimate 0.03 s after each truth sample
    tt = np.arange(0.0, 10.0, 0.1)
    truth = traj(tt, 0.5 * tt, 0.0, 0.0)
    te = tt[:-1] + 0.03
    est = traj(te, 0.5 * te, 0.0, 0.0)
    a = metrics.association_error(est, truth, max_diff=0.05)
    assert a.n == len(te) and a.rmse == pytest.approx(0.015, abs=1e-9)
    # the ATE of that exact track is the same 0.015 m; on the truth's own stamps it is 0
    assert metrics.ape(est, truth, 0.05).position.rmse == pytest.approx(0.015, abs=1e-9)
    assert metrics.association_error(truth, truth, 0.05).rmse == pytest.approx(0.0, abs=1e-12)


def _turning_truth(dt: float = 0.05, n: int = 400):
    """A robot turning at 0.5 rad/s on a 2 m radius, sampled every ``dt`` s."""
    t = dt * np.arange(n)
    yaw = 0.5 * t
    return t, 2.0 * np.sin(yaw), 2.0 * (1.0 - np.cos(yaw)), metrics.wrap(yaw + 0.5 * np.pi)


@pytest.mark.parametrize("pose_error", ["world", "se2"])
def test_nees_takes_the_truth_at_the_estimate_stamp(pose_error):
    """Estimates at 10 Hz half-way between 20 Hz truth samples (the sample bag's stamps): an
    estimate drawn from its own covariance about the true pose at its stamp has NEES ~ 3; the
    nearest truth sample would add 0.025 s of motion (5 cm, 0.7 deg), several sigmas here."""
    tt, x, y, yaw = _turning_truth()
    truth = traj(tt, x, y, yaw)
    te = tt[1:-1:2] + 0.025
    th = 0.5 * te
    true = np.column_stack([2.0 * np.sin(th), 2.0 * (1.0 - np.cos(th)), th + 0.5 * np.pi])
    sd = np.array([0.01, 0.01, 0.004])  # m, m, rad
    rng = np.random.default_rng(3)
    noisy = true + sd * rng.standard_normal(true.shape)
    est = traj(te, noisy[:, 0], noisy[:, 1], metrics.wrap(noisy[:, 2]),
               np.repeat(np.diag(sd**2)[None], len(te), axis=0))
    if pose_error == "se2":  # its covariance is then the world image of the body-frame one
        c, s = np.cos(est.pose[:, 2]), np.sin(est.pose[:, 2])
        a = np.zeros((len(te), 3, 3))
        a[:, 0, 0], a[:, 0, 1], a[:, 1, 0], a[:, 1, 1], a[:, 2, 2] = c, -s, s, c, 1.0
        est.cov[:] = a @ np.diag(sd**2) @ a.transpose(0, 2, 1)
    v = metrics.nees(est, truth, 0.05, pose_error)
    assert len(v) == len(te)
    assert abs(v.mean() - 3.0) < 4 * math.sqrt(6.0 / len(v))  # chi2(3): var 6
    # the nearest sample (what it used to be compared with) is 3 heading sigmas off
    near = metrics.pose_errors(est, truth, 0.05)
    assert np.median(np.abs(near.dyaw)) > 2.5 * sd[2]
    # sparse truth (1 Hz): nothing to interpolate between within 2 max_diff, nearest kept
    sparse = traj(tt[::20], x[::20], y[::20], yaw[::20])
    i, j = metrics.associate(est.t, sparse.t, 0.05)
    assert np.array_equal(metrics.reference_at(sparse, est.t[i], j, 0.05), sparse.pose[j])


@pytest.mark.parametrize("t0", [0.0, 1.7e9])
def test_truth_exactly_at_twice_max_diff_is_interpolated_despite_stamp_rounding(t0):
    """10 Hz truth against max_diff 0.05 s: every gap is 2 max_diff, but float rounding of
    epoch stamps puts many just over it. Each must still be interpolated: a track exactly on
    the truth (1 m/s, 0.03 s after each truth sample) then has zero error, and NEES 0."""
    tt = t0 + np.arange(0, 60, 0.1)
    truth = traj(tt, tt - t0, 0.0, 0.0)
    te = tt[:-1] + 0.03
    est = traj(te, te - t0, 0.0, 0.0, cov=np.diag([1e-4, 1e-4, 1e-4]))
    i, j = metrics.associate(te, tt, 0.05)
    ref = metrics.reference_at(truth, te[i], j, 0.05)
    # the truth's own position at each estimate stamp (an independent computation)
    assert np.abs(ref[:, 0] - (te[i] - t0)).max() < 1e-5
    assert metrics.nees_series(est, truth, 0.05).value.max() < 1e-3


def test_rpe_mean_delta_is_the_pairs_actual_spacing():
    """Consecutive 1 s pairs on a track sampled every 0.4 s are 1.2 s apart (the first sample
    at or past 1 s); on 0.1 s samples 1.0 s. Path pairs of 10 m on 0.4 m steps: 10.0 m."""
    ref = traj(np.arange(0.0, 100.0, 0.05), np.arange(0.0, 100.0, 0.05), 0.0, 0.0)
    for dt, want in ((0.4, 3 * 0.4), (0.1, 1.0)):
        t = np.arange(0.0, 99.0, dt)
        est = traj(t, t, 0.0, 0.0)
        a, b = metrics.rpe_pairs(t, est.pose[:, :2], 1.0)
        assert np.allclose(t[b] - t[a], want)  # independently, from the pairs themselves
        assert metrics.rpe_mean_delta(est, ref, 1.0) == pytest.approx(want)
    t = np.arange(0.0, 99.0, 0.4)
    assert metrics.rpe_mean_delta(traj(t, t, 0.0, 0.0), ref, 10.0, unit="m") == \
        pytest.approx(10.0, abs=0.4)
