"""Tests for ddfuse.factors.kinematics: exact SE(2) constant-twist motion."""

import math
import random

import mpmath
import pytest
from ddfuse.factors.kinematics import (
    SERIES_THRESHOLD,
    se2_increment,
    se2_step,
    se2_step_jac,
    twist_coeffs,
    wrap_angle,
)


def rk4_unicycle(x, y, psi, v, w, dt, n=2000):
    """Fine RK4 integration of x' = v cos psi, y' = v sin psi, psi' = w."""
    h = dt / n
    for _ in range(n):
        k1 = (v * math.cos(psi), v * math.sin(psi))
        p2 = psi + 0.5 * h * w
        k2 = (v * math.cos(p2), v * math.sin(p2))
        k3 = k2
        p4 = psi + h * w
        k4 = (v * math.cos(p4), v * math.sin(p4))
        x += h / 6.0 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        y += h / 6.0 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        psi = p4
    return x, y, psi


def coeffs_ref(a):
    with mpmath.workdps(40):
        a = mpmath.mpf(a)
        if a == 0:
            return (1.0, 0.0, 0.0, 0.5)
        s = mpmath.sin(a) / a
        c = (1 - mpmath.cos(a)) / a
        ds = (a * mpmath.cos(a) - mpmath.sin(a)) / a**2
        dc = (a * mpmath.sin(a) - 1 + mpmath.cos(a)) / a**2
        return tuple(float(t) for t in (s, c, ds, dc))


@pytest.mark.parametrize("w", [0.0, 1e-9, 1e-5, 0.3, -1.2, 4.0])
def test_se2_step_matches_ode_integration(w):
    rng = random.Random(1)
    for _ in range(5):
        x, y = rng.uniform(-50, 50), rng.uniform(-50, 50)
        psi = rng.uniform(-math.pi, math.pi)
        v = rng.uniform(-2, 3)
        dt = rng.uniform(0.01, 2.0)
        got = se2_step(x, y, psi, v, w, dt)
        ref = rk4_unicycle(x, y, psi, v, w, dt)
        for g, r in zip(got, ref, strict=True):
            assert abs(g - r) < 1e-10


def test_twist_coeffs_against_high_precision():
    worst = 0.0
    for a in [0.0, 1e-12, 1e-9, 1e-5, 1e-3, 0.05, 0.0999999, 0.1, 0.1000001, 0.5, 2.0, 3.1]:
        for sgn in (1.0, -1.0):
            got = twist_coeffs(sgn * a)
            ref = coeffs_ref(sgn * a)
            worst = max(worst, max(abs(g - r) for g, r in zip(got, ref, strict=True)))
    assert worst < 1e-14


def test_continuity_across_series_threshold():
    eps = 1e-12
    for t in (SERIES_THRESHOLD, -SERIES_THRESHOLD):
        lo = twist_coeffs(t * (1 - eps))
        hi = twist_coeffs(t * (1 + eps))
        for a, b in zip(lo, hi, strict=True):
            assert abs(a - b) < 1e-13
    # the step itself, through w at dt = 1 s
    p_lo = se2_step_jac(1.0, 2.0, 0.4, 1.5, SERIES_THRESHOLD - 1e-13, 1.0)
    p_hi = se2_step_jac(1.0, 2.0, 0.4, 1.5, SERIES_THRESHOLD + 1e-13, 1.0)
    for a, b in zip(p_lo[:3], p_hi[:3], strict=True):
        assert abs(a - b) < 1e-12
    for ra, rb in zip(p_lo[3], p_hi[3], strict=True):
        for a, b in zip(ra, rb, strict=True):
            assert abs(a - b) < 1e-12


def test_zero_twist_and_straight_line():
    assert se2_step(1.0, 2.0, 0.3, 0.0, 0.0, 5.0) == (1.0, 2.0, 0.3)
    x1, y1, p1 = se2_step(0.0, 0.0, math.pi / 2, 2.0, 0.0, 3.0)
    assert abs(x1) < 1e-15 and abs(y1 - 6.0) < 1e-15 and p1 == math.pi / 2
    # a full circle returns to the start
    x1, y1, p1 = se2_step(3.0, -1.0, 0.7, 1.0, 2 * math.pi / 10.0, 10.0)
    assert abs(x1 - 3.0) < 1e-12 and abs(y1 + 1.0) < 1e-12
    assert abs(p1 - (0.7 + 2 * math.pi)) < 1e-12


def test_increment_composes_to_step():
    x, y, psi, v, w, dt = 2.0, -3.0, 2.9, 1.3, 0.7, 0.8
    dx, dy, dpsi = se2_increment(v, w, dt)
    x1, y1, p1 = se2_step(x, y, psi, v, w, dt)
    assert abs(x + math.cos(psi) * dx - math.sin(psi) * dy - x1) < 1e-14
    assert abs(y + math.sin(psi) * dx + math.cos(psi) * dy - y1) < 1e-14
    assert abs(psi + dpsi - p1) < 1e-15


@pytest.mark.parametrize("w", [0.0, 1e-9, 1e-5, 0.0999, 0.1001, -0.7, 3.0])
@pytest.mark.parametrize("psi", [0.0, math.pi - 1e-9, -math.pi + 1e-9, 1.0])
def test_jacobian_central_differences(w, psi):
    args = [4.0, -2.0, psi, 1.7, w, 0.9]
    *val, j = se2_step_jac(*args)
    assert tuple(val) == se2_step(*args)
    h = 1e-6
    for k in range(5):
        ap = list(args)
        am = list(args)
        ap[k] += h
        am[k] -= h
        fp = se2_step(*ap)
        fm = se2_step(*am)
        for r in range(3):
            num = (fp[r] - fm[r]) / (2 * h)
            assert abs(num - j[r][k]) < 1e-8, (r, k, num, j[r][k])


@pytest.mark.parametrize("w", [0.0, 1e-9, 1e-5, 0.05, 0.1, 0.2])
def test_jacobian_wrt_w_exact_near_zero(w):
    """d/dw against a 40-digit reference; finite differences cannot resolve 1e-12."""
    x, y, psi, v, dt = 0.0, 0.0, 0.6, 2.0, 1.0
    *_, j = se2_step_jac(x, y, psi, v, w, dt)
    with mpmath.workdps(40):
        mw = mpmath.mpf(w)

        def f(ww):
            a = ww * dt
            if a == 0:
                s, c = mpmath.mpf(1), mpmath.mpf(0)
            else:
                s, c = mpmath.sin(a) / a, (1 - mpmath.cos(a)) / a
            d = v * dt
            cp, sp = mpmath.cos(psi), mpmath.sin(psi)
            return cp * d * s - sp * d * c, sp * d * s + cp * d * c

        ref = [float(mpmath.diff(lambda ww, i=i: f(ww)[i], mw)) for i in range(2)]
    assert abs(j[0][4] - ref[0]) < 1e-12
    assert abs(j[1][4] - ref[1]) < 1e-12


def test_wrap_angle():
    assert wrap_angle(math.pi) == -math.pi
    assert abs(wrap_angle(3 * math.pi + 0.1) - (-math.pi + 0.1)) < 1e-12
    assert abs(wrap_angle(-0.2) + 0.2) < 1e-15
    for a in [-100.0, -7.0, 0.0, 2.0, 50.0]:
        w = wrap_angle(a)
        assert -math.pi <= w < math.pi
        assert abs(math.remainder(w - a, 2 * math.pi)) < 1e-12
