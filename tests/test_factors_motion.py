"""Motion factor: residual values, noise model, and a tiny graph optimised with LM."""

import math

import gtsam
import numpy as np
import pytest
from ddfuse.factors.gps import gps_factor
from ddfuse.factors.kinematics import se2_step
from ddfuse.factors.motion import MotionNoise, motion_error, motion_factor
from ddfuse.factors.state import DIM, make_state


def truth_states(n, dt, v=1.0, w=0.2, x0=(0.0, 0.0, 0.0), bg=0.01, hoff=-0.05):
    states = [make_state(*x0, v, w, bg, hoff)]
    for _ in range(n - 1):
        s = states[-1]
        x, y, p = se2_step(s[0], s[1], s[2], v, w, dt)
        states.append(make_state(x, y, p, v, w, bg, hoff))
    return states


def values_of(states, keys=None):
    v = gtsam.Values()
    for i, s in enumerate(states):
        v.insert(i if keys is None else keys[i], np.asarray(s, dtype=float))
    return v


@pytest.mark.parametrize("twist", ["mean", "start"])
@pytest.mark.parametrize("w", [0.0, 1e-9, 1e-5, 0.9, -2.0])
@pytest.mark.parametrize("psi0", [math.pi - 0.05, -math.pi + 0.01, 0.3])
def test_zero_residual_on_constant_twist(twist, w, psi0):
    states = truth_states(2, 0.5, v=1.7, w=w, x0=(3.0, -4.0, psi0))
    f = motion_factor(0, 1, 0.5, gtsam.noiseModel.Unit.Create(DIM), twist=twist)
    e = f.unwhitenedError(values_of(states))
    assert e.shape == (DIM,) and e.dtype == np.float64
    assert np.max(np.abs(e)) < 1e-13


def test_residual_components_and_wrap():
    si = make_state(1.0, 2.0, math.pi - 0.01, 1.0, 0.0, 0.01, math.pi - 0.02)
    sj = make_state(1.0, 2.5, -math.pi + 0.01, 1.5, 0.3, 0.015, -math.pi + 0.02)
    e = motion_error(si, sj, 0.1, twist="start")
    # p_j - p_i = (0, 0.5) world; psi_i ~ pi so body frame is rotated by ~180 deg
    c, s = math.cos(si[2]), math.sin(si[2])
    assert e[0] == pytest.approx(s * 0.5 - 0.1)
    assert e[1] == pytest.approx(c * 0.5 - 0.0)
    assert e[2] == pytest.approx(0.02)  # wrapped, not -2 pi + 0.02
    assert e[3:6] == pytest.approx((0.5, 0.3, 0.005))
    assert e[6] == pytest.approx(0.04)
    f = motion_factor(0, 1, 0.1, gtsam.noiseModel.Unit.Create(DIM), twist="start")
    np.testing.assert_allclose(f.unwhitenedError(values_of([si, sj])), e, atol=1e-14)


def test_mean_twist_is_second_order_for_ramping_yaw_rate():
    """With w ramping linearly, the trapezoid twist error shrinks as dt^3, the start one as dt^2."""

    def fine(x, y, p, v, w0, w1, dt, n=4000):
        h = dt / n
        for k in range(n):
            wk = w0 + (w1 - w0) * (k + 0.5) / n
            x, y, p = se2_step(x, y, p, v, wk, h)
        return x, y, p

    errs = {"mean": [], "start": []}
    for dt in (0.4, 0.2):
        w0, w1 = 0.2, 0.2 + 1.0 * dt
        x, y, p = fine(0.0, 0.0, 0.0, 1.0, w0, w1, dt)
        si = make_state(0, 0, 0, 1.0, w0)
        sj = make_state(x, y, p, 1.0, w1)
        for tw in errs:
            errs[tw].append(abs(motion_error(si, sj, dt, tw)[2]))
    assert errs["mean"][0] < 1e-12  # heading: trapezoid is exact for a linear w
    assert errs["start"][1] / errs["start"][0] == pytest.approx(0.25, rel=0.05)


def test_noise_sigmas():
    q = MotionNoise(
        pos_long=0.1,
        pos_lat=0.02,
        heading=0.01,
        acc=0.5,
        yaw_acc=0.3,
        gyro_bias=1e-3,
        heading_offset=2e-3,
    )
    dt = 0.25
    s = q.sigmas(dt)
    assert s[0] == pytest.approx(math.sqrt(0.01 * dt + 0.25 * dt**3 / 12))
    assert s[1] == pytest.approx(0.02 * math.sqrt(dt))
    assert s[2] == pytest.approx(math.sqrt(1e-4 * dt + 0.09 * dt**3 / 12))
    assert s[3:] == pytest.approx((0.25, 0.15, 1e-3 * 0.5, 2e-3 * 0.5, 1e-4 * 0.5, 1e-4 * 0.5))
    assert q.sigmas(dt, "start")[2] == pytest.approx(math.sqrt(1e-4 * dt + 0.09 * dt**3 / 3))
    m = q.noise_model(dt)
    np.testing.assert_allclose(m.sigmas(), s)
    with pytest.raises(ValueError):
        q.sigmas(0.0)
    with pytest.raises(ValueError):
        motion_factor(0, 1, -0.1, q)
    with pytest.raises(ValueError):
        motion_factor(0, 1, 0.1, q, twist="end")


def test_tiny_graph_recovers_trajectory():
    """3 keyframes: weak prior + motion + GPS (with lever arm) -> LM recovers the truth."""
    dt = 1.0
    lever = (0.3, 0.1)
    truth = truth_states(3, dt, v=1.2, w=0.35, x0=(5.0, -2.0, 2.8))
    graph = gtsam.NonlinearFactorGraph()
    prior_sigmas = np.array([10.0, 10.0, 3.0, 5.0, 5.0, 1e-3, 1e-3, 1e-3, 1e-3])
    graph.add(gtsam.PriorFactorVector(0, truth[0], gtsam.noiseModel.Diagonal.Sigmas(prior_sigmas)))
    noise = MotionNoise()
    for k in range(2):
        graph.add(motion_factor(k, k + 1, dt, noise))
    for k, s in enumerate(truth):
        c, sn = math.cos(s[2]), math.sin(s[2])
        e = s[0] + c * lever[0] - sn * lever[1]
        n = s[1] + sn * lever[0] + c * lever[1]
        graph.add(gps_factor(k, e, n, 0.5, lever_arm=lever))
    init = gtsam.Values()
    rng = np.random.default_rng(3)
    for k, s in enumerate(truth):
        guess = s + np.concatenate([rng.normal(0, 1.0, 2), [0.6, 0.3, -0.2, 0.0, 0.0, 0.0, 0.0]])
        init.insert(k, guess)
    assert graph.error(init) > 1.0
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-20)
    params.setMaxIterations(100)
    result = gtsam.LevenbergMarquardtOptimizer(graph, init, params).optimize()
    assert graph.error(result) < 1e-12
    for k, s in enumerate(truth):
        est = result.atVector(k)
        np.testing.assert_allclose(est[:2], s[:2], atol=1e-6)
        assert abs(math.remainder(est[2] - s[2], 2 * math.pi)) < 1e-6
        np.testing.assert_allclose(est[3:], s[3:], atol=1e-6)
