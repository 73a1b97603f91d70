"""Layout of the per-keyframe state vector used by every factor in this package.

One gtsam Vector key per keyframe holds a flat 9-vector in the world (local ENU) frame::

    index  name   unit    meaning
    0      x      m       position east
    1      y      m       position north
    2      psi    rad     heading of body x, CCW from east; NOT kept wrapped (see below)
    3      v      m/s     forward speed along body x
    4      w      rad/s   yaw rate, CCW positive
    5      bg     rad/s   gyro bias: gyro reading = w + bg
    6      hoff   rad     heading-sensor offset: heading reading = wrap(psi + hoff)
    7      k_v    1       odometry speed scale: true speed = k_v * odometry speed
    8      k_w    1       odometry yaw-rate scale: true yaw rate = k_w * odometry yaw rate

Because the state is a plain vector, gtsam's retract is ``x + delta`` and the tangent space is the
vector itself, in the same (world-frame) coordinates. ``psi`` and ``hoff`` may drift outside
[-pi, pi) as the optimiser adds deltas; every factor wraps its angle residuals, so only the
residuals need to be wrap-safe. Callers that compare a measured angle with ``psi`` should either
use a factor (which wraps) or unwrap the measurement against the prediction
(``z = psi_pred + wrap(z - psi_pred)``).
"""

from __future__ import annotations

import numpy as np

X, Y, PSI, V, W, BG, HOFF, KV, KW = range(9)
DIM = 9
NAMES = ("x", "y", "psi", "v", "w", "bg", "hoff", "k_v", "k_w")
UNITS = ("m", "m", "rad", "m/s", "rad/s", "rad/s", "rad", "1", "1")


def make_state(
    x: float = 0.0,
    y: float = 0.0,
    psi: float = 0.0,
    v: float = 0.0,
    w: float = 0.0,
    bg: float = 0.0,
    hoff: float = 0.0,
    k_v: float = 1.0,
    k_w: float = 1.0,
) -> np.ndarray:
    """A state vector, shape (9,), float64, in the layout above."""
    return np.array((x, y, psi, v, w, bg, hoff, k_v, k_w), dtype=np.float64)
