"""The unicycle EKF's measurement models, written once for both of its paths.

Each ``*_rows`` function writes one measurement's innovation y = z - h(x), its Jacobian rows
d h / d x and its covariance into rows ``nr``.. of the caller's arrays ``H`` (>= nr + m, n),
``y`` and ``R`` (square), whose entries there are zero on entry, and returns the number of rows
m. The state ``x`` (n,) is that of :class:`~ddfuse.ekf_baseline.unicycle.UnicycleEkf` (its
module docstring: state, scale states, "Measurements" and "Pose error"): ``ks`` the index of
k_v (k_w follows; -1 without scale states), ``w_true`` whether state 4 is the true yaw rate
(a gyro is fused) rather than the odometry's, ``lie`` whether the pose error is the body-frame
SE(2) one. Units: m, rad, s; angles' innovations wrapped to [-pi, pi).

Plain floats and array element writes only: the reference path calls them on numpy arrays
(``UnicycleEkf._apply``), the compiled kernels (``ddfuse.ekf_baseline.kalman_jit``) compile
these same functions (``numba.extending.register_jitable``).
"""

from __future__ import annotations

import math

from ddfuse.factors.kinematics import antenna_position, se2_step_jac

__all__ = ["delayed_gps_terms", "gyro_rows", "heading_rows", "speed_rows", "yaw_rate_rows",
           "gps_rows", "wheel_rows"]

_PI = math.pi
_TWO_PI = 2.0 * math.pi


def delayed_gps_terms(
    x: float, y: float, psi: float, u: float, om: float, kv: float, kw: float, lx: float,
    ly: float, d: float, w_true: bool = False
) -> tuple[float, ...]:
    """The GPS antenna ``d`` s before the state's time (lever arm (lx, ly) m, body frame),
    reached by the exact constant-twist step backwards with the true twist (k_v u, k_w om)
    (k_v = k_w = 1 without scale states; with ``w_true`` the yaw rate is om itself, as in
    ``unicycle_motion.scaled_step_terms``), and its Jacobian.

    Returns (east, north, de/dpsi, de/du, de/dom, de/dk_v, de/dk_w, dn/dpsi, dn/du, dn/dom,
    dn/dk_v, dn/dk_w); d/dx of east and d/dy of north are 1, the rest 0."""
    gw = 1.0 if w_true else kw
    ow = 0.0 if w_true else om
    xb, yb, pb, J = se2_step_jac(x, y, psi, kv * u, gw * om, -d)
    e, n, ae, an = antenna_position(xb, yb, pb, lx, ly)
    je = J[0]
    jn = J[1]
    # d psi(t - d) / d (psi, w) = (1, -d); w.r.t. the true twist (v, w) = (k_v u, k_w om)
    de_v = je[3]
    de_w = je[4] - d * ae
    dn_v = jn[3]
    dn_w = jn[4] - d * an
    return (e, n,
            je[2] + ae, de_v * kv, de_w * gw, de_v * u, de_w * ow,
            jn[2] + an, dn_v * kv, dn_w * gw, dn_v * u, dn_w * ow)


def gyro_rows(x, ks, w_true, bi, bias, z, r, H, y, R, nr):
    """A gyro's yaw rate ``z`` (rad/s, variance ``r``): h = w + b, the bias b the state ``bi``
    (-1: the configured ``bias``); a gyro the scale states' convention leaves on the
    odometry-frame yaw rate om sees k_w om + b."""
    b = bias if bi < 0 else x[bi]
    if ks < 0 or w_true:
        y[nr] = z - (x[4] + b)
        H[nr, 4] = 1.0
    else:  # the gyro sees the true yaw rate k_w om (+ bias)
        kw = x[ks + 1]
        om = x[4]
        y[nr] = z - (kw * om + b)
        H[nr, 4] = kw
        H[nr, ks + 1] = om
    if bi >= 0:
        H[nr, bi] = 1.0
    R[nr, nr] = r
    return 1


def heading_rows(x, hi, hoff, z, r, H, y, R, nr):
    """A heading ``z`` (rad): h = wrap(psi + offset), the offset the state ``hi`` (-1: the
    configured ``hoff``); the innovation wrapped."""
    if hi < 0:
        hpred = x[2] + hoff
    else:
        hpred = x[2] + x[hi]
        H[nr, hi] = 1.0
    H[nr, 2] = 1.0
    y[nr] = (z - hpred + _PI) % _TWO_PI - _PI
    R[nr, nr] = r
    return 1


