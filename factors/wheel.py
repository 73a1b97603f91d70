"""Wheel-encoder factors on one keyframe state.

* ``wheel_speed_factor``: forward speed from odometry, z = v (m/s).
* ``wheel_rates_factor``: left/right wheel angular speeds (rad/s) through wheel radius r (m) and
  track width L (m, distance between the wheel contact points)::

      w_l = (v - w L / 2) / r,    w_r = (v + w L / 2) / r

  error = (w_l - z_l, w_r - z_r), rad/s.
* ``wheel_rates_calib_factor``: the same with a second key, a gtsam Vector2 [r_scale, L_scale]
  (dimensionless), so that the effective radius is r * r_scale and the track L * L_scale. The
  caller adds a prior near [1, 1] and, if the scales may drift, a ``BetweenFactorVector`` random
  walk between calibration keys. Observability: with a gyro observing w, L_scale is observable
  from turning; r_scale needs an absolute speed/position source (GPS).

All errors are linear in (v, w) for fixed r and L, so the plain versions use constant Jacobians.
"""

from __future__ import annotations

import gtsam
import numpy as np
from ddfuse.factors.noise import NoiseLike, as_noise_model
from ddfuse.factors.state import DIM, V, W

__all__ = [
    "wheel_speed_factor",
    "wheel_rates_factor",
    "wheel_rates_calib_factor",
    "wheel_rates",
    "body_twist",
]

_H_SPEED = np.zeros((1, DIM))
_H_SPEED[0, V] = 1.0


def wheel_rates(v: float, w: float, radius: float, track: float) -> tuple[float, float]:
    """Left and right wheel angular speeds (rad/s) for body speed v (m/s) and yaw rate w (rad/s)."""
    half = 0.5 * w * track
    return (v - half) / radius, (v + half) / radius


def body_twist(w_left: float, w_right: float, radius: float, track: float) -> tuple[float, float]:
    """Inverse of ``wheel_rates``: (v m/s, w rad/s) from wheel angular speeds (rad/s)."""
    return 0.5 * radius * (w_left + w_right), radius * (w_right - w_left) / track


def wheel_speed_factor(key: int, v_meas: float, noise: NoiseLike) -> gtsam.CustomFactor:
    """Forward-speed factor, error v - z (m/s). ``noise``: 1-D model or sigma (m/s)."""
    z = float(v_meas)
    h = _H_SPEED  # gtsam copies Jacobians and errors into Eigen objects: buffers can be reused
    e = np.zeros(1)
    me = memoryview(e)

    def error(this, values, H):
        if H is not None:
            H[0] = h
        me[0] = values.atVector(key).tolist()[3] - z
        return e

    return gtsam.CustomFactor(as_noise_model(noise, 1), [key], error)


def wheel_rates_factor(
    key: int,
    w_left: float,
    w_right: float,
    radius: float,
    track: float,
    noise: NoiseLike,
) -> gtsam.CustomFactor:
    """Left/right wheel angular-speed factor, 2-D error (rad/s), fixed radius and track.

    Args:
        key: 9-vector state key.
        w_left, w_right: measured wheel angular speeds, rad/s, positive driving forward.
        radius: wheel radius, m. track: track width, m.
        noise: 2-D model or sigma(s), rad/s.
    """
    r = float(radius)
    half_l = 0.5 * float(track)
    zl = float(w_left)
    zr = float(w_right)
    h = np.zeros((2, DIM))
    h[0, V] = h[1, V] = 1.0 / r
    h[0, W] = -half_l / r
    h[1, W] = half_l / r
    e = np.zeros(2)
    me = memoryview(e)

    def error(this, values, H):
        s = values.atVector(key).tolist()
        v = s[3]
        a = half_l * s[4]
        if H is not None:
            H[0] = h
        me[0] = (v - a) / r - zl
        me[1] = (v + a) / r - zr
        return e

    return gtsam.CustomFactor(as_noise_model(noise, 2), [key], error)


def wheel_rates_calib_factor(
    key: int,
    calib_key: int,
    w_left: float,
    w_right: float,
    radius: float,
    track: float,
    noise: NoiseLike,
) -> gtsam.CustomFactor:
    """Left/right wheel angular-speed factor with a calibration key (2 keys, 2-D error, rad/s).

    ``calib_key`` holds a gtsam Vector2 [r_scale, L_scale]; the effective wheel radius is
    ``radius * r_scale`` (m) and the track ``track * L_scale`` (m). Jacobians: 2x9 for the state,
    2x2 for the calibration.
    """
    r0 = float(radius)
    half_l0 = 0.5 * float(track)
    zl = float(w_left)
    zr = float(w_right)
    # gtsam copies Jacobians and errors into Eigen objects, so these buffers are reused
    hs = np.zeros((2, DIM))
    hc = np.zeros((2, 2))
    ms = memoryview(hs.reshape(-1))
    mc = memoryview(hc.reshape(-1))
    e = np.zeros(2)
    me = memoryview(e)

    def error(this, values, H):
        s = values.atVector(key).tolist()
        sr, sl = values.atVector(calib_key).tolist()
        v = s[3]
        w = s[4]
        inv_r = 1.0 / (r0 * sr)
        hl = half_l0 * sl
        pl = (v - hl * w) * inv_r
        pr = (v + hl * w) * inv_r
        if H is not None:
            # flat index: DIM r + c (state), 2 r + c (calibration)
            ms[3] = ms[DIM + 3] = inv_r
            ms[4] = -hl * inv_r
            ms[DIM + 4] = hl * inv_r
            # d/dr_scale of (.)/(r0 sr) is -(.)/sr; d/dL_scale is -+ half_l0 w / (r0 sr)
            g = half_l0 * w * inv_r
            mc[0] = -pl / sr
            mc[2] = -pr / sr
            mc[1] = -g
            mc[3] = g
            H[0] = hs
            H[1] = hc
        me[0] = pl - zl
        me[1] = pr - zr
        return e

    return gtsam.CustomFactor(as_noise_model(noise, 2), [key, calib_key], error)
