"""Wheel+gyro preintegration: increment, covariance, bias Jacobian and the factor."""

import math

import gtsam
import numpy as np
import pytest
from ddfuse.factors.gps import gps_factor
from ddfuse.factors.heading import heading_factor
from ddfuse.factors.kinematics import se2_step
from ddfuse.factors.preintegration import WheelGyroPreintegration, preintegrated_factor
from ddfuse.factors.state import DIM, make_state

VAR_V = 0.05**2
VAR_W = 0.01**2


def samples(n=100, dt=0.01, bias=0.0, w_scale=0.5, seed=0):
    """Smoothly varying (v, w) samples; gyro readings include ``bias``."""
    rng = np.random.default_rng(seed)
    ph = rng.uniform(0, 6)
    out = []
    for k in range(n):
        v = 1.0 + 0.3 * math.sin(0.05 * k + ph)
        w = w_scale * math.cos(0.03 * k + ph)
        out.append((dt * (1.0 + 0.2 * rng.random()), v, w + bias, VAR_V, VAR_W))
    return out


def integrate(sams, bg_lin=0.0):
    p = WheelGyroPreintegration(bg_lin)
    for s in sams:
        p.integrate(*s)
    return p


@pytest.mark.parametrize("w_scale", [0.0, 1e-9, 0.5, 3.0])
def test_equals_stepping_se2_step(w_scale):
    sams = samples(w_scale=w_scale, bias=0.02)
    p = integrate(sams, bg_lin=0.02)
    x = y = psi = 0.0
    for dt, v, wg, _, _ in sams:
        x, y, psi = se2_step(x, y, psi, v, wg - 0.02, dt)
    assert p.n == len(sams)
    assert p.dt_total == pytest.approx(sum(s[0] for s in sams))
    assert max(abs(a - b) for a, b in zip(p.delta, (x, y, psi), strict=True)) < 1e-12


def test_predict_composes_with_keyframe_pose():
    sams = samples(bias=0.01)
    p = integrate(sams, bg_lin=0.01)
    si = make_state(3.0, -1.0, 3.0, 0.0, 0.0, 0.01, 0.2)
    x, y, psi = si[0], si[1], si[2]
    for dt, v, wg, _, _ in sams:
        x, y, psi = se2_step(x, y, psi, v, wg - 0.01, dt)
    sj = p.predict(si)
    np.testing.assert_allclose(sj[:3], [x, y, psi], atol=1e-12)
    assert sj[3] == sams[-1][1] and sj[4] == pytest.approx(sams[-1][2] - 0.01)
    assert sj[5] == 0.01 and sj[6] == 0.2
    # the factor is zero at the prediction
    f = preintegrated_factor(1, 2, p)
    v = gtsam.Values()
    v.insert(1, si)
    v.insert(2, sj)
    assert np.max(np.abs(f.unwhitenedError(v))) < 1e-12


def test_bias_jacobian_finite_differences():
    sams = samples(n=200, w_scale=1.0)
    b0, h = 0.03, 1e-6
    p = integrate(sams, b0)
    num = (np.array(integrate(sams, b0 + h).delta) - np.array(integrate(sams, b0 - h).delta)) / (
        2 * h
    )
    np.testing.assert_allclose(p.bias_jacobian, num, atol=1e-7)
    assert p.bias_jacobian[2] == pytest.approx(-p.dt_total)


def test_first_order_bias_correction():
    sams = samples(n=100, w_scale=0.8)
    p = integrate(sams, 0.0)
    for db in (1e-3, 1e-2):
        exact = np.array(integrate(sams, db).delta)
        approx = np.array(p.delta_at(db))
        assert np.max(np.abs(approx - exact)) < 2.0 * db * db  # second order remainder
        assert np.max(np.abs(np.array(p.delta) - exact)) > 0.1 * db  # and the correction matters


def test_reintegrate_matches_fresh():
    sams = samples()
    p = integrate(sams, 0.0)
    p.reintegrate(0.05)
    q = integrate(sams, 0.05)
    assert p.delta == q.delta and p.bias_jacobian == q.bias_jacobian
    np.testing.assert_array_equal(p.covariance, q.covariance)


