"""Preintegrated wheel-speed + gyro odometry between two keyframes (the fast path).

Accumulation (``WheelGyroPreintegration``)
------------------------------------------
Samples (dt, v_meas, w_gyro, var_v, var_w) are held constant over their ``dt`` (zero-order hold)
and integrated exactly as constant twists (``kinematics.se2_step_jac``) into the pose of
keyframe j expressed in the frame of keyframe i::

    delta = (dx, dy, dpsi)   m, m, rad;  (dx, dy) along keyframe i's body x (forward) and y (left)
    w     = w_meas - g bg_lin  (rad/s) with ``bg_lin`` the gyro-bias linearisation point and
                               g the sample's bias gain: 1 for a raw gyro reading, 0 for a
                               yaw rate that carries no gyro bias (wheel odometry), and the gyro's
                               weight when a gyro and an odometry yaw rate are fused per sample

For every sample, with F and G the Jacobians of the step with respect to the running delta and to
(v, w)::

    cov  <- F cov F^T + G_v G_v^T var_v + G_w G_w^T var_w      (3x3, same coordinates as delta)
    J_bg <- F J_bg - g G_w                                     (3, d delta / d bg)

``var_v`` (m/s)^2 and ``var_w`` (rad/s)^2 are the variances of each held sample. The first-order
bias correction is ``delta(bg) = delta + J_bg (bg - bg_lin)`` as in IMU preintegration; once the
estimated bias moves far from ``bg_lin`` (say more than a few sigma of the bias prior) call
``reintegrate(new_bg_lin)``, which replays the stored samples.

Factor (``preintegrated_factor``, 2 keys i and j, 7-D error)
------------------------------------------------------------
::

    e[0:2] = R(psi_i)^T (p_j - p_i) - (dx + Jx db, dy + Jy db)     m,  db = bg_i - bg_lin
    e[2]   = wrap(psi_j - psi_i - (dpsi + Jpsi db))                 rad
    e[3]   = v_j - v_last                                           m/s
    e[4]   = w_j + g_last bg_j - w_meas_last                        rad/s
    e[5]   = bg_j - bg_i                                            rad/s
    e[6]   = wrap(hoff_j - hoff_i)                                  rad

Rows 3 and 4 tie the keyframe-j twist states to the LAST sample of the interval (speed and raw
yaw rate, the latter through g_last bg_j), with that sample's variances; they make v_j, w_j
meaningful without separate wheel/gyro factors at the keyframe. Their small correlation with the
pose rows (the last sample also enters the delta) is ignored. Rows 5 and 6 are random walks.
The 7x7 covariance is block diagonal: [cov + extra pose noise, var_v, var_w, q_bg^2 T,
q_hoff^2 T], with T the integrated time.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from factors.kinematics import se2_step_jac

__all__ = ["WheelGyroPreintegration", "preintegrated_factor"]

_PI = math.pi
_TWO_PI = 2.0 * math.pi


class WheelGyroPreintegration:
    """Accumulates wheel speed + gyro samples into an SE(2) increment; see the module docstring.

    All state is plain Python floats so that ``integrate`` stays cheap (a few microseconds).
    """

    __slots__ = (
        "bg_lin",
        "dx",
        "dy",
        "dpsi",
        "dt_total",
        "c_xx",
        "c_xy",
        "c_xp",
        "c_yy",
        "c_yp",
        "c_pp",
        "j_x",
        "j_y",
        "j_p",
        "last_v",
        "last_w_gyro",
        "last_var_v",
        "last_var_w",
        "last_gain",
        "n",
        "samples",
        "keep_samples",
    )

    def __init__(self, bg_lin: float = 0.0, keep_samples: bool = True) -> None:
        """``bg_lin``: gyro-bias linearisation point, rad/s. ``keep_samples``: store the samples
        so that ``reintegrate`` can replay them with a new bias."""
        self.keep_samples = keep_samples
        self.reset(bg_lin)

    def reset(self, bg_lin: float | None = None) -> None:
        """Start a new interval (optionally with a new bias linearisation point, rad/s)."""
        if bg_lin is not None:
            self.bg_lin = float(bg_lin)
        self.dx = self.dy = self.dpsi = 0.0
        self.dt_total = 0.0
        self.c_xx = self.c_xy = self.c_xp = self.c_yy = self.c_yp = self.c_pp = 0.0
        self.j_x = self.j_y = self.j_p = 0.0
        self.last_v = self.last_w_gyro = 0.0
        self.last_var_v = self.last_var_w = 0.0
        self.last_gain = 1.0
        self.n = 0
        self.samples: list[tuple[float, float, float, float, float, float]] = []

    def integrate(self, dt: float, v: float, w_gyro: float, var_v: float, var_w: float,
                  gain: float = 1.0) -> None:
        """Add one sample held for ``dt`` s: speed ``v`` m/s, yaw rate ``w_gyro`` rad/s as
        measured (gyro bias not removed), their variances (m/s)^2 and (rad/s)^2 over this ``dt``,
        and ``gain``: how much of the gyro bias the yaw rate carries (1 raw gyro, 0 odometry)."""
        if self.keep_samples:
            self.samples.append((dt, v, w_gyro, var_v, var_w, gain))
        x1, y1, p1, j = se2_step_jac(self.dx, self.dy, self.dpsi, v,
                                     w_gyro - gain * self.bg_lin, dt)
        j0, j1 = j[0], j[1]
        a = j0[2]  # -(y1 - y): d x1 / d dpsi
        b = j1[2]  # x1 - x:    d y1 / d dpsi
        gvx, gvy = j0[3], j1[3]
        gwx, gwy, gwp = j0[4], j1[4], dt
        gbx, gby, gbp = gain * gwx, gain * gwy, gain * dt
        cxx, cxy, cxp = self.c_xx, self.c_xy, self.c_xp
        cyy, cyp, cpp = self.c_yy, self.c_yp, self.c_pp
        # F cov F^T with F = [[1, 0, a], [0, 1, b], [0, 0, 1]], then the sample's noise
        self.c_xx = cxx + 2.0 * a * cxp + a * a * cpp + gvx * gvx * var_v + gwx * gwx * var_w
        self.c_xy = cxy + a * cyp + b * cxp + a * b * cpp + gvx * gvy * var_v + gwx * gwy * var_w
        self.c_xp = cxp + a * cpp + gwx * gwp * var_w
        self.c_yy = cyy + 2.0 * b * cyp + b * b * cpp + gvy * gvy * var_v + gwy * gwy * var_w
        self.c_yp = cyp + b * cpp + gwy * gwp * var_w
        self.c_pp = cpp + gwp * gwp * var_w
        jp = self.j_p
        self.j_x += a * jp - gbx
        self.j_y += b * jp - gby
        self.j_p = jp - gbp
        self.dx, self.dy, self.dpsi = x1, y1, p1
        self.dt_total += dt
        self.last_v = v
        self.last_w_gyro = w_gyro
        self.last_var_v = var_v
        self.last_var_w = var_w
        self.last_gain = gain
        self.n += 1

    def reintegrate(self, bg_lin: float) -> None:
        """Replay the stored samples with a new bias linearisation point (rad/s)."""
        if not self.keep_samples:
            raise RuntimeError("reintegrate needs keep_samples=True")
        samples = self.samples
        self.reset(bg_lin)
        for s in samples:
            self.integrate(*s)

    @property
    def delta(self) -> tuple[float, float, float]:
        """(dx m, dy m, dpsi rad) at ``bg_lin``, in keyframe i's body frame."""
        return self.dx, self.dy, self.dpsi

    def delta_at(self, bg: float) -> tuple[float, float, float]:
        """First-order bias-corrected increment for gyro bias ``bg`` (rad/s)."""
        db = bg - self.bg_lin
        return self.dx + self.j_x * db, self.dy + self.j_y * db, self.dpsi + self.j_p * db

    @property
    def bias_jacobian(self) -> tuple[float, float, float]:
        """d(dx, dy, dpsi)/d bg, in (m, m, rad) per rad/s."""
        return self.j_x, self.j_y, self.j_p

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

    def predict(self, state_i) -> np.ndarray:
        """Initial guess for the 7-state at keyframe j from the state at i (array-like, (7,)).

        Pose = pose_i composed with the bias-corrected delta; v, w from the last sample (w with
        its share of the bias bg_i removed); bg and hoff carried over. ``psi`` is not wrapped.
        """
        x, y, psi, _, _, bg, hoff = (float(t) for t in state_i)
        dx, dy, dp = self.delta_at(bg)
        c = math.cos(psi)
        s = math.sin(psi)
        return np.array(
            (
                x + c * dx - s * dy,
                y + s * dx + c * dy,
                psi + dp,
                self.last_v,
                self.last_w_gyro - self.last_gain * bg,
                bg,
                hoff,
            )
        )

    def pose2_between(self, bg: float | None = None) -> tuple[gtsam.Pose2, np.ndarray]:
        """The increment as a ``gtsam.Pose2`` and its 3x3 covariance in Pose2's tangent space.

        For a Pose2-keyed graph with ``gtsam.BetweenFactorPose2`` (bias held fixed at ``bg``,
        default ``bg_lin``). Pose2 perturbations are body-frame at the increment, so the
        translation block is rotated by R(dpsi)^T.
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
) -> gtsam.CustomFactor:
    """Preintegrated wheel+gyro factor between keyframe states ``key_i`` and ``key_j``.

    Args:
        key_i, key_j: 7-vector state keys (``factors.state``).
        pim: the accumulated interval (at least one sample). Its values are copied: the object can
            be reset and reused afterwards.
        gyro_bias_rw: gyro-bias random-walk density, rad/s/sqrt(s).
        heading_offset_rw: heading-offset random-walk density, rad/sqrt(s).
        pose_noise: extra white-noise densities added to the pose rows, (m/sqrt(s), m/sqrt(s),
            rad/sqrt(s)) in keyframe i's frame: unmodelled slip, and a floor that keeps the
            covariance invertible when the robot stands still.
        noise: a 7-D noise model that replaces the computed one (e.g. robust), optional.

    Returns a ``gtsam.CustomFactor`` with the 7-D error of the module docstring.
    """
    if pim.n == 0:
        raise ValueError("preintegration has no samples")
    t = pim.dt_total
    if noise is None:
        cov = np.zeros((7, 7))
        cov[:3, :3] = pim.covariance
        cov[0, 0] += pose_noise[0] ** 2 * t
        cov[1, 1] += pose_noise[1] ** 2 * t
        cov[2, 2] += pose_noise[2] ** 2 * t
        cov[3, 3] = pim.last_var_v
        cov[4, 4] = pim.last_var_w
        cov[5, 5] = gyro_bias_rw**2 * t
        cov[6, 6] = heading_offset_rw**2 * t
        noise = gtsam.noiseModel.Gaussian.Covariance(cov)
    ddx, ddy, ddp = pim.dx, pim.dy, pim.dpsi
    jx, jy, jp = pim.j_x, pim.j_y, pim.j_p
    bl = pim.bg_lin
    zv = pim.last_v
    zw = pim.last_w_gyro
    zg = pim.last_gain
    cos = math.cos
    sin = math.sin
    # Buffers owned by this factor, rewritten in place (gtsam copies them into Eigen objects);
    # flat memoryview writes are ~3x cheaper than numpy item assignment.
    hi = np.zeros((7, 7))
    hi[2, 2] = -1.0
    hi[0, 5] = -jx
    hi[1, 5] = -jy
    hi[2, 5] = -jp
    hi[5, 5] = -1.0
    hi[6, 6] = -1.0
    hj = np.eye(7)
    hj[4, 5] = zg
    mi = memoryview(hi.reshape(-1))
    mj = memoryview(hj.reshape(-1))
    e = np.zeros(7)
    me = memoryview(e)
    ki = key_i
    kj = key_j

    def error(this, values, H):
        xi, yi, pi, _, _, bi, hoi = values.atVector(ki).tolist()
        xj, yj, pj, vj, wj, bj, hoj = values.atVector(kj).tolist()
        db = bi - bl
        dx = xj - xi
        dy = yj - yi
        cp = cos(pi)
        sp = sin(pi)
        u0 = cp * dx + sp * dy
        u1 = cp * dy - sp * dx
        if H is not None:
            mi[0] = -cp  # flat index 7 r + c is row r, column c
            mi[1] = -sp
            mi[2] = u1
            mi[7] = sp
            mi[8] = -cp
            mi[9] = -u0
            mj[0] = cp
            mj[1] = sp
            mj[7] = -sp
            mj[8] = cp
            H[0] = hi
            H[1] = hj
        me[0] = u0 - ddx - jx * db
        me[1] = u1 - ddy - jy * db
        me[2] = (pj - pi - ddp - jp * db + _PI) % _TWO_PI - _PI
        me[3] = vj - zv
        me[4] = wj + zg * bj - zw
        me[5] = bj - bi
        me[6] = (hoj - hoi + _PI) % _TWO_PI - _PI
        return e

    return gtsam.CustomFactor(noise, [key_i, key_j], error)