def speed_rows(x, z, r, H, y, R, nr):
    """The odometry's forward speed ``z`` (m/s): h = v (with scale states the odometry-frame
    speed itself)."""
    y[nr] = z - x[3]
    H[nr, 3] = 1.0
    R[nr, nr] = r
    return 1


def yaw_rate_rows(x, ks, w_true, z, r, H, y, R, nr):
    """The odometry's yaw rate ``z`` (rad/s): h = w, or w / k_w when state 4 is the true yaw
    rate."""
    if ks >= 0 and w_true:
        kw = x[ks + 1]
        y[nr] = z - x[4] / kw
        H[nr, 4] = 1.0 / kw
        H[nr, ks + 1] = -x[4] / (kw * kw)
    else:
        y[nr] = z - x[4]
        H[nr, 4] = 1.0
    R[nr, nr] = r
    return 1


def gps_rows(x, ks, w_true, lie, lx, ly, d, z0, z1, r0, r1, r01, r10, H, y, R, nr):
    """A fix (east ``z0``, north ``z1``, m; covariance [[r0, r01], [r10, r1]]): the antenna
    (lever arm (lx, ly) m) at the fix's time, ``d`` s before the state's, reached by the exact
    constant-twist step backwards (:func:`delayed_gps_terms`). With the body-frame pose error
    (``lie``) d(east, north) / d(rho_x, rho_y) = R(psi)."""
    if d == 0.0:
        e, n, de, dn = antenna_position(x[0], x[1], x[2], lx, ly)
        y[nr] = z0 - e
        y[nr + 1] = z1 - n
        H[nr, 0] = 1.0
        H[nr + 1, 1] = 1.0
        if not (lx == 0.0 and ly == 0.0):
            H[nr, 2] = de
            H[nr + 1, 2] = dn
    else:
        kv = 1.0 if ks < 0 else x[ks]
        kw = 1.0 if ks < 0 else x[ks + 1]
        g = delayed_gps_terms(x[0], x[1], x[2], x[3], x[4], kv, kw, lx, ly, d, w_true)
        y[nr] = z0 - g[0]
        y[nr + 1] = z1 - g[1]
        H[nr, 0] = 1.0
        H[nr, 2] = g[2]
        H[nr, 3] = g[3]
        H[nr, 4] = g[4]
        H[nr + 1, 1] = 1.0
        H[nr + 1, 2] = g[7]
        H[nr + 1, 3] = g[8]
        H[nr + 1, 4] = g[9]
        if ks >= 0:
            H[nr, ks] = g[5]
            H[nr, ks + 1] = g[6]
            H[nr + 1, ks] = g[10]
            H[nr + 1, ks + 1] = g[11]
    if lie:
        c = math.cos(x[2])
        sn = math.sin(x[2])
        H[nr, 0] = c
        H[nr, 1] = -sn
        H[nr + 1, 0] = sn
        H[nr + 1, 1] = c
    R[nr, nr] = r0
    R[nr, nr + 1] = r01
    R[nr + 1, nr] = r10
    R[nr + 1, nr + 1] = r1
    return 2


def wheel_rows(x, ks, w_true, rw, track, z0, z1, r0, r1, H, y, R, nr):
    """Wheel speeds (left ``z0``, right ``z1``, rad/s): the state's (odometry-frame) twist
    through the nominal geometry (wheel radius ``rw``, ``track`` width, m),
    ((v - w L/2) / r, (v + w L/2) / r), w / k_w when state 4 is the true yaw rate."""
    k = 0.5 * track / rw
    if ks >= 0 and w_true:  # (the odometry-frame yaw rate is w / k_w)
        kw = x[ks + 1]
        k /= kw
        dk = x[4] * k / kw
        H[nr, ks + 1] = dk
        H[nr + 1, ks + 1] = -dk
    vr = x[3] / rw
    wr = x[4] * k
    H[nr, 3] = 1.0 / rw
    H[nr, 4] = -k
    H[nr + 1, 3] = 1.0 / rw
    H[nr + 1, 4] = k
    y[nr] = z0 - (vr - wr)
    y[nr + 1] = z1 - (vr + wr)
    R[nr, nr] = r0
    R[nr + 1, nr + 1] = r1
    return 2