def test_covariance_matches_linearised_propagation():
    """cov = sum_k G_k var_k G_k^T with G_k = d delta / d sample_k by central differences."""
    sams = samples(n=60, w_scale=1.5)
    p = integrate(sams)
    h = 1e-6
    cov = np.zeros((3, 3))
    for k in range(len(sams)):
        for idx, var in ((1, VAR_V), (2, VAR_W)):
            sp = [list(s) for s in sams]
            sm = [list(s) for s in sams]
            sp[k][idx] += h
            sm[k][idx] -= h
            g = (np.array(integrate(sp).delta) - np.array(integrate(sm).delta)) / (2 * h)
            cov += np.outer(g, g) * var
    np.testing.assert_allclose(p.covariance, cov, rtol=1e-6, atol=1e-14)
    assert np.all(np.linalg.eigvalsh(p.covariance) > 0)


def test_covariance_monte_carlo():
    """Sample noise propagated through the exact integration agrees with the covariance."""
    rng = np.random.default_rng(1)
    sams = samples(n=50, w_scale=1.0)
    p = integrate(sams)
    deltas = []
    for _ in range(2000):
        q = WheelGyroPreintegration(keep_samples=False)
        for dt, v, w, vv, vw in sams:
            q.integrate(dt, v + rng.normal() * 0.05 * 4, w + rng.normal() * 0.01 * 4, vv, vw)
        deltas.append(q.delta)
    emp = np.cov(np.array(deltas).T) / 16.0  # noise was 4 sigma to dominate nonlinearity
    np.testing.assert_allclose(np.diag(emp), np.diag(p.covariance), rtol=0.15)


def test_factor_rows_and_noise():
    sams = samples(bias=0.02)
    p = integrate(sams, 0.0)
    f = preintegrated_factor(1, 2, p, gyro_bias_rw=1e-3, heading_offset_rw=2e-3)
    cov = f.noiseModel().covariance()
    t = p.dt_total
    assert cov[5, 5] == pytest.approx(1e-6 * t) and cov[6, 6] == pytest.approx(4e-6 * t)
    assert cov[3, 3] == VAR_V and cov[4, 4] == VAR_W
    extra = np.diag([1e-4 * t, 1e-4 * t, 1e-6 * t])
    np.testing.assert_allclose(cov[:3, :3] - p.covariance, extra, rtol=1e-9, atol=1e-15)
    # the true bias gives zero pose residual only through the bias Jacobian
    si = make_state(0, 0, 0.3, 0, 0, 0.02, 0.0)
    sj = integrate(sams, 0.02).predict(si)
    v = gtsam.Values()
    v.insert(1, si)
    v.insert(2, sj)
    e = f.unwhitenedError(v)
    corrected = np.max(np.abs(e[:3]))  # second-order remainder of a 0.02 rad/s bias
    e_nocorr = preintegrated_factor(1, 2, p, noise=gtsam.noiseModel.Unit.Create(9))
    v2 = gtsam.Values()
    v2.insert(1, make_state(0, 0, 0.3, 0, 0, 0.0, 0.0))
    v2.insert(2, sj)
    uncorrected = np.max(np.abs(e_nocorr.unwhitenedError(v2)[:3]))
    assert uncorrected > 1e-2 and corrected < 0.02 * uncorrected
    assert e[4] == pytest.approx(0.0, abs=1e-15)  # w_j + bg_j - last gyro reading
    with pytest.raises(ValueError):
        preintegrated_factor(1, 2, WheelGyroPreintegration())


def test_pose2_between_matches_factor_to_first_order():
    sams = samples(w_scale=1.0)
    p = integrate(sams)
    delta, cov = p.pose2_between()
    si = make_state(2.0, 1.0, -2.9)
    sj = p.predict(si)
    pi = gtsam.Pose2(si[0], si[1], si[2])
    between = gtsam.BetweenFactorPose2(1, 2, delta, gtsam.noiseModel.Gaussian.Covariance(cov))
    f = preintegrated_factor(1, 2, p, noise=gtsam.noiseModel.Unit.Create(9))
    dp = np.array([1e-5, -2e-5, 3e-5])
    vb = gtsam.Values()
    vb.insert(1, pi)
    vb.insert(2, gtsam.Pose2(sj[0] + dp[0], sj[1] + dp[1], sj[2] + dp[2]))
    vf = gtsam.Values()
    vf.insert(1, si)
    vf.insert(2, sj + np.concatenate([dp, np.zeros(6)]))
    xi = between.unwhitenedError(vb)
    e = f.unwhitenedError(vf)[:3]
    c, s = math.cos(delta.theta()), math.sin(delta.theta())
    rot = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1.0]])
    np.testing.assert_allclose(xi, rot @ e, atol=1e-9)
    # hence equal Mahalanobis distances
    m1 = xi @ np.linalg.solve(cov, xi)
    m2 = e @ np.linalg.solve(p.covariance, e)
    assert m1 == pytest.approx(m2, rel=1e-3)


