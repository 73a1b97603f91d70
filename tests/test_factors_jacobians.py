"""Analytic Jacobians of every factor vs central differences through gtsam's Values.retract.

States include yaw rates of exactly 0, 1e-9 and 1e-5 rad/s (the series branch of the kinematics),
rates across the series threshold, and headings on both sides of +-pi.
"""

import math
import random

import gtsam
import numpy as np
import pytest
from ddfuse.factors.gps import gps_factor, gps_predict, gps_predict_jacobian
from ddfuse.factors.gyro import bias_difference_factor
from ddfuse.factors.heading import heading_factor
from ddfuse.factors.landmark import range_bearing_factor, range_factor
from ddfuse.factors.preintegration import WheelGyroPreintegration, preintegrated_factor
from jacobian_checks import analytic_jacobians, max_jacobian_error, numerical_jacobians

KI, KJ = 1, 2
TOL = 1e-6


def unit(d):
    return gtsam.noiseModel.Unit.Create(d)


def _pim():
    p = WheelGyroPreintegration(bg_lin=0.01)
    for k in range(30):
        p.integrate(0.02, 1.2 + 0.1 * math.sin(k), 0.3 * math.cos(0.2 * k), 0.05**2, 0.01**2)
    return p


PIM = _pim()


def _pim_fused():
    p = WheelGyroPreintegration(bg_lin=0.01)
    for k in range(30):
        p.integrate(0.02, 1.2, 0.3 * math.cos(0.2 * k), 0.05**2, 0.01**2, gain=0.6)
    return p


PIM_FUSED = _pim_fused()

FACTORS = {
    "bias_difference": lambda: bias_difference_factor(KI, 0.31, 0.27, 0.004, 0.02),
    "heading": lambda: heading_factor(KI, 3.1, unit(1)),
    "heading_no_offset": lambda: heading_factor(KI, -3.1, unit(1), use_offset=False),
    "gps": lambda: gps_factor(KI, 3.0, -4.0, unit(2)),
    "gps_lever": lambda: gps_factor(KI, 3.0, -4.0, unit(2), lever_arm=(0.4, -0.25)),
    "gps_lever_dt": lambda: gps_factor(KI, 3.0, -4.0, unit(2), lever_arm=(0.4, -0.25), dt_fix=0.23),
    "gps_neg_dt": lambda: gps_factor(KI, 3.0, -4.0, unit(2), lever_arm=(-0.3, 0.1), dt_fix=-0.4),
    "range_bearing": lambda: range_bearing_factor(KI, (7.0, -2.0), 5.0, 0.3, unit(2), (0.2, 0.1)),
    "range": lambda: range_factor(KI, (7.0, -2.0), 5.0, unit(1), (0.2, 0.1)),
    "range_bearing_dt": lambda: range_bearing_factor(KI, (7.0, -2.0), 5.0, 0.3, unit(2),
                                                     (0.2, 0.1), dt=0.23),
    "range_neg_dt": lambda: range_factor(KI, (7.0, -2.0), 5.0, unit(1), (0.2, 0.1), dt=-0.4),
    # bearings with an error common to their frame: conditional on two earlier sightings
    "range_bearing_frame": lambda: range_bearing_factor(
        KI, (7.0, -2.0), 5.0, 0.3, unit(2), (0.2, 0.1),
        earlier=[((-3.0, 4.0, 2.9), 0.4), ((1.0, 9.0, -3.1), 0.25)]),
    "range_bearing_frame_dt": lambda: range_bearing_factor(
        KI, (7.0, -2.0), 5.0, 0.3, unit(2), (0.2, 0.1), dt=0.23,
        earlier=[((-3.0, 4.0, 2.9), 0.4), ((1.0, 9.0, -3.1), 0.25)]),
    "preintegrated": lambda: preintegrated_factor(KI, KJ, PIM, noise=unit(9)),
    "preintegrated_fused": lambda: preintegrated_factor(KI, KJ, PIM_FUSED, noise=unit(9)),
}

YAW_RATES = [0.0, 1e-9, 1e-5, -1e-5, 0.0999 / 0.37, 0.1001 / 0.37, 0.8, -2.0]
HEADINGS = [math.pi - 1e-6, -math.pi + 1e-6, math.pi + 0.2, 0.4]


