"""Tests of the shared Kalman core: update algebra, Joseph form, gate, lock-out recovery."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.ekf_baseline.kalman import KalmanCore, chi2_threshold
from ddfuse.estimation.estimator import EstimatorLog
from scipy.stats import chi2


def _random_spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


@pytest.mark.parametrize("m", [1, 2, 3, 5])
def test_update_matches_information_form(m):
    """The posterior equals the information-form result (P^-1 + H^T R^-1 H)^-1, independent
    algebra, and the logged innovation, S and NIS are the textbook ones; for m = 1..3 rows
    (S inverted by its adjugate) and 5 (by Gauss-Jordan)."""
    rng = np.random.default_rng(m)
    n = 5 if m < 5 else 7
    x0 = rng.normal(size=n)
    P0 = _random_spd(rng, n)
    H = rng.normal(size=(m, n))
    R = _random_spd(rng, m, 0.1)
    z = rng.normal(size=m)
    kf = KalmanCore(x0, P0)
    assert kf.update(0.0, "s", "k", z, H @ x0, H, R)
    Pinf = np.linalg.inv(np.linalg.inv(P0) + H.T @ np.linalg.inv(R) @ H)
    xinf = x0 + Pinf @ H.T @ np.linalg.inv(R) @ (z - H @ x0)
    np.testing.assert_allclose(kf.P, Pinf, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(kf.x, xinf, rtol=1e-9, atol=1e-12)
    inn = kf.log.innovations[-1]
    S = H @ P0 @ H.T + R
    np.testing.assert_allclose(inn.residual, z - H @ x0)
    np.testing.assert_allclose(inn.cov, S)
    y = z - H @ x0
    assert inn.nis == pytest.approx(float(y @ np.linalg.solve(S, y)), rel=1e-10)
    assert np.array_equal(kf.P, kf.P.T)


def test_scalar_update_is_the_textbook_formula():
    """One scalar measurement z = h x + v, v ~ N(0, r): K = P h / s, s = h P h + r,
    x' = x + K (z - h x), P' = P - K s K^T."""
    rng = np.random.default_rng(11)
    n = 6
    x0 = rng.normal(size=n)
    P0 = _random_spd(rng, n)
    h = np.zeros(n)
    h[[1, 4]] = (0.7, -1.3)  # a sparse row: the update sums over H's support only
    r, z = 0.2, 0.9
    kf = KalmanCore(x0, P0)
    assert kf.update(0.0, "s", "k", [z], [h @ x0], h[None, :], [[r]])
    s = h @ P0 @ h + r
    K = P0 @ h / s
    np.testing.assert_allclose(kf.x, x0 + K * (z - h @ x0), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(kf.P, P0 - s * np.outer(K, K), rtol=1e-11, atol=1e-12)


def test_unobserved_uncorrelated_states_keep_their_covariance_exactly():
    """States H does not observe and the observed ones are uncorrelated with get no gain: their
    mean, variances and covariances with each other are bit for bit those before the update."""
    rng = np.random.default_rng(5)
    n = 7
    P0 = np.zeros((n, n))
    P0[:3, :3] = _random_spd(rng, 3)
    P0[3:, 3:] = _random_spd(rng, 4)
    P0 = 0.5 * (P0 + P0.T)
    x0 = rng.normal(size=n)
    H = np.zeros((2, n))
    H[:, :3] = rng.normal(size=(2, 3))
    kf = KalmanCore(x0, P0)
    assert kf.update(0.0, "s", "k", H @ x0 + 0.5, H @ x0, H, 0.1 * np.eye(2))
    assert np.array_equal(kf.P[3:, 3:], P0[3:, 3:])
    assert np.array_equal(kf.P[3:, :3], np.zeros((4, 3)))
    assert np.array_equal(kf.x[3:], x0[3:])
    assert not np.array_equal(kf.P[:3, :3], P0[:3, :3])


def test_fused_block_is_the_update_with_its_noise_scaled():
    """``fuse``: a block fused with factor f is updated exactly as with R f (only the gain and
    the Joseph update see it; the gate and the log keep R); between two fused blocks the
    cross-covariance is scaled by sqrt(f_a f_b), i.e. the update with D R D, D = diag(sqrt f)."""
    rng = np.random.default_rng(3)
    n = 5
    x0 = rng.normal(size=n)
    P0 = _random_spd(rng, n)
    H = rng.normal(size=(3, n))
    R = _random_spd(rng, 3, 0.1)
    R[:2, 2] = R[2, :2] = 0.0
    z = H @ x0 + 0.3
    one = (("g", "gps", 0, 2, (), None),)
    fused = KalmanCore(x0, P0)
    fused.update_blocks(0.0, z[:2], H[:2] @ x0, H[:2], R[:2, :2], one, fuse=(4.0,))
    scaled = KalmanCore(x0, P0)
    scaled.update_blocks(0.0, z[:2], H[:2] @ x0, H[:2], 4.0 * R[:2, :2], one)
    assert np.array_equal(fused.x, scaled.x) and np.array_equal(fused.P, scaled.P)
    assert fused.last_verdicts == (True,)
    np.testing.assert_array_equal(fused.log.innovations[0].cov,
                                  H[:2] @ P0 @ H[:2].T + R[:2, :2])
    # two blocks with a cross-covariance
    R[:2, 2] = R[2, :2] = 0.01
    two = (("a", "ka", 0, 2, (), None), ("b", "kb", 2, 3, (), None))
    f = (4.0, 9.0)
    fused = KalmanCore(x0, P0)
    fused.update_blocks(0.0, z, H @ x0, H, R.copy(), two, fuse=f)
    d = np.sqrt([f[0], f[0], f[1]])
    scaled = KalmanCore(x0, P0)
    scaled.update_blocks(0.0, z, H @ x0, H, R * np.outer(d, d), two)
    np.testing.assert_allclose(fused.x, scaled.x, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(fused.P, scaled.P, rtol=1e-12, atol=1e-13)


def test_joseph_form_stays_psd_where_simple_form_fails():
    """A very precise measurement of a poorly known state, repeated: the simple form (I - KH)P
    rounds the measured state's variance to exactly 0 (verified: it does for these numbers), the
    Joseph form keeps it at its true value R/k after k updates and P positive definite."""
    P0 = np.array([[1e8, 1e4 - 1e-3], [1e4 - 1e-3, 1.0]])
    H = np.array([[1.0, 0.0]])
    R = np.array([[1e-10]])
    kf = KalmanCore(np.zeros(2), P0)
    for _ in range(20):
        kf.update(0.0, "s", "k", [0.0], kf.x[:1], H, R)
        assert np.array_equal(kf.P, kf.P.T)
        assert np.linalg.eigvalsh(kf.P).min() > 0.0
    # 20 independent measurements with variance R of (almost) only x0: variance R / 20
    assert kf.P[0, 0] == pytest.approx(1e-10 / 20, rel=1e-3)


def test_angle_innovation_wrapped_and_state_wrapped():
    kf = KalmanCore([3.1], [[0.1]], state_angles=(0,))
    kf.update(0.0, "imu", "heading", [-3.1], [3.1], [[1.0]], [[0.1]], angles=(0,))
    inn = kf.log.innovations[-1]
    assert inn.residual[0] == pytest.approx(2 * math.pi - 6.2)
    # halfway between 3.1 and -3.1 across the +-pi seam is pi, wrapped to -pi
    assert abs(abs(kf.x[0]) - math.pi) < 1e-9
    assert -math.pi <= kf.x[0] < math.pi


def test_chi2_threshold_cached_and_correct():
    assert chi2_threshold(0.99, 2) == pytest.approx(chi2.ppf(0.99, 2))
    assert chi2_threshold(0.9999, 1) == pytest.approx(15.1367, rel=1e-4)
    before = chi2_threshold.cache_info().hits
    chi2_threshold(0.99, 2)
    assert chi2_threshold.cache_info().hits == before + 1


def test_gate_rejects_outlier_and_logs_it():
    kf = KalmanCore([0.0], [[1.0]])
    # NIS = 100 / 1.01 >> chi2.ppf(0.99, 1) = 6.63
    assert not kf.update(1.0, "gps", "gps", [10.0], [0.0], [[1.0]], [[0.01]], gate=0.99)
    assert kf.x[0] == 0.0 and kf.P[0, 0] == 1.0
    assert kf.log.rejected[("gps", "gate")] == 1
    inn = kf.log.innovations[-1]
    assert not inn.accepted and inn.nis == pytest.approx(100 / 1.01)
    # an ordinary measurement passes
    assert kf.update(2.0, "gps", "gps", [0.5], [0.0], [[1.0]], [[0.01]], gate=0.99)


def test_nonfinite_and_singular_rejected():
    kf = KalmanCore([0.0], [[0.0]])
    assert not kf.update(0.0, "s", "k", [float("nan")], [0.0], [[1.0]], [[1.0]])
    assert kf.log.rejected[("s", "nonfinite")] == 1
    assert not kf.update(0.0, "s", "k", [1.0], [0.0], [[1.0]], [[0.0]])
    assert kf.log.rejected[("s", "singular")] == 1


def _standstill_then_move(lockout_count, seed=0):
    """Constant-velocity 1-D filter, position sensor 10 Hz (sigma 0.1 m). The robot stands still
    for 60 s (P collapses: the model's process noise is small), then moves at 0.5 m/s for 30 s.
    Returns the filter and the truth at the end."""
    rng = np.random.default_rng(seed)
    dt, sigma, q = 0.1, 0.1, 1e-6  # q: white-acceleration PSD, (m/s^2)^2/Hz -- deliberately low
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Q = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    kf = KalmanCore([0.0, 0.0], np.diag([1.0, 0.1]), EstimatorLog(), lockout_count=lockout_count,
                    lockout_time=1.0)
    pos = 0.0
    H, R = np.array([[1.0, 0.0]]), np.array([[sigma**2]])
    for k in range(1, 901):
        t = k * dt
        if t > 60.0:
            pos += 0.5 * dt
        kf.predict(F, Q)
        z = pos + sigma * rng.normal()
        kf.update(t, "pos", "position", [z], kf.x[:1], H, R, gate=0.9999)
    return kf, pos


def test_gate_lockout_happens_without_recovery():
    """The failure mode the recovery exists for: with recovery disabled the filter never accepts
    another measurement and ends far from the truth."""
    kf, pos = _standstill_then_move(lockout_count=10**9)
    assert abs(kf.x[0] - pos) > 5.0
    assert kf.log.rejected[("pos", "gate")] > 200
    assert not kf.recoveries


@pytest.mark.parametrize("seed", range(3))
def test_gate_lockout_recovery(seed):
    """With recovery the filter detects the lock-out, inflates P, logs it, and tracks again:
    final error within 5 sigma of the measurement noise."""
    kf, pos = _standstill_then_move(lockout_count=5, seed=seed)
    assert kf.recoveries, "lock-out not detected"
    assert any("lock-out" in msg for msg in kf.log.messages)
    assert kf.log.rejected[("pos", "lockout_recovery")] == len(kf.recoveries)
    assert abs(kf.x[0] - pos) < 5 * 0.1
    # velocity learned too (0.5 m/s), within a loose bound
    assert abs(kf.x[1] - 0.5) < 0.2
    # it detected it quickly: first recovery within 2 s of the robot starting to move
    # (rejections begin once the drift exceeds the gate; >= 5 rejections over >= 1 s)
    assert 60.0 < kf.recoveries[0][0] < 63.0
    assert np.linalg.eigvalsh(kf.P).min() > 0


def test_isolated_outliers_do_not_trigger_recovery():
    """A single bad measurement among good ones is rejected, the streak resets, no recovery."""
    rng = np.random.default_rng(5)
    kf = KalmanCore([0.0], [[1.0]], lockout_count=3, lockout_time=0.0)
    for k in range(200):
        kf.predict(np.eye(1), np.array([[1e-4]]))
        z = 0.1 * rng.normal() + (50.0 if k % 2 == 0 and k > 50 else 0.0)
        # every other measurement an outlier: never 3 in a row
        kf.update(k * 0.1, "s", "k", [z], kf.x, [[1.0]], [[0.01]], gate=0.999)
    assert not kf.recoveries
    assert kf.log.rejected[("s", "gate")] == 74
    assert abs(kf.x[0]) < 0.1


def test_update_blocks_equals_sequential_updates_and_gates_per_block():
    """Seed 003's stacked update of independent measurements equals applying them one after the
    other; each block is gated on its own (the outlier block is dropped, the rest applied), and
    each is logged with the NIS under the common prior."""
    rng = np.random.default_rng(7)
    n = 5
    x0 = rng.normal(size=n)
    P0 = _random_spd(rng, n)
    H1 = rng.normal(size=(2, n))
    H2 = rng.normal(size=(1, n))
    R1 = _random_spd(rng, 2, 0.1)
    R2 = np.array([[0.05]])
    z1 = H1 @ x0 + rng.normal(size=2) * 0.3
    z2 = H2 @ x0 + 0.2
    seq = KalmanCore(x0, P0)
    seq.update(0.0, "a", "ka", z1, H1 @ x0, H1, R1)
    seq.update(0.0, "b", "kb", z2, H2 @ seq.x, H2, R2)
    st = KalmanCore(x0, P0)
    H = np.vstack([H1, H2])
    R = np.zeros((3, 3))
    R[:2, :2], R[2:, 2:] = R1, R2
    z = np.concatenate([z1, z2])
    blocks = (("a", "ka", 0, 2, (), 0.999), ("b", "kb", 2, 3, (), 0.999))
    assert st.update_blocks(0.0, z, H @ x0, H, R, blocks) == 2
    np.testing.assert_allclose(st.x, seq.x, atol=1e-10)
    np.testing.assert_allclose(st.P, seq.P, atol=1e-10)
    S1 = H1 @ P0 @ H1.T + R1
    y1 = z1 - H1 @ x0
    assert st.log.innovations[0].nis == pytest.approx(float(y1 @ np.linalg.solve(S1, y1)))
    assert [i.sensor for i in st.log.innovations] == ["a", "b"]
    # now block b is an outlier: only a is applied, b is logged as rejected
    z_bad = z.copy()
    z_bad[2] += 1e3
    only_a = KalmanCore(x0, P0)
    only_a.update(0.0, "a", "ka", z1, H1 @ x0, H1, R1)
    st2 = KalmanCore(x0, P0)
    assert st2.update_blocks(0.0, z_bad, H @ x0, H, R, blocks) == 1
    np.testing.assert_allclose(st2.x, only_a.x, atol=1e-10)
    np.testing.assert_allclose(st2.P, only_a.P, atol=1e-10)
    assert st2.log.rejected[("b", "gate")] == 1
    rejected = [i for i in st2.log.innovations if not i.accepted]
    assert len(rejected) == 1 and rejected[0].sensor == "b"


def test_no_recovery_when_other_sensors_corroborate_the_filter():
    """Two sensors observe the same constant state: 'good' is right, 'bad' is biased by 20
    sigma. 'bad' is rejected persistently; since 'good' keeps being accepted on the same state,
    the core does not inflate P (no recovery), notes why, and follows 'good'. Without 'good' the
    same streak is a lock-out and is recovered (the check can fail both ways)."""
    rng = np.random.default_rng(9)
    for with_good in (True, False):
        # start confident at 0 (as after a stand-still), so that 'bad' is gated from the start
        kf = KalmanCore([0.0], [[1e-4]], lockout_count=5, lockout_time=1.0,
                        recovery_holdoff=10.0)
        H, R = np.array([[1.0]]), np.array([[0.01]])
        for k in range(600):
            t = 0.1 * k
            kf.predict(np.eye(1), np.array([[1e-6]]))
            if with_good:
                kf.update(t, "good", "v", [0.1 * rng.normal()], kf.x, H, R, gate=0.9999)
            kf.update(t, "bad", "v", [2.0 + 0.1 * rng.normal()], kf.x, H, R, gate=0.9999)
        if with_good:
            assert not kf.recoveries
            assert abs(kf.x[0]) < 0.05 and kf.P[0, 0] < 1e-3
            notes = [m for m in kf.log.messages if "disagrees with the others" in m]
            # verdicts at ~1 s, then after hold-offs of 10, 20 s: bounded, not per message
            assert 2 <= len(notes) <= 4
            assert kf.log.rejected[("bad", "gate")] > 550
        else:
            assert len(kf.recoveries) == 1 and abs(kf.x[0] - 2.0) < 0.05


def test_repeated_recoveries_are_held_off():
    """A sensor that runs away faster than any recovery can follow (10 units per 0.1 s, far
    outside the model) is never accepted between recoveries: they come only after hold-offs of
    10, 20, 40 s -- few, not one per streak. A sensor that jumps every 2 s and is accepted again
    after each recovery (independent lock-outs, e.g. landmark sighting gaps) is recovered every
    time."""
    H, R = np.array([[1.0]]), np.array([[0.01]])
    for jump_every, expect in ((1, "held_off"), (20, "each")):
        kf = KalmanCore([0.0], [[1.0]], lockout_count=5, lockout_time=1.0,
                        recovery_holdoff=10.0)
        for k in range(800):
            t = 0.1 * k
            kf.predict(np.eye(1), np.array([[1e-8]]))
            kf.update(t, "s", "k", [10.0 * (k // jump_every)], kf.x, H, R, gate=0.9999)
        times = [r[0] for r in kf.recoveries]
        if expect == "held_off":
            assert 2 <= len(times) <= 4
            gaps = np.diff(times)
            assert (gaps >= np.array([10.0, 20.0, 40.0])[: len(gaps)] - 1e-9).all()
        else:
            # a jump every 2 s, detected after >= 5 rejections spanning >= 1 s: ~39 recoveries
            assert len(times) >= 35
            assert abs(kf.x[0] - 10.0 * (799 // 20)) < 0.5


def _positive_definite(P: np.ndarray) -> bool:
    """Cholesky of the correlation matrix: scale-free, unlike eigenvalues of P itself (whose
    absolute error, ~1e-16 max|P|, exceeds a variance of 1e-11 next to one of 1e8)."""
    d = 1.0 / np.sqrt(np.diag(P))
    try:
        np.linalg.cholesky(P * np.outer(d, d))
    except np.linalg.LinAlgError:
        return False
    return True


@pytest.mark.parametrize("rows", [1, 2])
def test_precise_measurement_keeps_covariance_positive_definite(rows):
    """Measurements 1e18 times more precise than the prior, of states correlated with others:
    the factored Joseph form keeps the measured variance at R / k after k updates, P exactly
    symmetric and positive definite (the expanded form would cancel every digit)."""
    n = 7
    P0 = np.eye(n) * 1e8
    P0[3, 3] = 1.0
    P0[0, 3] = P0[3, 0] = 1e4 - 1e-3
    P0[1, 4] = P0[4, 1] = 1e4 - 1e-3
    kf = KalmanCore(np.zeros(n), P0)
    r = 1e-10
    R = ((r, 0.0), (0.0, r)) if rows == 2 else ((r,),)
    for k in range(20):
        kf.update_blocks(float(k), np.zeros(rows), 0.0, np.eye(n)[:rows], np.array(R),
                         [("s", "k", 0, rows, (), None)])
        assert _positive_definite(kf.P)
        assert np.array_equal(kf.P, kf.P.T)
    assert kf.P[0, 0] == pytest.approx(r / 20, rel=1e-3)
