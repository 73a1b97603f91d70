"""ddfuse.factors.preintegration_jit: the compiled preintegration equals the Python reference
(``factors.preintegration.WheelGyroPreintegration``) to 1e-9, and so does the smoother that uses
it."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from ddfuse.estimation.smoother import FixedLagSmoother
from ddfuse.factors.preintegration import WheelGyroPreintegration, preintegrated_factor
from ddfuse.factors.preintegration_jit import SLOTS, WheelGyroPreintegrationJit
from ddfuse.factors.state import make_state


def _samples(rng, n):
    """Held samples (dt, v, w_gyro, var_v, var_w, gain, w_odo): both branches of twist_coeffs
    (|w dt| below and above 0.1), reversing, standing still, gyro only / odometry only / fused."""
    out = []
    for _ in range(n):
        dt = rng.uniform(1e-3, 0.5)
        w = rng.choice([rng.normal(0, 0.02), rng.normal(0, 1.5)])
        gain = rng.choice([1.0, 0.0, rng.uniform(0.1, 0.9)])
        w_odo = 0.0 if gain == 1.0 else rng.normal(0, 0.5)
        v = rng.choice([0.0, rng.normal(0, 1.5)])
        out.append((dt, v, w, rng.uniform(1e-5, 1e-2), rng.uniform(1e-6, 1e-3), gain, w_odo))
    return out


def _assert_same(ref, jit):
    for name in SLOTS:
        a, b = getattr(ref, name), getattr(jit, name)
        assert b == pytest.approx(a, rel=1e-9, abs=1e-12), name
    assert isinstance(jit.n, int)


@pytest.mark.parametrize("seed", range(4))
def test_integrate_equals_reference(seed):
    rng = np.random.default_rng(seed)
    lin = (rng.normal(0, 0.01), 1 + rng.normal(0, 0.02), 1 + rng.normal(0, 0.02))
    ref = WheelGyroPreintegration(lin[0], keep_samples=True, kv_lin=lin[1], kw_lin=lin[2])
    jit = WheelGyroPreintegrationJit(lin[0], keep_samples=True, kv_lin=lin[1], kw_lin=lin[2])
    for s in _samples(rng, 200):
        ref.integrate(*s)
        jit.integrate(*s)
    _assert_same(ref, jit)
    assert abs(ref.dpsi) > 1.0  # the interval turned: the rotation terms were exercised
    # the derived quantities are the reference's own code on the same numbers
    np.testing.assert_allclose(jit.covariance, ref.covariance, rtol=1e-9, atol=1e-15)
    st = make_state(3.0, -2.0, 2.5, 0.5, 0.1, 0.004, 0.2, 1.01, 0.99)
    np.testing.assert_allclose(jit.predict(st), ref.predict(st), rtol=1e-9, atol=1e-12)
    # reset keeps (or replaces) the linearisation points as the reference does, and replays
    ref.reintegrate(0.02, 1.05)
    jit.reintegrate(0.02, 1.05)
    _assert_same(ref, jit)
    ref.reset()
    jit.reset()
    _assert_same(ref, jit)
    assert jit.n == 0 and jit.last_gain == 1.0 and jit.kv_lin == 1.05


@pytest.mark.parametrize("seed", range(2))
def test_one_read_accessors_equal_the_frozen_copy(seed):
    """``partial`` and ``yaw_terms`` (what the filtered output and each heading sample read, one
    array read instead of a ``frozen`` copy or a property per attribute) give bit for bit what
    the copy's ``delta_at``, ``covariance`` and attributes give, and the reference's to 1e-9."""
    rng = np.random.default_rng(10 + seed)
    ref = WheelGyroPreintegration(0.003, keep_samples=False, kv_lin=1.02, kw_lin=0.97)
    jit = WheelGyroPreintegrationJit(0.003, keep_samples=False, kv_lin=1.02, kw_lin=0.97)
    for s in _samples(rng, 50):
        ref.integrate(*s)
        jit.integrate(*s)
    bg, kv, kw = 0.0041, 1.013, 0.982
    frozen = jit.frozen()
    delta, cov = jit.partial(bg, kv, kw)
    assert delta == frozen.delta_at(bg, kv, kw)
    assert cov == frozen.covariance.tolist()
    assert jit.yaw_terms() == (frozen.dpsi, frozen.j_p, frozen.kw_p, frozen.c_pp)
    ref_delta, ref_cov = ref.partial(bg, kv, kw)
    assert ref_delta == ref.delta_at(bg, kv, kw)
    np.testing.assert_allclose(delta, ref_delta, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cov, ref_cov, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(jit.yaw_terms(), ref.yaw_terms(), rtol=1e-9, atol=1e-15)
    assert abs(delta[0] - jit.dx) > 0.0  # the bias and scales moved the increment


def test_factor_from_jit_equals_factor_from_reference():
    rng = np.random.default_rng(9)
    ref = WheelGyroPreintegration(0.003, keep_samples=False, kv_lin=1.02, kw_lin=0.97)
    jit = WheelGyroPreintegrationJit(0.003, keep_samples=False, kv_lin=1.02, kw_lin=0.97)
    for s in _samples(rng, 60):
        ref.integrate(*s)
        jit.integrate(*s)
    ki, kj = 1, 2
    fr, fj = preintegrated_factor(ki, kj, ref), preintegrated_factor(ki, kj, jit)
    for _ in range(5):
        v = gtsam.Values()
        v.insert(ki, make_state(*rng.normal(0, 1, 9)))
        v.insert(kj, make_state(*rng.normal(0, 1, 9)))
        assert fj.error(v) == pytest.approx(fr.error(v), rel=1e-9)
        np.testing.assert_allclose(fj.linearize(v).augmentedInformation(),
                                   fr.linearize(v).augmentedInformation(), rtol=1e-9, atol=1e-9)


def test_smoother_with_jit_equals_reference(sample_husky):
    """The whole smoother (filtered estimate at every 5th message, lagged keyframes) is the
    same with either preintegration."""
    cfg, stream = sample_husky
    out = []
    for reference in (True, False):
        sm = FixedLagSmoother(cfg, reference=reference)
        assert isinstance(sm.twist.pim, WheelGyroPreintegrationJit) != reference
        filt = []
        for i, m in enumerate(stream.measurements):
            sm.process(m)
            if i % 5 == 0 and (e := sm.estimate()) is not None:
                filt.append((e.t, *e.pose, *np.ravel(e.pose_cov)))
        sm.finish()
        lag = [(e.t, *e.pose, *np.ravel(e.pose_cov)) for e in sm.lagged_estimates()]
        out.append((np.array(filt), np.array(lag)))
    (fr, lr), (fj, lj) = out
    assert len(fr) > 1000 and len(lr) > 200
    np.testing.assert_allclose(fj, fr, rtol=0, atol=1e-9)
    np.testing.assert_allclose(lj, lr, rtol=0, atol=1e-9)
    assert math.isfinite(fj[-1, 1])


def test_cache_guard_drops_stale_kernels(tmp_path, monkeypatch):
    """numba checks only preintegration_jit.py's time stamp: a change of kinematics.py (compiled
    into the kernel) must drop the cached kernel, an unchanged source tree must keep it."""
    import ddfuse.factors.preintegration_jit as pj

    for name in pj._KERNEL_SOURCES:
        (tmp_path / name).write_bytes((pj._HERE / name).read_bytes())
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    monkeypatch.setattr(pj, "_HERE", tmp_path)
    pj._guard_cache()  # first run: records the sources' hash
    kernel = cache / "preintegration_jit.integrate-1.py311.nbi"
    kernel.write_text("cached")
    pj._guard_cache()
    assert kernel.exists()  # unchanged sources: the cache stays
    (tmp_path / "kinematics.py").write_text("# changed\n")
    pj._guard_cache()
    assert not kernel.exists()