def make_values(w, psi, seed):
    rng = random.Random(seed)
    si = np.array(
        [
            rng.uniform(-20, 20),
            rng.uniform(-20, 20),
            psi,
            rng.uniform(-1.5, 2.5),
            w,
            rng.uniform(-0.05, 0.05),
            rng.uniform(-math.pi, math.pi),
            rng.uniform(0.9, 1.1),
            rng.uniform(0.9, 1.1),
        ]
    )
    # j near i, heading on the other side of +-pi for the near-pi cases
    sj = si + np.array(
        [
            rng.uniform(-1, 1),
            rng.uniform(-1, 1),
            rng.uniform(-0.3, 0.3) + (2e-6 if psi > 3 else -2e-6 if psi < -3 else 0.0),
            rng.uniform(-0.2, 0.2),
            0.5 * w if rng.random() < 0.5 else w,
            rng.uniform(-0.01, 0.01),
            rng.uniform(-0.1, 0.1),
            rng.uniform(-0.01, 0.01),
            rng.uniform(-0.01, 0.01),
        ]
    )
    values = gtsam.Values()
    values.insert(KI, si)
    values.insert(KJ, sj)
    return values


def _subset(values, keys):
    out = gtsam.Values()
    for k in keys:
        out.insert(k, values.atVector(k))
    return out


@pytest.mark.parametrize("name", sorted(FACTORS))
def test_jacobians_match_central_differences(name):
    worst = 0.0
    for w in YAW_RATES:
        for psi in HEADINGS:
            factor = FACTORS[name]()
            values = _subset(make_values(w, psi, seed=hash((w, psi)) & 0xFFFF), factor.keys())
            err = max_jacobian_error(factor, values)
            worst = max(worst, err)
            assert err < TOL, (name, w, psi, err)
    # a sanity floor: the check itself is not vacuous
    assert worst < TOL


def test_check_detects_a_wrong_jacobian():
    """The comparison must be able to fail: a factor with a deliberately wrong Jacobian."""

    def bad(this, values, H):
        s = values.atVector(KI)
        if H is not None:
            H[0] = np.array([[1.0, 0, 0, 0, 0, 0, 0, 0, 0]])  # misses the y dependence
        return np.array([s[0] + 1e-3 * s[1]])

    f = gtsam.CustomFactor(unit(1), [KI], bad)
    v = gtsam.Values()
    v.insert(KI, np.zeros(9))
    assert max_jacobian_error(f, v) > 5e-4


@pytest.mark.parametrize("name", ["preintegrated", "gps_lever_dt", "heading"])
def test_buffers_are_copied_by_gtsam(name):
    """Factors reuse their Jacobian and error buffers; earlier results must not change."""
    f = FACTORS[name]()
    v1 = _subset(make_values(0.3, 0.2, 1), f.keys())
    v2 = _subset(make_values(-0.7, 2.0, 2), f.keys())
    lin1 = f.linearize(v1)
    a1, b1 = (x.copy() for x in lin1.jacobian())
    e1 = f.unwhitenedError(v1)
    e1c = e1.copy()
    lin2 = f.linearize(v2)
    f.unwhitenedError(v2)
    np.testing.assert_array_equal(lin1.jacobian()[0], a1)
    np.testing.assert_array_equal(lin1.jacobian()[1], b1)
    np.testing.assert_array_equal(e1, e1c)
    assert not np.allclose(lin2.jacobian()[1], b1)


def test_whitening_is_undone_for_diagonal_noise():
    """analytic_jacobians unwhitens: same result with unit noise and with the factor's own full
    covariance."""
    v = make_values(0.2, 1.0, 3)
    f1 = preintegrated_factor(KI, KJ, PIM, noise=unit(9))
    f2 = preintegrated_factor(KI, KJ, PIM)
    for a, b in zip(analytic_jacobians(f1, v), analytic_jacobians(f2, v), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9)
    nj = numerical_jacobians(f2, v)
    assert len(nj) == 2 and nj[0].shape == (9, 9)


def test_gps_predict_jacobian_is_the_factors_model():
    """The smoother gates a fix, logs its NIS and widens on a lock-out with
    ``gps_predict_jacobian``: the same prediction as ``gps_predict`` and the same Jacobian as
    the factor, at random states including w = 0, tiny w and either sign of dt."""
    rng = np.random.default_rng(11)
    for k in range(200):
        x = rng.normal(size=9)
        x[2] = rng.uniform(-math.pi, math.pi)
        x[4] = (0.0, 1e-7, rng.normal())[k % 3]
        lever = (0.0, 0.0) if k % 4 == 0 else tuple(rng.normal(size=2))
        dt = 0.0 if k % 5 == 0 else rng.normal()
        pred, h = gps_predict_jacobian(x, lever, dt)
        assert np.allclose(pred, gps_predict(x, lever, dt), rtol=0, atol=1e-12)
        values = gtsam.Values()
        values.insert(0, x)
        j = gps_factor(0, 0.0, 0.0, 1.0, lever, dt).linearize(values).jacobian()[0]
        assert np.allclose(h, j, rtol=0, atol=1e-9)
        # and both against central differences
        num = np.column_stack([(np.array(gps_predict(x + e, lever, dt))
                                - np.array(gps_predict(x - e, lever, dt))) / 2e-6
                               for e in np.eye(9) * 1e-6])
        assert np.allclose(h, num, rtol=0, atol=1e-6)
