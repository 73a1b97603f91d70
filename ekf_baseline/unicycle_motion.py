"""The unicycle EKF's motion model in plain floats: the process noise, the Euler and
constant-twist steps with their Jacobians (also with the odometry scale states), and the
SE(2) pose-error chart (the prediction's F and Q mapped to it, the retraction, the update's
position correction and the inverse chart).

State and conventions: :class:`~ddfuse.ekf_baseline.unicycle.UnicycleEkf` (x, y m world =
local ENU; psi rad CCW from east; v m/s; w rad/s; then calibration and scale states);
derivations and measured effects: docs/design/unicycle_ekf.md. The exact SE(2) step is the
smoother's motion model too (``ddfuse.factors.kinematics.se2_step_jac``). The functions the
compiled kernels (``ddfuse.ekf_baseline.kalman_jit``) call are compiled from this same code
(``numba.extending.register_jitable``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from ddfuse.factors.kinematics import se2_step_jac, twist_coeffs

__all__ = ["ProcessNoise", "unicycle_process_noise", "unicycle_process_noise_terms",
           "twist_densities", "euler_step_jac", "scaled_step_terms", "se2_error_terms",
           "se2_retract", "pose_correct", "se2_log_error"]

_cos = math.cos
_sin = math.sin


@dataclass(frozen=True)
class ProcessNoise:
    """Continuous-time process noise, as sigma densities (square roots of spectral densities).

    A white-noise density q drives a random walk whose sigma after dt seconds is q sqrt(dt).

    acc: m/s^2/sqrt(Hz) -- white forward acceleration driving v. 1.0: a ground robot changes its
        speed by ~1 m/s within ~1 s.
    yaw_acc: rad/s^2/sqrt(Hz) -- white yaw acceleration driving w; same reasoning, ~1 rad/s in 1 s.
        When the config states the twist's walk (robot.twist_walk: speed, yaw_rate, the same
        units), UnicycleEkf takes them; else, when it states the robot's acceleration limits
        (robot.max_accel, max_yaw_accel), :func:`twist_densities` of them.
    pos_long, pos_lat: m/sqrt(s) -- white body-frame velocity error on the position (wheel slip,
        the twist not being constant within a step); lateral smaller for a non-holonomic base.
    heading: rad/sqrt(s) -- white yaw-rate error on the heading.
    gyro_bias: rad/s/sqrt(s) -- gyro-bias random walk (MEMS bias instability order).
    heading_offset: rad/sqrt(s) -- random walk of a heading sensor's offset: a magnetometer
        disturbed by the robot and its surroundings wanders by tens of degrees over minutes
        (0.02 rad/sqrt(s) is 20 degrees 1-sigma over 5 minutes).
    """

    acc: float = 1.0
    yaw_acc: float = 1.0
    pos_long: float = 0.05
    pos_lat: float = 0.02
    heading: float = 0.01
    gyro_bias: float = 1e-4
    heading_offset: float = 0.02


def unicycle_process_noise(
    psi: float, v: float, dt: float, noise: ProcessNoise
) -> tuple[float, ...]:
    """Upper triangle of the 5x5 discrete Q of (x, y, psi, v, w) for a ``dt``-second step.

    Exact integral of the continuous model linearised at (psi, v): x' = v cos psi,
    y' = v sin psi, psi' = w, v' = n_a, w' = n_alpha, giving Phi(s) columns for the noise inputs
    (s cos psi, s sin psi, 0, 1, 0) and (-v sin psi s^2/2, v cos psi s^2/2, s, 0, 1). Slip and
    heading white noise add R(psi) diag(pos_long^2, pos_lat^2) R(psi)^T dt and heading^2 dt.
    Returned in row-major order: Qxx, Qxy, Qxpsi, Qxv, Qxw, Qyy, Qypsi, Qyv, Qyw, Qpp, Qpv, Qpw,
    Qvv, Qvw, Qww (units: products of the state units)."""
    return unicycle_process_noise_terms(psi, v, dt, noise.acc, noise.yaw_acc, noise.pos_long,
                                        noise.pos_lat, noise.heading)


def unicycle_process_noise_terms(
    psi: float, v: float, dt: float, acc: float, yaw_acc: float, pos_long: float,
    pos_lat: float, heading: float
) -> tuple[float, ...]:
    """:func:`unicycle_process_noise` with the :class:`ProcessNoise` densities as floats (same
    units), so that the compiled filter (ddfuse.ekf_baseline.kalman_jit) runs this same code."""
    qa = acc * acc
    qal = yaw_acc * yaw_acc
    pl2 = pos_long * pos_long
    pt2 = pos_lat * pos_lat
    c = _cos(psi)
    s = _sin(psi)
    dt2 = dt * dt
    dt3 = dt2 * dt
    a3 = qa * dt3 / 3.0
    b5 = qal * v * v * dt3 * dt2 / 20.0
    cc, ss, cs = c * c, s * s, c * s
    b4 = qal * v * dt2 * dt2 / 8.0
    b3 = qal * v * dt3 / 6.0
    a2 = qa * dt2 / 2.0
    return (
        a3 * cc + b5 * ss + (pl2 * cc + pt2 * ss) * dt,  # xx
        (a3 - b5 + (pl2 - pt2) * dt) * cs,  # xy
        -b4 * s,  # x psi
        a2 * c,  # x v
        -b3 * s,  # x w
        a3 * ss + b5 * cc + (pl2 * ss + pt2 * cc) * dt,  # yy
        b4 * c,  # y psi
        a2 * s,  # y v
        b3 * c,  # y w
        qal * dt3 / 3.0 + heading * heading * dt,  # psi psi
        0.0,  # psi v
        qal * dt2 / 2.0,  # psi w
        qa * dt,  # v v
        0.0,  # v w
        qal * dt,  # w w
    )


def twist_densities(a_max: float | None, yaw_a_max: float | None, t_v: float | None,
                    t_w: float | None, noise: ProcessNoise) -> ProcessNoise:
    """``noise`` with the white acceleration densities of v and w derived from the robot's
    largest accelerations (m/s^2, rad/s^2) and the sample periods (s) of the measurements of v
    and w (None: that density unchanged).

    Bar-Shalom, Li, Kirubarajan 2001, sec. 6.2.2: in the continuous white-noise acceleration
    model the velocity changes over a sampling period T by the order of sqrt(q T); a twist that
    changes by at most a_max T within one period gives q = a_max^2 T, density a_max sqrt(T)."""
    acc = noise.acc if a_max is None or t_v is None else a_max * math.sqrt(t_v)
    yaw_acc = noise.yaw_acc if yaw_a_max is None or t_w is None else yaw_a_max * math.sqrt(t_w)
    return replace(noise, acc=acc, yaw_acc=yaw_acc)


def euler_step_jac(
    x: float, y: float, psi: float, v: float, w: float, dt: float
) -> tuple[float, float, float, tuple[tuple[float, ...], ...]]:
    """Seed 003's explicit Euler step and its Jacobian (rows x, y, psi; columns x, y, psi, v, w).

    Same return layout as ``ddfuse.factors.kinematics.se2_step_jac``. Position error per step is
    O(v w dt^2) (the chord is taken along the start heading instead of the mean heading)."""
    c = _cos(psi)
    s = _sin(psi)
    d = v * dt
    j = (
        (1.0, 0.0, -d * s, dt * c, 0.0),
        (0.0, 1.0, d * c, dt * s, 0.0),
        (0.0, 0.0, 1.0, 0.0, dt),
    )
    return x + d * c, y + d * s, psi + w * dt, j


def scaled_step_terms(
    x: float, y: float, psi: float, u: float, om: float, kv: float, kw: float, dt: float,
    euler: bool, acc: float, yaw_acc: float, pos_long: float, pos_lat: float, heading: float,
    w_true: bool = False
) -> tuple[float, float, float, tuple[float, ...], tuple[float, ...]]:
    """Prediction with odometry scale states: states 3, 4 are the odometry-frame twist (u, om)
    and the body moves with the true twist (v, w) = (k_v u, k_w om); with ``w_true`` state 4
    is the true yaw rate itself (w = om: k_w does not enter the motion, its F entries are 0 and
    Q's om rows are not divided; module docstring, "Scale states"). ``euler``: the seed's
    Euler step (:func:`euler_step_jac`) instead of the exact SE(2) step; the densities are
    :class:`ProcessNoise`'s as floats (the compiled filter, ekf_baseline.kalman_jit, runs this
    same code).

    Returns the new (x, y, psi), the F entries in the order (x, y, psi rows) d/d(psi, u, om) of
    x and y, d psi/d om, then d/d(k_v, k_w) of x and y and d psi/d k_w, and the 5x5 Q upper
    triangle (``unicycle_process_noise``'s order) of (x, y, psi, u, om): the continuous white
    accelerations act on the true twist, so Q_true's u and om rows and columns are divided by
    k_v and k_w."""
    gw = 1.0 if w_true else kw  # d w / d om
    ow = 0.0 if w_true else om  # d w / d k_w
    v = kv * u
    w = gw * om
    if euler:
        x1, y1, p1, J = euler_step_jac(x, y, psi, v, w, dt)
    else:
        x1, y1, p1, J = se2_step_jac(x, y, psi, v, w, dt)
    j0 = J[0]
    j1 = J[1]
    F = (j0[2], j0[3] * kv, j0[4] * gw, j1[2], j1[3] * kv, j1[4] * gw, dt * gw,
         j0[3] * u, j0[4] * ow, j1[3] * u, j1[4] * ow, dt * ow)
    q = unicycle_process_noise_terms(psi, v, dt, acc, yaw_acc, pos_long, pos_lat, heading)
    a = 1.0 / kv
    b = 1.0 / gw
    q = (q[0], q[1], q[2], q[3] * a, q[4] * b,
         q[5], q[6], q[7] * a, q[8] * b,
         q[9], q[10] * a, q[11] * b,
         q[12] * a * a, q[13] * a * b, q[14] * b * b)
    return x1, y1, p1, F, q


def se2_error_terms(p0: float, p1: float, F: tuple[float, ...], q: tuple[float, ...]
                    ) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The prediction's F and Q for the SE(2) exponential-coordinate pose error (module
    docstring, "Pose error"): world-frame ones (``scaled_step_terms``' F layout, 12 entries,
    and Q's 15-entry upper triangle of (x, y, psi, u, om)) of a step from heading ``p0`` to
    ``p1`` (rad) mapped by the chart's Jacobians, F_xi = A1^-1 F A0, Q_xi = A1^-1 Q A1^-T,
    A = d(x, y, psi) / d(rho_x, rho_y, theta) at xi = 0 = blockdiag(R(psi), 1).

    For the exact step this is the Lie-group Jacobian: the pose block is the adjoint
    Ad(Exp(-tau dt)) (rotation R(p0 - p1), translation column R(p1)^T dF/dpsi), the twist
    columns the right Jacobian J_r(tau dt) dt times the scales. Returns (F' in F's layout, then
    the pose block's (0, 0), (0, 1), (1, 0), (1, 1) entries; Q' in Q's order)."""
    c = _cos(p1)
    s = _sin(p1)
    cd = _cos(p0 - p1)
    sd = _sin(p0 - p1)
    Fo = (c * F[0] + s * F[3], c * F[1] + s * F[4], c * F[2] + s * F[5],
          -s * F[0] + c * F[3], -s * F[1] + c * F[4], -s * F[2] + c * F[5], F[6],
          c * F[7] + s * F[9], c * F[8] + s * F[10], -s * F[7] + c * F[9],
          -s * F[8] + c * F[10], F[11], cd, -sd, sd, cd)
    a, b, d = q[0], q[1], q[5]
    cc, ss, cs = c * c, s * s, c * s
    qo = (cc * a + 2.0 * cs * b + ss * d,  # xx
          cs * (d - a) + (cc - ss) * b,  # xy
          c * q[2] + s * q[6], c * q[3] + s * q[7], c * q[4] + s * q[8],  # x psi, x u, x om
          ss * a - 2.0 * cs * b + cc * d,  # yy
          -s * q[2] + c * q[6], -s * q[3] + c * q[7], -s * q[4] + c * q[8],  # y psi, u, om
          q[9], q[10], q[11], q[12], q[13], q[14])
    return Fo, qo


def se2_retract(x: float, y: float, psi: float, d0: float, d1: float, d2: float
                ) -> tuple[float, float, float]:
    """The pose (x m, y m, psi rad, world) moved by the body-frame exponential coordinates
    (d0 m, d1 m, d2 rad): X Exp(d), Exp(rho, theta) = (R(theta), V(theta) rho),
    V = [[S, -C], [C, S]], S = sin(theta)/theta, C = (1 - cos theta)/theta. psi not wrapped."""
    sa, ca, _, _ = twist_coeffs(d2)
    tx = sa * d0 - ca * d1
    ty = ca * d0 + sa * d1
    c = _cos(psi)
    s = _sin(psi)
    return x + c * tx - s * ty, y + s * tx + c * ty, psi + d2


def pose_correct(x: float, y: float, psi: float, d0: float, d1: float) -> tuple[float, float]:
    """The position (m, world) after an update's correction (d0, d1) m of the body-frame
    position error rho at heading ``psi`` (rad, the prior's): (x, y) + R(psi) (d0, d1), the
    chart the measurement models are linearised in (the heading correction is added to psi).
    Not the exponential map's (x, y) + R(psi) V(d_theta) (d0, d1): a large correction (a gate
    lock-out's recovery, with the heading unknown) would then land off the measured position
    (module docstring, "Pose error"); the two agree to first order."""
    c = _cos(psi)
    s = _sin(psi)
    return x + c * d0 - s * d1, y + s * d0 + c * d1


def se2_log_error(dx: float, dy: float, dpsi: float, psi: float) -> tuple[float, float, float]:
    """xi = Log(X_hat^-1 X_true) of a true pose that differs from the estimate (heading ``psi``
    rad) by the world-frame (dx m, dy m) and the wrapped heading difference ``dpsi`` rad:
    rho = V(dpsi)^-1 R(psi)^T (dx, dy), theta = dpsi. The inverse of :func:`se2_retract`."""
    c = _cos(psi)
    s = _sin(psi)
    bx = c * dx + s * dy
    by = -s * dx + c * dy
    sa, ca, _, _ = twist_coeffs(dpsi)
    det = sa * sa + ca * ca
    return (sa * bx + ca * by) / det, (-ca * bx + sa * by) / det, dpsi
