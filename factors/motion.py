"""Differential-drive motion factor between two consecutive keyframe states (2 keys, 9-D error).

Model (states as in ``ddfuse.factors.state``; i = earlier keyframe, j = later, dt = t_j - t_i > 0)::

    twist used for the pose:   vm = a_i v_i + a_j v_j,  wm = a_i w_i + a_j w_j
        twist="mean"  (default): a_i = a_j = 1/2  -> trapezoid on v, w; exact for a constant twist
                                 and second-order accurate when v, w vary linearly over dt
        twist="start":           a_i = 1, a_j = 0 -> explicit (forward-Euler on v, w) step
    (dx_b, dy_b, dpsi) = kinematics.se2_increment(vm, wm, dt)    exact constant-twist increment

    e[0:2] = R(psi_i)^T (p_j - p_i) - (dx_b, dy_b)    m, in the body frame of keyframe i
                                                       (row 0 longitudinal, row 1 lateral)
    e[2]   = wrap(psi_j - psi_i - dpsi)                rad
    e[3]   = v_j - v_i                                 m/s    random walk / constant-accel model
    e[4]   = w_j - w_i                                 rad/s
    e[5]   = bg_j - bg_i                               rad/s  gyro-bias random walk
    e[6]   = wrap(hoff_j - hoff_i)                     rad    heading-offset random walk
    e[7:9] = k_j - k_i                                 1      odometry scales (constants)

The position residual is taken in keyframe i's body frame so that longitudinal and lateral
(slip) noise can differ; with equal sigmas it is statistically the same as a world-frame residual.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import gtsam
import numpy as np
from ddfuse.factors.kinematics import twist_coeffs
from ddfuse.factors.noise import NoiseLike, as_noise_model
from ddfuse.factors.state import DIM

__all__ = ["MotionNoise", "motion_factor", "motion_error"]

_PI = math.pi
_TWO_PI = 2.0 * math.pi
_TWISTS = {"mean": (0.5, 0.5), "start": (1.0, 0.0)}


@dataclass(frozen=True)
class MotionNoise:
    """Process-noise densities of the motion model; all are sigma densities (sqrt of PSD).

    A white-noise density q gives a random-walk sigma q sqrt(dt) after ``dt`` seconds.

    pos_long, pos_lat: m/sqrt(s) — white velocity noise on the body-frame position residual
        (model error, wheel slip); lateral is usually smaller for a non-holonomic base.
    heading: rad/sqrt(s) — white yaw-rate noise on the heading residual.
    acc: m/s^2/sqrt(Hz) — white forward acceleration driving v (v random walk).
    yaw_acc: rad/s^2/sqrt(Hz) — white yaw acceleration driving w.
    gyro_bias: rad/s/sqrt(s) — gyro-bias random walk.
    heading_offset: rad/sqrt(s) — heading-sensor offset random walk.
    scale: 1/sqrt(s) — random walk of the odometry scales k_v, k_w (constants; a floor).
    """

    pos_long: float = 0.05
    pos_lat: float = 0.02
    heading: float = 0.01
    acc: float = 0.5
    yaw_acc: float = 0.5
    gyro_bias: float = 1e-4
    heading_offset: float = 1e-4
    scale: float = 1e-4

    def sigmas(self, dt: float, twist: str = "mean") -> tuple[float, ...]:
        """The 9 error-row sigmas for an interval of ``dt`` seconds (units of the error rows).

        The acceleration noise also enters the pose rows: with white acceleration, integrating
        the trapezoid ("mean") twist leaves an error of variance q^2 dt^3 / 12 that is
        uncorrelated with the velocity increment; the "start" twist leaves q^2 dt^3 / 3 and a
        correlation with the velocity row that this diagonal model ignores.
        """
        if not dt > 0.0:
            raise ValueError(f"dt must be > 0, got {dt}")
        k = 12.0 if twist == "mean" else 3.0
        c3 = dt * dt * dt / k
        return (
            math.sqrt(self.pos_long**2 * dt + self.acc**2 * c3),
            math.sqrt(self.pos_lat**2 * dt),
            math.sqrt(self.heading**2 * dt + self.yaw_acc**2 * c3),
            self.acc * math.sqrt(dt),
            self.yaw_acc * math.sqrt(dt),
            self.gyro_bias * math.sqrt(dt),
            self.heading_offset * math.sqrt(dt),
            self.scale * math.sqrt(dt),
            self.scale * math.sqrt(dt),
        )

    def noise_model(self, dt: float, twist: str = "mean") -> gtsam.noiseModel.Diagonal:
        """Diagonal gtsam noise model for ``dt`` seconds, dimension 9."""
        return gtsam.noiseModel.Diagonal.Sigmas(np.array(self.sigmas(dt, twist)))


def motion_error(
    si: tuple[float, ...] | list[float],
    sj: tuple[float, ...] | list[float],
    dt: float,
    twist: str = "mean",
) -> tuple[float, ...]:
    """The 9-D motion residual for states ``si``, ``sj`` (plain sequences); reference helper."""
    ai, aj = _TWISTS[twist]
    xi, yi, pi, vi, wi, bi, hi, kvi, kwi = si
    xj, yj, pj, vj, wj, bj, hj, kvj, kwj = sj
    a = (ai * wi + aj * wj) * dt
    s, c, _, _ = twist_coeffs(a)
    d = (ai * vi + aj * vj) * dt
    dx = xj - xi
    dy = yj - yi
    cp = math.cos(pi)
    sp = math.sin(pi)
    return (
        cp * dx + sp * dy - d * s,
        cp * dy - sp * dx - d * c,
        (pj - pi - a + _PI) % _TWO_PI - _PI,
        vj - vi,
        wj - wi,
        bj - bi,
        (hj - hi + _PI) % _TWO_PI - _PI,
        kvj - kvi,
        kwj - kwi,
    )


def motion_factor(
    key_i: int,
    key_j: int,
    dt: float,
    noise: MotionNoise | NoiseLike,
    twist: str = "mean",
) -> gtsam.CustomFactor:
    """Motion factor between keyframe states ``key_i`` (time t) and ``key_j`` (time t + dt).

    Args:
        key_i, key_j: gtsam keys of 9-vector states (``ddfuse.factors.state`` layout).
        dt: t_j - t_i, s, > 0.
        noise: a ``MotionNoise`` (turned into a diagonal model for ``dt``) or any 9-D gtsam noise
            model / sigmas accepted by ``ddfuse.factors.noise.as_noise_model``.
        twist: "mean" (trapezoid, default) or "start"; see the module docstring.

    Returns a ``gtsam.CustomFactor`` with the 9-D error of the module docstring.
    """
    if twist not in _TWISTS:
        raise ValueError(f"twist must be one of {sorted(_TWISTS)}, got {twist!r}")
    if not dt > 0.0:
        raise ValueError(f"dt must be > 0, got {dt}")
    if isinstance(noise, MotionNoise):
        model = noise.noise_model(dt, twist)
    else:
        model = as_noise_model(noise, DIM)
    ai, aj = _TWISTS[twist]
    dt = float(dt)
    cos = math.cos
    sin = math.sin
    coeffs = twist_coeffs
    # Buffers owned by this factor: gtsam copies the returned error and the Jacobians into Eigen
    # objects, so they can be rewritten in place on every call. Element writes go through flat
    # memoryviews, ~3x cheaper than numpy item assignment.
    hi = -np.eye(DIM)
    hj = np.eye(DIM)
    hi[2, 4] = -ai * dt
    hj[2, 4] = -aj * dt
    mi = memoryview(hi.reshape(-1))
    mj = memoryview(hj.reshape(-1))
    e = np.zeros(DIM)
    me = memoryview(e)
    n = DIM
    ki = key_i
    kj = key_j

    def error(this, values, H):
        xi, yi, pi, vi, wi, bi, hoi, kvi, kwi = values.atVector(ki).tolist()
        xj, yj, pj, vj, wj, bj, hoj, kvj, kwj = values.atVector(kj).tolist()
        a = (ai * wi + aj * wj) * dt
        s, c, ds, dc = coeffs(a)
        d = (ai * vi + aj * vj) * dt
        dx = xj - xi
        dy = yj - yi
        cp = cos(pi)
        sp = sin(pi)
        u0 = cp * dx + sp * dy
        u1 = cp * dy - sp * dx
        if H is not None:
            # d(dx_b, dy_b)/d(vm, wm) = dt (S, C), d dt (S', C'); chain rule through a_i, a_j.
            # Flat index n r + c is row r, column c.
            ts = dt * s
            tc = dt * c
            dds = d * dt * ds
            ddc = d * dt * dc
            mi[0] = -cp
            mi[1] = -sp
            mi[2] = u1
            mi[3] = -ai * ts
            mi[4] = -ai * dds
            mi[n] = sp
            mi[n + 1] = -cp
            mi[n + 2] = -u0
            mi[n + 3] = -ai * tc
            mi[n + 4] = -ai * ddc
            mj[0] = cp
            mj[1] = sp
            mj[3] = -aj * ts
            mj[4] = -aj * dds
            mj[n] = -sp
            mj[n + 1] = cp
            mj[n + 3] = -aj * tc
            mj[n + 4] = -aj * ddc
            H[0] = hi
            H[1] = hj
        me[0] = u0 - d * s
        me[1] = u1 - d * c
        me[2] = (pj - pi - a + _PI) % _TWO_PI - _PI
        me[3] = vj - vi
        me[4] = wj - wi
        me[5] = bj - bi
        me[6] = (hoj - hoi + _PI) % _TWO_PI - _PI
        me[7] = kvj - kvi
        me[8] = kwj - kwi
        return e

    return gtsam.CustomFactor(model, [key_i, key_j], error)
