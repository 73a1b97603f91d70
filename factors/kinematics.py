"""Exact SE(2) constant-twist (unicycle) motion in plain ``math`` scalars.

A differential-drive robot moving with constant forward speed ``v`` (m/s, body x) and constant
yaw rate ``w`` (rad/s, CCW) for ``dt`` seconds from pose (x, y, psi) in the world (local ENU)
frame ends at::

    a      = w dt                                    (rad, heading change)
    dx_b   = v dt S(a),   S(a) = sin(a) / a          (m, body-frame displacement along x_i)
    dy_b   = v dt C(a),   C(a) = (1 - cos a) / a     (m, body-frame displacement along y_i)
    x1     = x + cos(psi) dx_b - sin(psi) dy_b
    y1     = y + sin(psi) dx_b + cos(psi) dy_b
    psi1   = psi + a                                 (NOT wrapped: callers wrap residuals)

This is the closed-form solution of the unicycle ODE, so it is exact for any ``dt`` when the
twist is constant. Used by the factors and by the EKF baseline, hence plain floats and no numpy.

Small-angle handling: S(a) and C(a) are well conditioned in the forms sin(a)/a and
2 sin^2(a/2)/a, but their derivatives S'(a) = (a cos a - sin a)/a^2 and
C'(a) = (a sin a - 1 + cos a)/a^2 lose about 2 log10(1/a) digits to cancellation. For
|a| < ``SERIES_THRESHOLD`` (0.1 rad) all four functions use Taylor series carried far enough that
the truncation error at the threshold is below 1e-16, while the closed forms at 0.1 rad keep
relative errors below ~1e-13. Values and first derivatives are therefore accurate to ~1e-13 on
both sides of the threshold and continuous across it to that accuracy.
"""

from __future__ import annotations

import math

__all__ = [
    "SERIES_THRESHOLD",
    "antenna_position",
    "twist_coeffs",
    "se2_increment",
    "se2_step",
    "se2_step_jac",
    "wrap_angle",
]

# Above this |w dt| the closed forms are used; below it the Taylor series (see module docstring).
SERIES_THRESHOLD = 0.1

_TWO_PI = 2.0 * math.pi
_PI = math.pi
_sin = math.sin
_cos = math.cos


def wrap_angle(a: float) -> float:
    """Wrap an angle (rad) to [-pi, pi); same convention as ``estimation.estimator.wrap_angle``."""
    return (a + _PI) % _TWO_PI - _PI


def antenna_position(
    x: float, y: float, psi: float, lx: float, ly: float
) -> tuple[float, float, float, float]:
    """World position of a point fixed on the body (a GPS antenna's lever arm): the body at
    (x, y) m heading ``psi`` rad (world = local ENU), the point at (lx, ly) m in the body frame
    (x forward, y left): (x, y) + R(psi) (lx, ly).

    Returns (east, north, d east / d psi, d north / d psi); d / d(x, y) is the identity. With
    x = y = 0 it is the lever arm's world-frame offset. Plain floats: the EKF kernels compile
    this same function (``numba.extending.register_jitable``)."""
    c = _cos(psi)
    s = _sin(psi)
    return x + c * lx - s * ly, y + s * lx + c * ly, -s * lx - c * ly, c * lx - s * ly


def twist_coeffs(a: float) -> tuple[float, float, float, float]:
    """S(a), C(a), S'(a), C'(a) for a = w dt (rad); see the module docstring.

    S(a) = sin(a)/a, C(a) = (1 - cos a)/a, and their derivatives with respect to ``a``.
    """
    if -SERIES_THRESHOLD < a < SERIES_THRESHOLD:
        a2 = a * a
        # Horner forms; the first omitted term is < 3e-17 at |a| = 0.1.
        s = 1.0 - a2 / 6.0 * (1.0 - a2 / 20.0 * (1.0 - a2 / 42.0 * (1.0 - a2 / 72.0)))
        c = a / 2.0 * (1.0 - a2 / 12.0 * (1.0 - a2 / 30.0 * (1.0 - a2 / 56.0 * (1.0 - a2 / 90.0))))
        ds = (
            -a / 3.0 * (1.0 - a2 / 10.0 * (1.0 - a2 / 28.0 * (1.0 - a2 / 54.0 * (1.0 - a2 / 88.0))))
        )
        dc = 0.5 * (1.0 - a2 / 4.0 * (1.0 - a2 / 18.0 * (1.0 - a2 / 40.0 * (1.0 - a2 / 70.0))))
        return s, c, ds, dc
    sa = _sin(a)
    ca = _cos(a)
    inv = 1.0 / a
    s = sa * inv
    sh = _sin(0.5 * a)
    c = 2.0 * sh * sh * inv  # 1 - cos a = 2 sin^2(a/2) avoids the cancellation of 1 - cos a
    ds = (ca - s) * inv
    dc = (sa - c) * inv
    return s, c, ds, dc


def se2_increment(v: float, w: float, dt: float) -> tuple[float, float, float]:
    """Body-frame pose increment (dx, dy, dpsi) in (m, m, rad) of a constant twist over ``dt`` s.

    The increment is expressed in the frame of the starting pose: x forward, y left.
    """
    a = w * dt
    s, c, _, _ = twist_coeffs(a)
    d = v * dt
    return d * s, d * c, a


def se2_step(
    x: float, y: float, psi: float, v: float, w: float, dt: float
) -> tuple[float, float, float]:
    """Pose after moving with constant (v, w) for ``dt`` seconds; exact, smooth at w = 0.

    Args are world-frame position (m), heading (rad, CCW from x/east), forward speed (m/s),
    yaw rate (rad/s) and duration (s; may be negative to propagate backwards).
    Returns (x1, y1, psi1); psi1 = psi + w dt is not wrapped.
    """
    a = w * dt
    s, c, _, _ = twist_coeffs(a)
    d = v * dt
    dxb = d * s
    dyb = d * c
    cp = _cos(psi)
    sp = _sin(psi)
    # same operation order as se2_step_jac so both return bit-identical poses
    return x + (cp * dxb - sp * dyb), y + (sp * dxb + cp * dyb), psi + a


def se2_step_jac(
    x: float, y: float, psi: float, v: float, w: float, dt: float
) -> tuple[float, float, float, tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]]:
    """``se2_step`` plus its 3x5 Jacobian with respect to (x, y, psi, v, w).

    Returns (x1, y1, psi1, J) with J a tuple of three rows (for x1, y1, psi1), each a tuple of
    five floats: d/dx, d/dy, d/dpsi, d/dv, d/dw. Units follow the arguments (e.g. dx1/dw in
    m per rad/s). The row for psi1 is (0, 0, 1, 0, dt).
    """
    a = w * dt
    s, c, ds, dc = twist_coeffs(a)
    d = v * dt
    dxb = d * s
    dyb = d * c
    cp = _cos(psi)
    sp = _sin(psi)
    ex = cp * dxb - sp * dyb
    ey = sp * dxb + cp * dyb
    # d(dxb, dyb)/dv = dt (S, C); d(dxb, dyb)/dw = v dt^2 (S', C')
    vs = dt * s
    vc = dt * c
    dd = d * dt
    ws = dd * ds
    wc = dd * dc
    j = (
        (1.0, 0.0, -ey, cp * vs - sp * vc, cp * ws - sp * wc),
        (0.0, 1.0, ex, sp * vs + cp * vc, sp * ws + cp * wc),
        (0.0, 0.0, 1.0, 0.0, dt),
    )
    return x + ex, y + ey, psi + a, j
