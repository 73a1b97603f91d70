"""Gyro factor on one keyframe state: z = w + bg (rad/s), 1-D error ``w + bg - z``.

Linear in the state, so the Jacobian is a constant 1x7 row. When several linear measurements of
one keyframe are available (gyro, wheel speed), the C++ alternative is to fold them into one
``PriorFactorVector`` with zero precision on unmeasured rows (the design study's design E); this
factor exists for clarity, robust noise models and per-measurement residuals.
"""

from __future__ import annotations

import gtsam
import numpy as np

from factors.noise import NoiseLike, as_noise_model
from factors.state import BG, DIM, W

__all__ = ["gyro_factor"]

_H = np.zeros((1, DIM))
_H[0, W] = 1.0
_H[0, BG] = 1.0


def gyro_factor(key: int, w_meas: float, noise: NoiseLike) -> gtsam.CustomFactor:
    """Gyro yaw-rate factor.

    Args:
        key: 7-vector state key (``factors.state``).
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