def test_graph_with_preintegration_estimates_gyro_bias():
    """4 keyframes of preintegrated odometry (gyro bias 0.02 rad/s, integrated with bg_lin = 0)
    plus GPS and heading: LM recovers poses and the bias."""
    bias = 0.02
    keys = [0, 1, 2, 3]
    graph = gtsam.NonlinearFactorGraph()
    truth = [make_state(0.0, 0.0, 2.5, 1.0, 0.0, bias, 0.1)]
    init = gtsam.Values()
    for k in keys[1:]:
        sams = samples(n=100, dt=0.01, bias=bias, w_scale=0.7, seed=k)
        exact = integrate(sams, bias)
        truth.append(exact.predict(truth[-1]))
        graph.add(preintegrated_factor(k - 1, k, integrate(sams, 0.0)))
    for k, s in enumerate(truth):
        graph.add(gps_factor(k, s[0], s[1], 0.05))
        graph.add(heading_factor(k, math.remainder(s[2] + s[6], 2 * math.pi), 0.01))
        init.insert(k, s + np.array([0.3, -0.2, 0.1, 0.1, 0.05, -0.02, 0.05, 0.0, 0.0]))
    prior = np.array([1e3, 1e3, 1e3, 1e3, 1e3, 1.0, 1e-3, 1e-4, 1e-4])  # hoff, scales fixed
    graph.add(gtsam.PriorFactorVector(0, truth[0], gtsam.noiseModel.Diagonal.Sigmas(prior)))
    result = gtsam.LevenbergMarquardtOptimizer(graph, init).optimize()
    for k, s in enumerate(truth):
        est = result.atVector(k)
        np.testing.assert_allclose(est[:2], s[:2], atol=1e-3)
        assert abs(math.remainder(est[2] - s[2], 2 * math.pi)) < 1e-3
        assert est[5] == pytest.approx(bias, abs=2e-3)
    assert result.atVector(3).shape == (DIM,)


def _integrate_gain(sams, bg_lin, gain):
    p = WheelGyroPreintegration(bg_lin)
    for s in sams:
        p.integrate(*s, gain=gain)
    return p


@pytest.mark.parametrize("gain", [0.0, 0.35, 1.0])
def test_bias_gain_scales_bias_dependence(gain):
    """A fused yaw rate carries a share ``gain`` of the gyro bias: the increment depends on bg
    through w - gain * bg (finite differences), and gain 0 (odometry) makes it bias-free."""
    sams = samples(n=150, w_scale=1.0)
    b0, h = 0.03, 1e-6
    p = _integrate_gain(sams, b0, gain)
    num = (np.array(_integrate_gain(sams, b0 + h, gain).delta)
           - np.array(_integrate_gain(sams, b0 - h, gain).delta)) / (2 * h)
    np.testing.assert_allclose(p.bias_jacobian, num, atol=1e-7)
    assert p.bias_jacobian[2] == pytest.approx(-gain * p.dt_total)
    # the same rates with the bias share removed up front integrate to the same increment
    q = integrate([(dt, v, w - gain * b0, vv, vw) for dt, v, w, vv, vw in sams], 0.0)
    np.testing.assert_allclose(p.delta, q.delta, atol=1e-12)
    # the factor is zero at the prediction, whose w has the bias share removed
    si = make_state(1.0, 2.0, 0.4, 0.0, 0.0, b0, 0.0)
    sj = p.predict(si)
    assert sj[4] == pytest.approx(sams[-1][2] - gain * b0)
    f = preintegrated_factor(1, 2, p, noise=gtsam.noiseModel.Unit.Create(9))
    v = gtsam.Values()
    v.insert(1, si)
    v.insert(2, sj)
    assert np.max(np.abs(f.unwhitenedError(v))) < 1e-12


