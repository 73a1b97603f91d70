"""GPS position factor on one keyframe state, local ENU (east, north), with lever arm and latency.

Measurement model (world = local ENU frame, m)::

    (x', y', psi') = kinematics.se2_step(x, y, psi, v, w, dt_fix)   # pose at the fix time
    h = (x', y') + R(psi') l                                         # antenna position
    error = h - z                                                    # 2-D, m

where ``l`` = (lx, ly) is the antenna position in the body frame (m, x forward, y left) and
``dt_fix`` (s) is the fix time minus the keyframe time (either sign), so a fix that is not exactly
at a keyframe is compared with the state propagated along its own constant twist. With
``dt_fix = 0`` and a zero lever arm this is ``gtsam.PoseTranslationPrior2D`` on the position.

Robust noise (``gtsam.noiseModel.Robust`` with Huber, Cauchy...) is passed by the caller as the
``noise`` argument.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from ddfuse.factors.kinematics import antenna_position, twist_coeffs
from ddfuse.factors.noise import NoiseLike, as_noise_model
from ddfuse.factors.state import DIM

__all__ = ["gps_factor", "gps_predict", "gps_predict_jacobian"]


def gps_predict(
    state: tuple[float, ...] | list[float],
    lever_arm: tuple[float, float] = (0.0, 0.0),
    dt_fix: float = 0.0,
) -> tuple[float, float]:
    """Predicted antenna position (east, north), m, for a 9-state; reference helper."""
    x, y, psi, v, w = state[:5]
    a = w * dt_fix
    s, c, _, _ = twist_coeffs(a)
    d = v * dt_fix
    cp, sp = math.cos(psi), math.sin(psi)
    x1 = x + cp * d * s - sp * d * c
    y1 = y + sp * d * s + cp * d * c
    rx, ry, _, _ = antenna_position(0.0, 0.0, psi + a, *lever_arm)
    return x1 + rx, y1 + ry


def gps_predict_jacobian(
    state: np.ndarray | list[float],
    lever_arm: tuple[float, float] = (0.0, 0.0),
    dt_fix: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The factor's prediction h (east, north), m, shape (2,), and its Jacobian with respect to
    the 9-state, shape (2, DIM): for gating a fix and for its innovation covariance, the same
    model as ``gps_factor``."""
    x, y, psi, v, w = (float(c) for c in state[:5])
    lx, ly = lever_arm
    dt = float(dt_fix)
    a = w * dt
    s, c, ds, dc = twist_coeffs(a)
    d = v * dt
    cp, sp = math.cos(psi), math.sin(psi)
    ex, ey = cp * d * s - sp * d * c, sp * d * s + cp * d * c
    rx, ry, _, _ = antenna_position(0.0, 0.0, psi + a, lx, ly)
    H = np.zeros((2, DIM))
    H[0, 0] = H[1, 1] = 1.0
    H[0, 2], H[1, 2] = -ey - ry, ex + rx
    H[0, 3], H[1, 3] = dt * (cp * s - sp * c), dt * (sp * s + cp * c)
    dd = d * dt
    H[0, 4] = dd * (cp * ds - sp * dc) - ry * dt
    H[1, 4] = dd * (sp * ds + cp * dc) + rx * dt
    return np.array((x + ex + rx, y + ey + ry)), H


def gps_factor(
    key: int,
    east: float,
    north: float,
    noise: NoiseLike,
    lever_arm: tuple[float, float] = (0.0, 0.0),
    dt_fix: float = 0.0,
) -> gtsam.CustomFactor:
    """GPS factor.

    Args:
        key: 9-vector state key (``ddfuse.factors.state``).
        east, north: fix position in the local ENU frame, m.
        noise: 2-D noise model or sigma(s), m; pass a robust model for outlier rejection.
        lever_arm: antenna (lx, ly) in the body frame, m.
        dt_fix: fix time - keyframe time, s.

    Returns a ``gtsam.CustomFactor`` with the 2-D error of the module docstring and a 2x9 Jacobian
    (zero in the bg and hoff columns).
    """
    zx = float(east)
    zy = float(north)
    lx, ly = float(lever_arm[0]), float(lever_arm[1])
    dt = float(dt_fix)
    model = as_noise_model(noise, 2)
    cos = math.cos
    sin = math.sin
    antenna = antenna_position
    # gtsam copies Jacobians and errors into Eigen objects, so these buffers are reused; flat
    # memoryview writes (index DIM r + c) beat numpy item assignment (docs/design/performance.md)
    h = np.zeros((2, DIM))
    h[0, 0] = h[1, 1] = 1.0
    mh = memoryview(h.reshape(-1))
    e = np.zeros(2)
    me = memoryview(e)

    if dt == 0.0:
        if lx == 0.0 and ly == 0.0:

            def error(this, values, H):
                s = values.atVector(key).tolist()
                if H is not None:
                    H[0] = h
                me[0] = s[0] - zx
                me[1] = s[1] - zy
                return e

        else:

            def error(this, values, H):
                x, y, psi = values.atVector(key).tolist()[:3]
                rx, ry, _, _ = antenna(0.0, 0.0, psi, lx, ly)
                if H is not None:
                    mh[2] = -ry
                    mh[DIM + 2] = rx
                    H[0] = h
                me[0] = x + rx - zx
                me[1] = y + ry - zy
                return e

        return gtsam.CustomFactor(model, [key], error)

    coeffs = twist_coeffs

    def error(this, values, H):
        x, y, psi, v, w = values.atVector(key).tolist()[:5]
        a = w * dt
        s, c, ds, dc = coeffs(a)
        d = v * dt
        cp = cos(psi)
        sp = sin(psi)
        dxb = d * s
        dyb = d * c
        ex = cp * dxb - sp * dyb
        ey = sp * dxb + cp * dyb
        rx, ry, _, _ = antenna(0.0, 0.0, psi + a, lx, ly)
        if H is not None:
            # through the step, plus the lever arm turning with psi' = psi + w dt
            vs = dt * s
            vc = dt * c
            dd = d * dt
            ws = dd * ds
            wc = dd * dc
            mh[2] = -ey - ry
            mh[DIM + 2] = ex + rx
            mh[3] = cp * vs - sp * vc
            mh[DIM + 3] = sp * vs + cp * vc
            mh[4] = cp * ws - sp * wc - ry * dt
            mh[DIM + 4] = sp * ws + cp * wc + rx * dt
            H[0] = h
        me[0] = x + ex + rx - zx
        me[1] = y + ey + ry - zy
        return e

    return gtsam.CustomFactor(model, [key], error)
