"""Range/bearing and range-only factors between a keyframe state and a landmark.

Geometry (world = local ENU / map frame, m, rad)::

    sensor position  q = p + R(psi) s            s = (sx, sy): sensor mount in the body frame, m
    (dx, dy)         = landmark - q
    range            = hypot(dx, dy)                             m
    bearing          = wrap(atan2(dy, dx) - psi)                 rad, body frame, CCW from body x

Errors are ``range - z_range`` and ``wrap(bearing - z_bearing)`` (rad, wrap-safe near +-pi).
The sensor is assumed aligned with the body axes (only offset, no mount rotation; subtract a
known mount yaw from the measured bearing before calling).

A sighting ``dt`` seconds from the keyframe (either sign) is compared with the keyframe pose
carried along its own constant twist, ``(x, y, psi) <- kinematics.se2_step(x, y, psi, v, w,
dt)``, as the GPS factor does; the Jacobian then has v and w columns too.

The landmark position is a constant of the factor (known map); one key, the state.

Bearings with an error common to their frame (``ddfuse.estimation.landmark_frames``):
``earlier`` lists the frame's earlier sightings on the same key and offset as ((lx, ly, z_bearing),
w); the bearing error is then ``e - sum_j w e_j``, each ``e_j`` the same model's bearing error
for that sighting (the conditional of the frame's stacked Gaussian, whose sigma the caller
gives in ``noise``); empty: the plain error.

GTSAM's ``BearingRangeFactor2D`` / ``RangeFactor2D`` need a Pose2 key, so they do not apply to the
9-vector state (``ddfuse.factors.state``); these CustomFactors implement the same model on it.
At zero range the bearing and the Jacobians are undefined; the range is floored at 1e-9 m to avoid
a division by zero, which keeps the factor finite but meaningless there.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from ddfuse.factors.kinematics import se2_step, se2_step_jac
from ddfuse.factors.noise import NoiseLike, as_noise_model
from ddfuse.factors.state import DIM

__all__ = [
    "range_bearing_factor",
    "range_factor",
    "range_bearing_predict",
]

_PI = math.pi
_TWO_PI = 2.0 * math.pi
_MIN_RANGE = 1e-9


def range_bearing_predict(
    state: tuple[float, ...] | list[float],
    landmark: tuple[float, float],
    sensor_offset: tuple[float, float] = (0.0, 0.0),
    dt: float = 0.0,
) -> tuple[float, float]:
    """Predicted (range m, bearing rad in [-pi, pi)) of ``landmark`` from a 9-state, ``dt`` s
    after its time."""
    x, y, psi = state[:3]
    if dt != 0.0:
        x, y, psi = se2_step(x, y, psi, state[3], state[4], dt)
    c, s = math.cos(psi), math.sin(psi)
    sx, sy = sensor_offset
    dx = landmark[0] - (x + c * sx - s * sy)
    dy = landmark[1] - (y + s * sx + c * sy)
    b = math.atan2(dy, dx) - psi
    return math.hypot(dx, dy), (b + _PI) % _TWO_PI - _PI


def _make(
    key: int,
    landmark: tuple[float, float],
    z_range: float,
    z_bearing: float | None,
    sensor_offset: tuple[float, float],
    noise: NoiseLike,
    dt: float = 0.0,
    earlier=(),
) -> gtsam.CustomFactor:
    dt = float(dt)
    earlier = tuple((float(lj[0]), float(lj[1]), float(lj[2]), float(w)) for lj, w in earlier)
    lx, ly = float(landmark[0]), float(landmark[1])
    sx, sy = float(sensor_offset[0]), float(sensor_offset[1])
    zr = float(z_range)
    bearing = z_bearing is not None
    zb = float(z_bearing) if bearing else 0.0
    dim = 2 if bearing else 1
    # gtsam copies Jacobians and errors into Eigen objects, so these buffers are reused; flat
    # memoryview writes (index DIM r + c) beat numpy item assignment
    # (docs/design/performance.md)
    hs = np.zeros((dim, DIM))
    ms = memoryview(hs.reshape(-1))
    e = np.zeros(dim)
    me = memoryview(e)
    cos = math.cos
    sin = math.sin
    atan2 = math.atan2
    sqrt = math.sqrt

    def error(this, values, H):
        if dt == 0.0:
            x, y, psi = values.atVector(key).tolist()[:3]
        else:
            x, y, psi, v, w = values.atVector(key).tolist()[:5]
            x, y, psi, jac = se2_step_jac(x, y, psi, v, w, dt)
        c = cos(psi)
        s = sin(psi)
        ox = c * sx - s * sy
        oy = s * sx + c * sy
        dx = lx - x - ox
        dy = ly - y - oy
        r2 = dx * dx + dy * dy
        r = sqrt(r2)
        if r < _MIN_RANGE:
            r = _MIN_RANGE
            r2 = r * r
        if H is not None:
            # d(dx, dy)/d(x, y) = -I; d(dx, dy)/dpsi = -(-oy, ox)
            gr_x = dx / r
            gr_y = dy / r
            ms[0] = -gr_x
            ms[1] = -gr_y
            ms[2] = gr_x * oy - gr_y * ox
            if bearing:
                gb_x = -dy / r2
                gb_y = dx / r2
                ms[DIM] = -gb_x
                ms[DIM + 1] = -gb_y
                ms[DIM + 2] = gb_x * oy - gb_y * ox - 1.0
                for ljx, ljy, _, w in earlier:  # minus the earlier sightings' rows, weighted
                    ex = ljx - x - ox
                    ey = ljy - y - oy
                    q = max(ex * ex + ey * ey, _MIN_RANGE * _MIN_RANGE)
                    ms[DIM] -= w * ey / q
                    ms[DIM + 1] += w * ex / q
                    ms[DIM + 2] -= w * (-ey / q * oy - ex / q * ox - 1.0)
            if dt != 0.0:
                # chain rule through the step: rows d(err)/d(x1, y1, psi1) times its 3x5 Jacobian
                for row in range(dim):
                    o = row * DIM
                    g0, g1, g2 = ms[o], ms[o + 1], ms[o + 2]
                    for col in range(5):
                        ms[o + col] = g0 * jac[0][col] + g1 * jac[1][col] + g2 * jac[2][col]
            H[0] = hs
        me[0] = r - zr
        if bearing:
            me[1] = (atan2(dy, dx) - psi - zb + _PI) % _TWO_PI - _PI
            for ljx, ljy, zbj, w in earlier:
                me[1] -= w * ((atan2(ljy - y - oy, ljx - x - ox) - psi - zbj + _PI) % _TWO_PI
                              - _PI)
        return e

    return gtsam.CustomFactor(as_noise_model(noise, dim), [key], error)


def range_bearing_factor(
    key: int,
    landmark: tuple[float, float],
    z_range: float,
    z_bearing: float,
    noise: NoiseLike,
    sensor_offset: tuple[float, float] = (0.0, 0.0),
    dt: float = 0.0,
    earlier=(),
) -> gtsam.CustomFactor:
    """Range (m) and bearing (rad) to a known landmark (x, y) in m, sighted ``dt`` s after the
    keyframe; 2-D error, 1 key. ``earlier``: the frame's earlier sightings, ((lx, ly,
    z_bearing), w) each (module docstring)."""
    return _make(key, landmark, z_range, z_bearing, sensor_offset, noise, dt, earlier)


def range_factor(
    key: int,
    landmark: tuple[float, float],
    z_range: float,
    noise: NoiseLike,
    sensor_offset: tuple[float, float] = (0.0, 0.0),
    dt: float = 0.0,
) -> gtsam.CustomFactor:
    """Range (m) to a known landmark (x, y) in m, sighted ``dt`` s after the keyframe; 1-D
    error, 1 key."""
    return _make(key, landmark, z_range, None, sensor_offset, noise, dt)
