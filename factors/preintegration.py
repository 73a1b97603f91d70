"""Preintegrated wheel-speed + gyro odometry between two keyframes (the fast path).

Accumulation (``WheelGyroPreintegration``). Samples (dt, v_meas, w_gyro, var_v, var_w, gain, w_odo)
are held constant over their ``dt`` (zero-order hold) and integrated exactly as constant twists
(``kinematics.se2_step_jac``) into the pose of keyframe j expressed in the frame of keyframe i::

    delta = (dx, dy, dpsi)   m, m, rad;  (dx, dy) along keyframe i's body x (forward) and y (left)
    v     = k_v,lin v_meas                              (m/s)
    w     = w_gyro - g bg_lin + k_w,lin w_odo           (rad/s)

with ``bg_lin``, ``kv_lin``, ``kw_lin`` the linearisation points of the gyro bias and the
odometry's speed and yaw-rate scales (``ddfuse.factors.state``: true speed = k_v x odometry speed).
``w_gyro`` is the part of the yaw rate that carries the gyro bias with gain g (1 for a raw gyro
reading, the gyro's weight when a gyro and an odometry yaw rate are fused per sample), ``w_odo``
the part that carries the odometry's scale (the odometry's weight times its yaw rate; 0 for a
gyro alone); ``var_v`` (m/s)^2 and ``var_w`` (rad/s)^2 are each held sample's variances. The
increment carries its 3x3 covariance and its Jacobians J_bg, J_kv, J_kw (3-vectors) for the
first-order correction ``delta(bg, k) = delta + J_bg db + J_kv dk_v + J_kw dk_w``; far from the
linearisation points (a few sigma of their priors) call ``reintegrate``.

Factor (``preintegrated_factor``, 2 keys i and j, 9-D error)::

    e[0:2] = R(psi_i)^T (p_j - p_i) - (dx, dy)(bg_i, k_i)       m
    e[2]   = wrap(psi_j - psi_i - dpsi(bg_i, k_i))               rad
    e[3]   = v_j - k_v,j v_last                                  m/s
    e[4]   = w_j + g_last bg_j - w_gyro,last - k_w,j w_odo,last  rad/s
    e[5]   = bg_j - bg_i                                         rad/s
    e[6]   = wrap(hoff_j - hoff_i)                               rad
    e[7:9] = k_j - k_i                                           1

Rows 3 and 4 tie the keyframe-j twist to the interval's LAST sample; rows 5 to 8 are random
walks. The 9x9 covariance is block diagonal: [cov + extra pose noise, var_v, var_w, q_bg^2 T,
q_hoff^2 T, q_k^2 T, q_k^2 T], with T the integrated time.

Design notes and measurements: docs/design/preintegration.md
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from ddfuse.factors.kinematics import se2_step_jac
from ddfuse.factors.state import BG, DIM, KV, KW

__all__ = ["WheelGyroPreintegration", "integrate_step", "preintegrated_factor"]

_PI = math.pi
# what ``preintegrated_factor(record=...)`` records, in order (the names of its closure)
RECORD_FIELDS = ("ddx", "ddy", "ddp", "jx", "jy", "jp", "vx", "vy", "wx", "wy", "wp", "bl", "kvl",
                 "kwl", "zv", "zw", "zo", "zg")
_TWO_PI = 2.0 * math.pi


def integrate_step(dx, dy, dpsi, c_xx, c_xy, c_xp, c_yy, c_yp, c_pp, j_x, j_y, j_p, kv_x, kv_y,
                   kw_x, kw_y, kw_p, bg_lin, kv_lin, kw_lin, dt, v, w_gyro, var_v, var_w, gain,
                   w_odo):
    """One sample of the preintegration, in plain floats: the increment (dx, dy m, dpsi rad),
    its covariance's upper triangle (c_xx ... c_pp), its Jacobians with respect to the gyro bias
    (j_x, j_y, j_p) and the odometry scales (kv_x, kv_y; kw_x, kw_y, kw_p) before the sample,
    the linearisation points (bg_lin rad/s, kv_lin, kw_lin), and the sample as
    :meth:`WheelGyroPreintegration.integrate` takes it. Returns those 17 quantities after it,
    in the same order. The reference class and the compiled kernel
    (``ddfuse.factors.preintegration_jit``, ``register_jitable``) both call it."""
    x1, y1, p1, j = se2_step_jac(dx, dy, dpsi, kv_lin * v,
                                 w_gyro - gain * bg_lin + kw_lin * w_odo, dt)
    j0, j1 = j[0], j[1]
    a = j0[2]  # -(y1 - y): d x1 / d dpsi
    b = j1[2]  # x1 - x:    d y1 / d dpsi
    gvx, gvy = j0[3], j1[3]
    gwx, gwy, gwp = j0[4], j1[4], dt
    vv = var_v * kv_lin * kv_lin  # the sample's noise, scaled like the speed
    # F cov F^T with F = [[1, 0, a], [0, 1, b], [0, 0, 1]], then the sample's noise
    n_xx = c_xx + 2.0 * a * c_xp + a * a * c_pp + gvx * gvx * vv + gwx * gwx * var_w
    n_xy = c_xy + a * c_yp + b * c_xp + a * b * c_pp + gvx * gvy * vv + gwx * gwy * var_w
    n_xp = c_xp + a * c_pp + gwx * gwp * var_w
    n_yy = c_yy + 2.0 * b * c_yp + b * b * c_pp + gvy * gvy * vv + gwy * gwy * var_w
    n_yp = c_yp + b * c_pp + gwy * gwp * var_w
    n_pp = c_pp + gwp * gwp * var_w
    # Jacobians wrt bias and scales: F J + G (d twist / d parameter)
    return (x1, y1, p1, n_xx, n_xy, n_xp, n_yy, n_yp, n_pp,
            j_x + (a * j_p - gain * gwx), j_y + (b * j_p - gain * gwy), j_p - gain * gwp,
            kv_x + v * gvx, kv_y + v * gvy,
            kw_x + (a * kw_p + w_odo * gwx), kw_y + (b * kw_p + w_odo * gwy), kw_p + w_odo * gwp)


class WheelGyroPreintegration:
    """Accumulates wheel speed + gyro samples into an SE(2) increment; see the module docstring.

    All state is plain Python floats (``__slots__``): ``preintegration_jit`` mirrors it slot by
    slot.
    """

    __slots__ = (
        "bg_lin", "kv_lin", "kw_lin",
        "dx", "dy", "dpsi", "dt_total",
        "c_xx", "c_xy", "c_xp", "c_yy", "c_yp", "c_pp",
        "j_x", "j_y", "j_p",
        "kv_x", "kv_y",
        "kw_x", "kw_y", "kw_p",
        "last_v", "last_w_gyro", "last_w_odo", "last_var_v", "last_var_w", "last_gain",
        "n", "samples", "keep_samples",
    )

    def __init__(self, bg_lin: float = 0.0, keep_samples: bool = True, kv_lin: float = 1.0,
                 kw_lin: float = 1.0) -> None:
        """``bg_lin``: gyro-bias linearisation point, rad/s; ``kv_lin``, ``kw_lin``: the
        odometry scales' (unitless). ``keep_samples``: store the samples so that
        ``reintegrate`` can replay them with new linearisation points."""
        self.keep_samples = keep_samples
        self.kv_lin = float(kv_lin)
        self.kw_lin = float(kw_lin)
        self.reset(bg_lin)

    def reset(self, bg_lin: float | None = None, kv_lin: float | None = None,
              kw_lin: float | None = None) -> None:
        """Start a new interval, optionally with new linearisation points (bias rad/s, scales)."""
        if bg_lin is not None:
            self.bg_lin = float(bg_lin)
        if kv_lin is not None:
            self.kv_lin = float(kv_lin)
        if kw_lin is not None:
            self.kw_lin = float(kw_lin)
        self.dx = self.dy = self.dpsi = 0.0
        self.dt_total = 0.0
        self.c_xx = self.c_xy = self.c_xp = self.c_yy = self.c_yp = self.c_pp = 0.0
        self.j_x = self.j_y = self.j_p = 0.0
        self.kv_x = self.kv_y = 0.0  # the speed scale does not turn the robot
        self.kw_x = self.kw_y = self.kw_p = 0.0
        self.last_v = self.last_w_gyro = self.last_w_odo = 0.0
        self.last_var_v = self.last_var_w = 0.0
        self.last_gain = 1.0
        self.n = 0
        self.samples: list[tuple[float, ...]] = []

    def integrate(self, dt: float, v: float, w_gyro: float, var_v: float, var_w: float,
                  gain: float = 1.0, w_odo: float = 0.0) -> None:
        """Add one sample held for ``dt`` s: odometry speed ``v`` m/s; the yaw rate as measured
        (biases and scales not removed) split into ``w_gyro`` rad/s, which carries ``gain`` times
        the gyro bias (1 raw gyro, 0 none), and ``w_odo`` rad/s, which carries the odometry's
        yaw-rate scale; their variances (m/s)^2 and (rad/s)^2 over this ``dt``."""
        if self.keep_samples:
            self.samples.append((dt, v, w_gyro, var_v, var_w, gain, w_odo))
        (self.dx, self.dy, self.dpsi, self.c_xx, self.c_xy, self.c_xp, self.c_yy, self.c_yp,
         self.c_pp, self.j_x, self.j_y, self.j_p, self.kv_x, self.kv_y, self.kw_x, self.kw_y,
         self.kw_p) = integrate_step(
            self.dx, self.dy, self.dpsi, self.c_xx, self.c_xy, self.c_xp, self.c_yy, self.c_yp,
            self.c_pp, self.j_x, self.j_y, self.j_p, self.kv_x, self.kv_y, self.kw_x, self.kw_y,
            self.kw_p, self.bg_lin, self.kv_lin, self.kw_lin,
            dt, v, w_gyro, var_v, var_w, gain, w_odo)
        self.dt_total += dt
        self.last_v = v
        self.last_w_gyro = w_gyro
        self.last_w_odo = w_odo
        self.last_var_v = var_v
        self.last_var_w = var_w
        self.last_gain = gain
        self.n += 1

    def reintegrate(self, bg_lin: float, kv_lin: float | None = None,
                    kw_lin: float | None = None) -> None:
        """Replay the stored samples with new linearisation points (rad/s; scales)."""
        if not self.keep_samples:
            raise RuntimeError("reintegrate needs keep_samples=True")
        samples = self.samples
        self.reset(bg_lin, kv_lin, kw_lin)
        for s in samples:
            self.integrate(*s)

    @property
    def delta(self) -> tuple[float, float, float]:
        """(dx m, dy m, dpsi rad) at the linearisation points, in keyframe i's body frame."""
        return self.dx, self.dy, self.dpsi

    def delta_at(self, bg: float, kv: float | None = None,
                 kw: float | None = None) -> tuple[float, float, float]:
        """First-order corrected increment for gyro bias ``bg`` (rad/s) and the odometry
        scales ``kv``, ``kw`` (default: their linearisation points)."""
        db = bg - self.bg_lin
        dv = 0.0 if kv is None else kv - self.kv_lin
        dw = 0.0 if kw is None else kw - self.kw_lin
        return (self.dx + self.j_x * db + self.kv_x * dv + self.kw_x * dw,
                self.dy + self.j_y * db + self.kv_y * dv + self.kw_y * dw,
                self.dpsi + self.j_p * db + self.kw_p * dw)

    def yaw_terms(self) -> tuple[float, float, float, float]:
        """(dpsi rad, j_p, kw_p, c_pp rad^2): the preintegrated yaw, its first-order terms in
        the gyro bias and the yaw-rate scale, and its variance (what a heading sample carried
        back to keyframe i reads)."""
        return self.dpsi, self.j_p, self.kw_p, self.c_pp

    def partial(self, bg: float, kv: float, kw: float) -> tuple[tuple[float, float, float],
                                                                list[list[float]]]:
        """``delta_at(bg, kv, kw)`` and ``covariance`` as three row lists, together: what an
        output between keyframes composes with the keyframe (one read of the compiled twin's
        array instead of a ``frozen`` copy)."""
        return self.delta_at(bg, kv, kw), [[self.c_xx, self.c_xy, self.c_xp],
                                           [self.c_xy, self.c_yy, self.c_yp],
                                           [self.c_xp, self.c_yp, self.c_pp]]

    @property
    def bias_jacobian(self) -> tuple[float, float, float]:
        """d(dx, dy, dpsi)/d bg, in (m, m, rad) per rad/s."""
        return self.j_x, self.j_y, self.j_p

    @property
    def scale_jacobians(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """d(dx, dy, dpsi)/d k_v and d(dx, dy, dpsi)/d k_w, (m, m, rad) per unit scale."""
        return (self.kv_x, self.kv_y, 0.0), (self.kw_x, self.kw_y, self.kw_p)

    @property
    def covariance(self) -> np.ndarray:
        """3x3 covariance of (dx, dy, dpsi), (m, m, rad), from the sample noise only."""
        return np.array(
            (
                (self.c_xx, self.c_xy, self.c_xp),
                (self.c_xy, self.c_yy, self.c_yp),
                (self.c_xp, self.c_yp, self.c_pp),
            )
        )

    def last_rates(self, state) -> tuple[float, float]:
        """(v m/s, w rad/s) of the last sample with the biases and scales of ``state``."""
        kv, kw = float(state[KV]), float(state[KW])
        return (kv * self.last_v,
                self.last_w_gyro - self.last_gain * float(state[BG]) + kw * self.last_w_odo)

    def predict(self, state_i) -> np.ndarray:
        """Initial guess for the state at keyframe j from the state at i (array-like, (9,)).

        Pose = pose_i composed with the corrected delta; v, w from the last sample (with the
        biases and scales of state_i); bg, hoff and the scales carried over. ``psi`` is not
        wrapped.
        """
        x, y, psi, _, _, bg, hoff, kv, kw = (float(t) for t in state_i)
        dx, dy, dp = self.delta_at(bg, kv, kw)
        c = math.cos(psi)
        s = math.sin(psi)
        v, w = self.last_rates(state_i)
        return np.array((x + c * dx - s * dy, y + s * dx + c * dy, psi + dp, v, w, bg, hoff,
                         kv, kw))

    def pose2_between(self, bg: float | None = None) -> tuple[gtsam.Pose2, np.ndarray]:
        """The increment as a ``gtsam.Pose2`` and its 3x3 covariance in Pose2's tangent space.

        For a Pose2-keyed graph with ``gtsam.BetweenFactorPose2`` (bias held fixed at ``bg``,
        default ``bg_lin``; scales at their linearisation points). Pose2 perturbations are
        body-frame at the increment, so the translation block is rotated by R(dpsi)^T.
        """
        dx, dy, dp = self.delta_at(self.bg_lin if bg is None else bg)
        c = math.cos(dp)
        s = math.sin(dp)
        rot = np.array(((c, s, 0.0), (-s, c, 0.0), (0.0, 0.0, 1.0)))
        return gtsam.Pose2(dx, dy, dp), rot @ self.covariance @ rot.T


def preintegrated_factor(
    key_i: int,
    key_j: int,
    pim: WheelGyroPreintegration,
    gyro_bias_rw: float = 1e-4,
    heading_offset_rw: float = 1e-4,
    pose_noise: tuple[float, float, float] = (0.01, 0.01, 0.001),
    noise: gtsam.noiseModel.Base | None = None,
    scale_rw: float = 1e-5,
    record: list | None = None,
) -> gtsam.CustomFactor:
    """Preintegrated wheel+gyro factor between keyframe states ``key_i`` and ``key_j``.

    Args:
        key_i, key_j: 9-vector state keys (``ddfuse.factors.state``).
        pim: the accumulated interval (at least one sample). Its values are copied: the object can
            be reset and reused afterwards.
        gyro_bias_rw: gyro-bias random-walk density, rad/s/sqrt(s).
        heading_offset_rw: heading-offset random-walk density, rad/sqrt(s).
        pose_noise: extra white-noise densities added to the pose rows, (m/sqrt(s), m/sqrt(s),
            rad/sqrt(s)) in keyframe i's frame: unmodelled slip, and a floor that keeps the
            covariance invertible when the robot stands still.
        noise: a 9-D noise model that replaces the computed one (e.g. robust), optional.
        scale_rw: random-walk density of the odometry scales, 1/sqrt(s): constants in truth, a
            floor that keeps the covariance invertible.
        record: when given, ``(factor, noise model, constants)`` is appended to it, the
            constants in the order of ``RECORD_FIELDS`` (the batch evaluates these factors
            together with numpy: ``estimation.smoother.batch_factors``).

    Returns a ``gtsam.CustomFactor`` with the 9-D error of the module docstring.
    """
    if pim.n == 0:
        raise ValueError("preintegration has no samples")
    t = pim.dt_total
    if noise is None:
        cov = np.zeros((DIM, DIM))
        cov[:3, :3] = pim.covariance
        cov[0, 0] += pose_noise[0] ** 2 * t
        cov[1, 1] += pose_noise[1] ** 2 * t
        cov[2, 2] += pose_noise[2] ** 2 * t
        cov[3, 3] = pim.last_var_v * pim.kv_lin**2
        cov[4, 4] = pim.last_var_w
        cov[5, 5] = gyro_bias_rw**2 * t
        cov[6, 6] = heading_offset_rw**2 * t
        cov[7, 7] = cov[8, 8] = scale_rw**2 * t
        noise = gtsam.noiseModel.Gaussian.Covariance(cov)
    ddx, ddy, ddp = pim.dx, pim.dy, pim.dpsi
    jx, jy, jp = pim.j_x, pim.j_y, pim.j_p
    vx, vy = pim.kv_x, pim.kv_y
    wx, wy, wp = pim.kw_x, pim.kw_y, pim.kw_p
    bl, kvl, kwl = pim.bg_lin, pim.kv_lin, pim.kw_lin
    zv = pim.last_v
    zw = pim.last_w_gyro
    zo = pim.last_w_odo
    zg = pim.last_gain
    cos = math.cos
    sin = math.sin
    # Buffers owned by this factor, rewritten in place (gtsam copies them into Eigen objects);
    # flat memoryview writes are cheaper than numpy item assignment (docs/design/preintegration.md)
    hi = np.zeros((DIM, DIM))
    hi[2, 2] = -1.0
    hi[:3, BG] = (-jx, -jy, -jp)
    hi[:3, KV] = (-vx, -vy, 0.0)
    hi[:3, KW] = (-wx, -wy, -wp)
    for r in range(5, DIM):
        hi[r, r] = -1.0
    hj = np.eye(DIM)
    hj[4, BG] = zg
    hj[3, KV] = -zv
    hj[4, KW] = -zo
    mi = memoryview(hi.reshape(-1))
    mj = memoryview(hj.reshape(-1))
    e = np.zeros(DIM)
    me = memoryview(e)
    ki = key_i
    kj = key_j
    n = DIM

    def error(this, values, H):
        xi, yi, pi, _, _, bi, hoi, kvi, kwi = values.atVector(ki).tolist()
        xj, yj, pj, vj, wj, bj, hoj, kvj, kwj = values.atVector(kj).tolist()
        db = bi - bl
        dv = kvi - kvl
        dw = kwi - kwl
        dx = xj - xi
        dy = yj - yi
        cp = cos(pi)
        sp = sin(pi)
        u0 = cp * dx + sp * dy
        u1 = cp * dy - sp * dx
        if H is not None:
            mi[0] = -cp  # flat index n r + c is row r, column c
            mi[1] = -sp
            mi[2] = u1
            mi[n] = sp
            mi[n + 1] = -cp
            mi[n + 2] = -u0
            mj[0] = cp
            mj[1] = sp
            mj[n] = -sp
            mj[n + 1] = cp
            H[0] = hi
            H[1] = hj
        me[0] = u0 - ddx - jx * db - vx * dv - wx * dw
        me[1] = u1 - ddy - jy * db - vy * dv - wy * dw
        me[2] = (pj - pi - ddp - jp * db - wp * dw + _PI) % _TWO_PI - _PI
        me[3] = vj - kvj * zv
        me[4] = wj + zg * bj - zw - kwj * zo
        me[5] = bj - bi
        me[6] = (hoj - hoi + _PI) % _TWO_PI - _PI
        me[7] = kvj - kvi
        me[8] = kwj - kwi
        return e

    factor = gtsam.CustomFactor(noise, [key_i, key_j], error)
    if record is not None:
        record.append((factor, noise, (ddx, ddy, ddp, jx, jy, jp, vx, vy, wx, wy, wp, bl, kvl,
                                       kwl, zv, zw, zo, zg)))
    return factor
