"""Gyro factors on one keyframe state (rad/s, 1-D errors, linear in the state).

``gyro_factor``: a gyro reading z = w + bg, error ``w + bg - z``; the Jacobian is a constant 1x9
row. ``bias_difference_factor``: the mean gyro reading and the mean odometry yaw rate over the
same interval, z_g - k_w z_o = bg, error ``bg + k_w z_o - z_g``. When several linear measurements of
one keyframe are available (gyro, wheel speed), the C++ alternative is to fold them into one
``PriorFactorVector`` with zero precision on unmeasured rows (the design study's design E); this
factor exists for clarity, robust noise models and per-measurement residuals.
"""

from __future__ import annotations

import gtsam
import numpy as np

from factors.noise import NoiseLike, as_noise_model
from factors.state import BG, DIM, KW, W

__all__ = ["bias_difference_factor", "gyro_factor"]

_H = np.zeros((1, DIM))
_H[0, W] = 1.0
_H[0, BG] = 1.0


def gyro_factor(key: int, w_meas: float, noise: NoiseLike) -> gtsam.CustomFactor:
    """Gyro yaw-rate factor.

    Args:
        key: 9-vector state key (``factors.state``).
        w_meas: gyro z reading, rad/s, CCW positive, body frame.
        noise: 1-D noise model or sigma (rad/s).
    """
    z = float(w_meas)
    h = _H  # gtsam copies Jacobians and errors into Eigen objects, so buffers can be reused
    e = np.zeros(1)
    me = memoryview(e)

    def error(this, values, H):
        s = values.atVector(key).tolist()
        if H is not None:
            H[0] = h
        me[0] = s[4] + s[5] - z
        return e

    return gtsam.CustomFactor(as_noise_model(noise, 1), [key], error)


def bias_difference_factor(key: int, mean_gyro: float, mean_odo: float,
                           sigma: float) -> gtsam.CustomFactor:
    """The gyro bias seen as the difference of two yaw rates held over the same interval.

    Args:
        key: 9-vector state key (``factors.state``), at the end of the interval.
        mean_gyro: mean gyro yaw rate over the interval, rad/s (bias included).
        mean_odo: mean odometry yaw rate over the same time, rad/s (before the k_w scale).
        sigma: sigma of (mean_gyro - k_w mean_odo), rad/s: sqrt of the two rates' summed noise
            densities over the interval's duration.
    """
    zg, zo = float(mean_gyro), float(mean_odo)
    h = np.zeros((1, DIM))
    h[0, BG] = 1.0
    h[0, KW] = zo
    e = np.zeros(1)
    me = memoryview(e)

    def error(this, values, H):
        s = values.atVector(key).tolist()
        if H is not None:
            H[0] = h
        me[0] = s[BG] + s[KW] * zo - zg
        return e

    return gtsam.CustomFactor(as_noise_model(sigma, 1), [key], error)
