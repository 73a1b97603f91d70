"""Seed 004's linear Kalman filters: the document's worked numbers, the corrected Q, consistency."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.ekf_baseline.kalman import KalmanCore
from ddfuse.ekf_baseline.linear import (
    ConstantAccelerationKF,
    Kalman1D,
    ca_process_noise,
    ca_transition,
    multiply_gaussians,
)
from scipy.linalg import expm
from scipy.stats import chi2

INCH = 0.0254  # m


def test_seed_worked_example_21_vs_19p5_inches():
    """Seed 004 'Concept': commanded 100 rpm on 4-inch wheels for 1 s predicts 21 inches, the
    encoders measure 19.5 inches. With the pseudocode's PROCESS_VAR = MEASUREMENT_VAR = 0.1 and a
    start known exactly (variance 0), the gain is 0.5 and the estimate is the average, 20.25 in,
    with variance 0.05 (halved)."""
    v = 100.0 / 60.0 * math.pi * 4.0 * INCH  # 100 rpm, 4" wheels: 20.94 in/s, "21 inches per sec"
    assert v / INCH == pytest.approx(21.0, abs=0.1)
    # Work in inches like the seed (the filter is unit-agnostic); seed's prediction is 21 in.
    kf = Kalman1D(0.0, 0.0, process_psd=0.1, meas_var=0.1)
    kf.predict(21.0, 1.0)
    assert kf.x == pytest.approx(21.0) and kf.var == pytest.approx(0.1)
    assert kf.gain() == pytest.approx(0.5)
    assert kf.update(19.5)
    assert kf.x == pytest.approx(20.25)
    assert kf.var == pytest.approx(0.05)


def test_seed_pseudocode_loop_converges_to_golden_ratio_gain():
    """The seed's loop (PROCESS_VAR = MEASUREMENT_VAR = 0.1 per step, TIME_STEP = 0.01 s) has a
    steady state p^2 + q p - q r = 0: posterior variance 0.1 (sqrt5 - 1)/2 = 0.0618 and gain
    1/phi = 0.618, and, with the residual restored in the update, tracks a moving target."""
    dt = 0.01
    kf = Kalman1D(0.0, 0.5, process_psd=0.1 / dt, meas_var=0.1)
    rng = np.random.default_rng(0)
    truth = 0.0
    errs = []
    for _ in range(2000):
        truth += 0.5 * dt
        kf.predict(0.5, dt)
        kf.update(truth + math.sqrt(0.1) * rng.normal())
        errs.append(kf.x - truth)
    assert kf.var == pytest.approx(0.1 * (math.sqrt(5) - 1) / 2, rel=1e-9)
    kf.predict(0.5, dt)
    assert kf.gain() == pytest.approx(2 / (1 + math.sqrt(5)), rel=1e-9)
    # the seed's update (state + gain, no residual) would run away by 0.618 per step
    assert abs(np.mean(errs[100:])) < 0.05
    # the truth here moves exactly as commanded (no process noise), so the steady-state error is
    # e_k = (1 - K) e_{k-1} + K v_k with variance K r / (2 - K) = 0.0447, below the filter's
    # (conservative) 0.0618; 1900 correlated samples: within 15 %
    K = 2 / (1 + math.sqrt(5))
    assert np.var(errs[100:]) == pytest.approx(K * 0.1 / (2 - K), rel=0.15)


def test_ca_transition_is_seed_matrix():
    dt = 0.3
    np.testing.assert_array_equal(
        ca_transition(dt), [[1, dt, 0.5 * dt * dt], [0, 1, dt], [0, 0, 1]]
    )
    kf = ConstantAccelerationKF([0.0, 0.0], axes=2, jerk_psd=1.0, meas_std=0.1)
    F, Q = kf.matrices(dt)
    np.testing.assert_array_equal(F[:3, :3], ca_transition(dt))
    np.testing.assert_array_equal(F[3:, 3:], ca_transition(dt))
    assert not F[:3, 3:].any() and not Q[:3, 3:].any()


@pytest.mark.parametrize("dt", [0.01, 0.1, 1.0, 3.0])
def test_ca_process_noise_is_van_loan_discretisation(dt):
    """Closed-form Q equals the Van Loan matrix-exponential discretisation of white jerk."""
    q = 0.7
    A = np.array([[0.0, 1, 0], [0, 0, 1], [0, 0, 0]])
    G = np.array([[0.0], [0], [1]])
    M = np.zeros((6, 6))
    M[:3, :3] = -A
    M[:3, 3:] = G @ G.T * q
    M[3:, 3:] = A.T
    E = expm(M * dt)
    Phi = E[3:, 3:].T
    Qvl = Phi @ E[:3, 3:]
    np.testing.assert_allclose(Phi, ca_transition(dt), atol=1e-12)
    np.testing.assert_allclose(ca_process_noise(dt, q), Qvl, rtol=1e-9, atol=1e-15)
    assert np.linalg.eigvalsh(ca_process_noise(dt, q)).min() > 0


def test_seed_example_q_is_not_a_covariance():
    """Erratum check: the seed's per-axis Q block [[0, .001], [.001, .001]] is indefinite."""
    seed_block = np.array([[0.0, 0.001], [0.001, 0.001]])
    assert np.linalg.eigvalsh(seed_block).min() < 0


