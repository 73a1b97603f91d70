"""The landmark EKFs' measurement and odometry-driven motion models, written once for both of
their paths.

Plain floats and array element writes only: the Python filters (``ekf_baseline.landmark``) call
them as they are, the compiled kernels (``ddfuse.ekf_baseline.kalman_jit``) compile these same
functions (``numba.extending.register_jitable``, ``kalman_jit_layout``). Frames and units as in
``ekf_baseline.landmark``: pose (x m, y m, psi rad) in the map frame, psi CCW from its x axis;
a bearing in the body frame, CCW from forward x, wrapped to [-pi, pi).
"""

from __future__ import annotations

import math

from ddfuse.ekf_baseline.unicycle_motion import euler_step_jac
from ddfuse.factors.kinematics import se2_step_jac

__all__ = ["MIN_RANGE", "range_bearing_terms", "landmark_rows", "odometry_step",
           "odometry_noise_terms"]

_PI = math.pi
_TWO_PI = 2.0 * math.pi
MIN_RANGE = 1e-6  # m: a sighting from (or a landmark at) the body origin has no bearing


def range_bearing_terms(px: float, py: float, psi: float, lx: float, ly: float):
    """Predicted range and bearing of the landmark (lx, ly) from the pose (px, py, psi), and the
    terms of their Jacobian: (r, b, dx / r, dy / r, dy / r^2, dx / r^2) with (dx, dy) the
    landmark minus the position, so that d r / d (px, py) = -(dx, dy) / r and
    d b / d (px, py, psi) = (dy, -dx) / r^2, -1 (the landmark's columns: minus the position's).
    When r < MIN_RANGE the bearing is undefined: (r, 0, 0, 0, 0, 0), the caller checks r."""
    dx = lx - px
    dy = ly - py
    q = dx * dx + dy * dy
    r = math.sqrt(q)
    if r < MIN_RANGE:
        return r, 0.0, 0.0, 0.0, 0.0, 0.0
    b = (math.atan2(dy, dx) - psi + _PI) % _TWO_PI - _PI
    return r, b, dx / r, dy / r, dy / q, dx / q


def landmark_rows(x, lx, ly, with_bearing, zr, zb, rr, rb, H, y, R, nr):
    """One sighting of the known landmark (lx, ly) m: range ``zr`` (m, variance ``rr``) and,
    ``with_bearing``, bearing ``zb`` (rad, variance ``rb``), as the innovation y = z - h(x)
    (the bearing's wrapped), its rows of d h / d x (pose columns 0..2) and R, written at row
    ``nr`` of ``H``, ``y``, ``R`` (zero there on entry; ``unicycle_measurements``' contract).
    Returns the number of rows, 0 when the landmark is at the body origin (r < MIN_RANGE)."""
    r, b, ar, br, aq, bq = range_bearing_terms(x[0], x[1], x[2], lx, ly)
    if r < MIN_RANGE:
        return 0
    y[nr] = zr - r
    H[nr, 0] = -ar
    H[nr, 1] = -br
    R[nr, nr] = rr
    if not with_bearing:
        return 1
    y[nr + 1] = (zb - b + _PI) % _TWO_PI - _PI
    H[nr + 1, 0] = aq
    H[nr + 1, 1] = -bq
    H[nr + 1, 2] = -1.0
    R[nr + 1, nr + 1] = rb
    return 2


def odometry_step(x: float, y: float, psi: float, v: float, w: float, dt: float, euler: bool):
    """The pose after ``dt`` s of the twist (v m/s, w rad/s): the constant-twist arc
    (``se2_step_jac``) or, ``euler``, the seed's first-order step (``euler_step_jac``);
    (x1, y1, psi1 unwrapped, J) with J's rows d (x1, y1, psi1) / d (x, y, psi, v, w)."""
    if euler:
        return euler_step_jac(x, y, psi, v, w, dt)
    return se2_step_jac(x, y, psi, v, w, dt)


def odometry_noise_terms(J, kv: float, kw: float, v_var: float, w_var: float, tau: float,
                         dt: float, psi: float, ql: float, qt: float, qh: float, slip: bool):
    """The pose's process noise over a step of ``dt`` s (m^2, rad^2; upper triangle
    (q00, q01, q02, q11, q12, q22) of x, y, psi): the odometry's error, white from sample to
    sample and held for its period ``tau`` s, G diag(kv^2 v_var, kw^2 w_var) G^T tau / dt with
    G = J[:, 3:5] (``odometry_step`` at the scaled twist); with ``slip``, the robot's white
    body-frame velocity (``ql`` longitudinal, ``qt`` lateral, m^2/s) and yaw-rate (``qh``,
    rad^2/s) noise over the step, rotated into the map frame at the heading ``psi`` it starts
    from (``ekf_baseline.landmark``'s module docstring)."""
    a0 = kv * kv * v_var
    a1 = kw * kw * w_var
    f = tau / dt
    g00, g01 = J[0][3] * a0, J[0][4] * a1
    g10, g11 = J[1][3] * a0, J[1][4] * a1
    g20, g21 = J[2][3] * a0, J[2][4] * a1
    q00 = (g00 * J[0][3] + g01 * J[0][4]) * f
    q01 = (g00 * J[1][3] + g01 * J[1][4]) * f
    q02 = (g00 * J[2][3] + g01 * J[2][4]) * f
    q11 = (g10 * J[1][3] + g11 * J[1][4]) * f
    q12 = (g10 * J[2][3] + g11 * J[2][4]) * f
    q22 = (g20 * J[2][3] + g21 * J[2][4]) * f
    if slip:
        c = math.cos(psi)
        s = math.sin(psi)
        q00 += dt * (c * c * ql + s * s * qt)
        q01 += dt * (c * s * (ql - qt))
        q11 += dt * (s * s * ql + c * c * qt)
        q22 += dt * qh
    return q00, q01, q02, q11, q12, q22