def _integrate_split(sams, bg_lin=0.0, kv_lin=1.0, kw_lin=1.0, share=0.4):
    """The samples' yaw rate split into a gyro part (gain 1 - share) and an odometry part."""
    p = WheelGyroPreintegration(bg_lin, kv_lin=kv_lin, kw_lin=kw_lin)
    for dt, v, w, var_v, var_w in sams:
        p.integrate(dt, v, (1.0 - share) * w, var_v, var_w, gain=1.0 - share, w_odo=share * w)
    return p


@pytest.mark.parametrize("which", ["kv", "kw"])
def test_scale_jacobians_finite_differences(which):
    """d delta / d k_v and d k_w of the running integration equal central differences of a
    re-integration at shifted linearisation points."""
    sams = samples(w_scale=1.0)
    h = 1e-6
    base = dict(bg_lin=0.01, kv_lin=0.98, kw_lin=1.03)
    up, dn = dict(base), dict(base)
    up[f"{which}_lin"] += h
    dn[f"{which}_lin"] -= h
    num = (np.array(_integrate_split(sams, **up).delta)
           - np.array(_integrate_split(sams, **dn).delta)) / (2 * h)
    jv, jw = _integrate_split(sams, **base).scale_jacobians
    np.testing.assert_allclose(jv if which == "kv" else jw, num, atol=1e-6)
    assert num[2] == pytest.approx(0.0, abs=1e-9) if which == "kv" else abs(num[2]) > 1e-3


def test_delta_at_scales_first_order():
    """delta_at(bg, kv, kw) with the scale Jacobians predicts a re-integration at the new scales
    to second order in the change."""
    sams = samples(w_scale=1.0)
    p = _integrate_split(sams)
    d = 1e-3
    exact = np.array(_integrate_split(sams, kv_lin=1 + d, kw_lin=1 - d).delta)
    first = np.array(p.delta_at(0.0, 1 + d, 1 - d))
    zeroth = np.array(p.delta)
    assert np.max(np.abs(first - exact)) < 0.05 * np.max(np.abs(zeroth - exact))


def test_graph_with_preintegration_estimates_odometry_scales():
    """Odometry that under-reports speed by 3 % and yaw rate by 5 %, preintegrated at scales 1,
    with GPS and a heading sensor: LM recovers k_v and k_w."""
    kv, kw = 1.03, 1.05
    keys = range(8)
    graph = gtsam.NonlinearFactorGraph()
    truth = [make_state(0.0, 0.0, 0.3, 1.0, 0.0, 0.0, 0.0, kv, kw)]
    init = gtsam.Values()
    for k in keys[1:]:
        sams = [(dt, v / kv, w / kw, var_v, var_w)
                for dt, v, w, var_v, var_w in samples(n=100, dt=0.01, w_scale=0.7, seed=k)]
        truth.append(_integrate_split(sams, kv_lin=kv, kw_lin=kw, share=1.0).predict(truth[-1]))
        graph.add(preintegrated_factor(k - 1, k, _integrate_split(sams, share=1.0)))
    for k, s in enumerate(truth):
        graph.add(gps_factor(k, s[0], s[1], 0.01))
        graph.add(heading_factor(k, math.remainder(s[2] + s[6], 2 * math.pi), 1e-3))
        init.insert(k, s + np.array([0.1, -0.1, 0.02, 0.1, 0.05, 0.0, 0.0, -0.03, -0.05]))
    prior = np.array([1e-3, 1e-3, 1e-3, 1e3, 1e3, 1e-4, 1e-4, 1.0, 1.0])  # scales free
    graph.add(gtsam.PriorFactorVector(0, truth[0], gtsam.noiseModel.Diagonal.Sigmas(prior)))
    result = gtsam.LevenbergMarquardtOptimizer(graph, init).optimize()
    est = result.atVector(7)
    assert est[7] == pytest.approx(kv, abs=2e-3)
    assert est[8] == pytest.approx(kw, abs=2e-3)
