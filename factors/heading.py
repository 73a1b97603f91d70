"""Absolute heading factor (compass / IMU yaw) on one keyframe state.

Measurement model: z = wrap(psi + hoff) (rad, CCW from east), where ``hoff`` is the state's
heading-sensor offset. Error (1-D, rad) ``wrap(psi + hoff - z)`` in [-pi, pi), so measurements and
states on opposite sides of +-pi give a small residual. With ``use_offset=False`` the offset is
ignored (z = wrap(psi)) and the Jacobian has no ``hoff`` column entry.

``gtsam.PoseRotationPrior2D`` does the same for a Pose2 key but does not apply to the vector state.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from ddfuse.factors.noise import NoiseLike, as_noise_model
from ddfuse.factors.state import DIM, HOFF, PSI

__all__ = ["heading_factor"]

_PI = math.pi
_TWO_PI = 2.0 * math.pi
_H_OFF = np.zeros((1, DIM))
_H_OFF[0, PSI] = 1.0
_H_OFF[0, HOFF] = 1.0
_H_NO_OFF = np.zeros((1, DIM))
_H_NO_OFF[0, PSI] = 1.0


def heading_factor(
    key: int, heading_meas: float, noise: NoiseLike, use_offset: bool = True
) -> gtsam.CustomFactor:
    """Absolute heading factor.

    Args:
        key: 9-vector state key (``ddfuse.factors.state``).
        heading_meas: measured heading, rad, CCW from east (any range; it is wrapped).
        noise: 1-D noise model or sigma (rad); may be robust.
        use_offset: model the sensor's heading offset ``hoff`` (default) or not.
    """
    z = float(heading_meas)
    # gtsam copies Jacobians and errors into Eigen objects, so buffers can be reused
    e = np.zeros(1)
    me = memoryview(e)
    if use_offset:
        h = _H_OFF

        def error(this, values, H):
            s = values.atVector(key).tolist()
            if H is not None:
                H[0] = h
            me[0] = (s[2] + s[6] - z + _PI) % _TWO_PI - _PI
            return e

    else:
        h = _H_NO_OFF

        def error(this, values, H):
            s = values.atVector(key).tolist()
            if H is not None:
                H[0] = h
            me[0] = (s[2] - z + _PI) % _TWO_PI - _PI
            return e

    return gtsam.CustomFactor(as_noise_model(noise, 1), [key], error)