def _simulate_ca(rng, axes, steps, dt, q, sigma):
    kf = ConstantAccelerationKF(np.zeros(3 * axes), axes=axes, jerk_psd=q, meas_std=sigma,
                                p0_std=(0.5, 0.3, 0.2))
    truth = rng.normal(size=3 * axes) * np.tile([0.5, 0.3, 0.2], axes)
    F, Q = kf.matrices(dt)
    Lq = np.linalg.cholesky(Q)
    nees = []
    pos_err = []
    for _ in range(steps):
        truth = F @ truth + Lq @ rng.normal(size=3 * axes)
        kf.predict(dt)
        z = truth[0::3] + sigma * rng.normal(size=axes)
        kf.update(z)
        e = kf.x - truth
        nees.append(float(e @ np.linalg.solve(kf.P, e)))
        pos_err.append(e[0::3])
    return np.array(nees), np.array(pos_err)


def test_constant_acceleration_consistency_and_accuracy():
    """Truth drawn from the same model: the average NEES over 40 runs at several times lies in
    the two-sided 99 % chi-square band, and the filtered position error is well below the
    measurement noise."""
    rng = np.random.default_rng(42)
    axes, steps, dt, q, sigma, runs = 2, 150, 0.1, 2.0, 0.3, 40
    all_nees, all_pos = [], []
    for _ in range(runs):
        nees, pos = _simulate_ca(rng, axes, steps, dt, q, sigma)
        all_nees.append(nees)
        all_pos.append(pos)
    all_nees = np.array(all_nees)
    dof = 3 * axes
    lo, hi = chi2.ppf([0.005, 0.995], runs * dof) / runs
    for k in (10, 50, 149):  # well-separated times
        assert lo < all_nees[:, k].mean() < hi, (k, all_nees[:, k].mean(), lo, hi)
    rmse = np.sqrt(np.mean(np.array(all_pos)[:, 20:] ** 2))
    assert rmse < 0.8 * sigma


def test_angle_axis_wraps():
    kf = ConstantAccelerationKF([3.1], axes=1, jerk_psd=1.0, meas_std=0.05,
                                p0_std=(0.1, 0.1, 0.1), angle_axes=(0,))
    for _ in range(20):
        kf.predict(0.1)
        kf.update([-3.1])  # 0.083 rad across the seam, not 6.2 rad back
    assert -math.pi <= kf.x[0] < math.pi
    assert abs(((kf.x[0] + 3.1 + math.pi) % (2 * math.pi)) - math.pi) < 0.01


def test_multiply_gaussians_equals_kalman_update_with_identity_h():
    rng = np.random.default_rng(3)
    m1, m2 = rng.normal(size=3), rng.normal(size=3)
    A, B = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
    C1, C2 = A @ A.T + np.eye(3), B @ B.T + 0.5 * np.eye(3)
    mean, cov = multiply_gaussians(m1, C1, m2, C2)
    kf = KalmanCore(m1, C1)
    kf.update(0.0, "s", "k", m2, m1, np.eye(3), C2)
    np.testing.assert_allclose(mean, kf.x, atol=1e-10)
    np.testing.assert_allclose(cov, kf.P, atol=1e-10)
    # 1-D: the seed's gain formula
    mean1, var1 = multiply_gaussians([21.0], [[0.1]], [19.5], [[0.1]])
    assert mean1[0] == pytest.approx(20.25) and var1[0, 0] == pytest.approx(0.05)


def test_update_from_the_seeds_singular_p0_stays_a_covariance_errata_004_9():
    """Errata 004 #9: the seed's P0 with zero velocity and acceleration variance ("the robot
    starts still", ``p0_std=(0.7, 0, 0)``) is allowed because the update is the Joseph form.
    First update, with a fix far more precise than the prior (sigma 1e-9 m against 0.7 m, so
    that K rounds to exactly 1): the position variance is R (the Joseph form's K R K^T), not
    the 0 of the short form (I - K H) P, v and a stay exactly known (zero rows), P symmetric.
    Then 200 predict/update cycles of 10 ms keep P symmetric and positive definite (Q makes
    the velocity and acceleration uncertain after the first predict)."""
    meas = 1e-9
    kf = ConstantAccelerationKF([0.0], axes=1, jerk_psd=1.0, meas_std=meas, p0_std=(0.7, 0.0, 0.0))
    assert np.linalg.matrix_rank(kf.P) == 1
    assert kf.update([0.3])
    P = kf.P
    assert P[0, 0] == pytest.approx(meas**2, rel=1e-6, abs=0.0)  # short form: exactly 0
    assert np.all(P[1:, :] == 0.0) and np.all(P[:, 1:] == 0.0)
    assert kf.x[0] == pytest.approx(0.3)

    rng = np.random.default_rng(2)
    kf = ConstantAccelerationKF([0.0], axes=1, jerk_psd=1.0, meas_std=0.01)  # default P0
    assert np.linalg.matrix_rank(kf.P) == 1  # the default is singular too: (1, 0, 0)
    for k in range(200):
        if k:
            kf.predict(0.01)
        t = 0.01 * k
        kf.update([0.5 * t * t + rng.normal(0.0, 0.01)])  # true a = 1 m/s^2
        P = kf.P
        assert np.array_equal(P, P.T)
        if k:
            assert np.linalg.eigvalsh(P).min() > 0.0
    assert kf.x[2] == pytest.approx(1.0, abs=0.5)
