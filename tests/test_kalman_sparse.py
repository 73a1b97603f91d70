"""The Kalman core's fast path ``update_sparse`` against its dense numpy reference
``update_blocks`` (through ``update_dense``): same state, covariance, log and verdicts."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.ekf_baseline.kalman import JOSEPH_EXPANDED_MIN, KalmanCore

N = 7
ANGLES = (2, 6)


def _pair(rng, P0=None, **kw):
    x0 = rng.normal(size=N)
    x0[2] = 3.1  # next to the +-pi seam: updates carry it across
    if P0 is None:
        A = rng.normal(size=(N, N))
        P0 = A @ A.T + N * np.eye(N)
    return (KalmanCore(x0, P0, state_angles=ANGLES, **kw),
            KalmanCore(x0, P0, state_angles=ANGLES, **kw))


def _random_row(rng):
    cols = rng.choice(N, size=rng.integers(1, 3), replace=False)
    return tuple((int(c), float(rng.choice([1.0, rng.normal()]))) for c in cols)


def _random_block(rng, k, outlier):
    m = int(rng.integers(1, 3))
    rows = tuple(_random_row(rng) for _ in range(m))
    if m == 1:
        R = ((float(rng.uniform(0.01, 1.0)),),)
    else:
        a, d = rng.uniform(0.01, 1.0, size=2)
        b = 0.5 * math.sqrt(a * d) * rng.uniform(-1, 1)
        R = ((float(a), float(b)), (float(b), float(d)))
    y = tuple(float(v) for v in rng.normal(size=m) * (30.0 if outlier else 0.5))
    return (f"s{k}", "k", y, rows, R, 0.999)


def _assert_same(a: KalmanCore, b: KalmanCore, what: str, since: int = 0) -> int:
    """State, covariance, counters, notes and the innovations logged from index ``since`` on
    agree; returns the log's length."""
    np.testing.assert_allclose(a.x, b.x, rtol=1e-9, atol=1e-9, err_msg=what)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-9, atol=1e-9 * np.abs(b.P).max(),
                               err_msg=what)
    assert np.array_equal(a.P, a.P.T), what
    assert a.log.rejected == b.log.rejected, what
    assert a.log.messages == b.log.messages, what
    assert len(a.log.innovations) == len(b.log.innovations), what
    for ia, ib in zip(a.log.innovations[since:], b.log.innovations[since:], strict=True):
        assert (ia.t, ia.sensor, ia.kind, ia.accepted) == (ib.t, ib.sensor, ib.kind, ib.accepted)
        np.testing.assert_allclose(ia.residual, ib.residual, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(ia.cov, ib.cov, rtol=1e-9, err_msg=what)
        assert ia.nis == pytest.approx(ib.nis, rel=1e-8), what
    return len(a.log.innovations)


def _positive_definite(P: np.ndarray) -> bool:
    """Cholesky of the correlation matrix: scale-free, unlike eigenvalues of P itself (whose
    absolute error, ~1e-16 max|P|, exceeds a variance of 1e-11 next to one of 1e8)."""
    d = 1.0 / np.sqrt(np.diag(P))
    try:
        np.linalg.cholesky(P * np.outer(d, d))
    except np.linalg.LinAlgError:
        return False
    return True


@pytest.mark.parametrize("seed", range(6))
def test_random_sparse_updates_match_dense_reference(seed):
    """Random sequences of 1-3 blocks of 1-2 sparse rows (scalar and stacked, correlated R
    within a block), with outliers that the gate rejects, angle states wrapped across +-pi."""
    rng = np.random.default_rng(seed)
    fast, ref = _pair(rng)
    F = np.eye(N)
    F[0, 3] = F[1, 4] = 0.1
    Q = np.diag(rng.uniform(0.001, 0.05, size=N))
    n_rejected = 0
    logged = 0
    signs = set()
    for step in range(300):
        t = 0.1 * step
        for kf in (fast, ref):
            kf.predict(F, Q)
        blocks = [_random_block(rng, k, rng.uniform() < 0.1)
                  for k in range(int(rng.integers(0, 3)))]
        # a heading sensor on state 2 that swings across +-pi: its wrapped innovation
        target = math.pi + 0.4 * math.sin(0.05 * step)
        y = (target - fast.x[2] + math.pi) % (2 * math.pi) - math.pi
        blocks.insert(int(rng.integers(0, len(blocks) + 1)),
                      ("heading", "yaw", (float(y),), (((2, 1.0),),), ((0.01,),), 0.999))
        got = fast.update_sparse(t, blocks)
        assert got == ref.update_dense(t, blocks)
        n_rejected += len(blocks) - got
        logged = _assert_same(fast, ref, f"step {step}", logged)
        if abs(fast.x[2]) > 2.5:
            signs.add(math.copysign(1.0, fast.x[2]))
    assert n_rejected > 20  # the gate was exercised
    assert signs == {-1.0, 1.0}  # the angle state crossed the seam at +-pi


def test_lockout_recovery_matches_dense_reference():
    """A sensor that jumps (a kidnapped robot) and is rejected until the core declares the
    lock-out, inflates P and accepts it: recoveries, notes and the result are the reference's,
    for a scalar and a two-row sensor, alone or stacked with an uncorrelated one."""
    rng = np.random.default_rng(3)
    sensors = [((((0, 1.0),),), ((0.01,),)),
               ((((0, 1.0),), ((1, 1.0),)), ((0.01, 0.002), (0.002, 0.02)))]
    for rows, R in sensors:
        for with_other in (False, True):
            fast, ref = _pair(rng, lockout_count=5, lockout_time=1.0)
            F, Q = np.eye(N), np.eye(N) * 1e-6
            logged = 0
            for step in range(80):
                t = 0.1 * step
                truth = 0.0 if step < 30 else 50.0
                for kf in (fast, ref):
                    kf.predict(F, Q)
                y = tuple(truth - float(fast.x[r[0][0]]) + 0.05 * rng.normal() for r in rows)
                blocks = [("jumpy", "pos", y, rows, R, 0.9999)]
                if with_other:
                    blocks.append(("other", "v", (0.1 * rng.normal(),), (((3, 1.0),),),
                                   ((0.01,),), 0.9999))
                assert fast.update_sparse(t, blocks) == ref.update_dense(t, blocks)
                logged = _assert_same(fast, ref, f"rows {len(rows)} other {with_other} step {step}",
                                      logged)
            assert fast.recoveries and len(fast.recoveries) == len(ref.recoveries)
            assert abs(fast.x[0] - 50.0) < 1.0


@pytest.mark.parametrize("rows", [1, 2])
def test_precise_measurement_keeps_covariance_positive_definite(rows):
    """Measurements far more precise than the prior (r / s < JOSEPH_EXPANDED_MIN): the fast
    path switches to the factored Joseph product and, like the reference, keeps the measured
    variance at R / k after k updates and P positive definite."""
    P0 = np.eye(N) * 1e8
    P0[3, 3] = 1.0
    P0[0, 3] = P0[3, 0] = 1e4 - 1e-3
    P0[1, 4] = P0[4, 1] = 1e4 - 1e-3
    fast = KalmanCore(np.zeros(N), P0)
    ref = KalmanCore(np.zeros(N), P0)
    r = 1e-10
    assert r / (P0[0, 0] + r) < JOSEPH_EXPANDED_MIN
    hrows = (((0, 1.0),), ((1, 1.0),))[:rows]
    R = ((r, 0.0), (0.0, r)) if rows == 2 else ((r,),)
    for k in range(20):
        blocks = [("s", "k", (0.0,) * rows, hrows, R, None)]
        fast.update_sparse(float(k), blocks)
        ref.update_dense(float(k), blocks)
        assert _positive_definite(fast.P)
        assert np.array_equal(fast.P, fast.P.T)
    assert fast.P[0, 0] == pytest.approx(r / 20, rel=1e-3)
    np.testing.assert_allclose(fast.P, ref.P, rtol=1e-6, atol=1e-18)
