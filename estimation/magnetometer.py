"""A magnetometer (sensor_msgs/MagneticField) as the global heading Theta_g of seed 000.

Model (docs/design/sensors.md): the earth's field in the local ENU frame is horizontal
intensity H pointing to magnetic north, which lies ``declination`` D clockwise of true north, and
a vertical part: B = (H sin D, H cos D, B_up), T. A level body (x forward, y left, z up) at yaw
psi (rad, CCW from east) reads b = Rz(psi)^T B plus its hard-iron offset h (T, constant in the
sensor frame) and noise. The field's direction in the body, atan2(b_y, b_x) = (pi/2 - D) - psi,
so

    psi = pi/2 - D - atan2(b_y - h_y, b_x - h_x)

which ``magnetic_yaw`` returns wrapped to [-pi, pi]. This is seed 000's Theta_g (the compass
bearing theta = pi/2 - psi once D is applied) written once as a yaw: every estimator that takes a
``Heading`` (the unicycle EKF, the smoother, ekf_igvc's Theta_g row) uses it unchanged, with the
sensor's ``heading_offset`` (a mounting or soft-iron residual: configured, or 'estimate').

The reading's noise (std s_B per axis, T) maps to the yaw's variance s_B^2 / |b_h|^2, |b_h| the
horizontal field's magnitude: a weak horizontal field (near a magnetic pole, or a large
disturbance cancelling it) gives a correspondingly poor heading. Tilt is not compensated: the
body is taken as level (the planar robot of every estimator here); on a slope the vertical
field leaks into b_x, b_y (docs/design/sensors.md says how much).
"""

from __future__ import annotations

import math
from collections.abc import Callable

from ddfuse.estimation.config import SensorConfig
from ddfuse.estimation.frames import IDENTITY, rotate, rpy_matrix
from ddfuse.estimation.measurements import Heading
from ddfuse.estimation.reject import Reject

__all__ = ["MIN_HORIZONTAL_FIELD", "body_field", "magnetic_yaw", "magnetometer_converter"]

_HALF_PI = 0.5 * math.pi
_TWO_PI = 2.0 * math.pi
# T: a horizontal field weaker than this is no heading (the earth's is 5-40 uT away from the
# magnetic poles; a reading this weak is a saturated or disturbed sensor)
MIN_HORIZONTAL_FIELD = 1e-6


def magnetic_yaw(bx: float, by: float, declination: float) -> float:
    """Yaw of the body (rad, CCW from local east, wrapped to [-pi, pi]) from the horizontal
    field in the body frame (``bx``, ``by``, T, hard iron removed) and the declination (rad,
    east of true north positive)."""
    return math.remainder(_HALF_PI - declination - math.atan2(by, bx), _TWO_PI)


def body_field(yaw, field_enu: tuple[float, float, float]):
    """The earth's field (T) in a level body frame at ``yaw`` (rad, CCW from east; a float or
    an array): (b_x, b_y, b_z) = Rz(yaw)^T (E, N, U). The simulator's magnetometer."""
    import numpy as np

    e, n, u = field_enu
    c, s = np.cos(yaw), np.sin(yaw)
    return e * c + n * s, -e * s + n * c, u + 0.0 * c


def magnetometer_converter(s: SensorConfig, key: str) -> Callable[[tuple], list]:
    """The converter of magnetometer ``s`` (config key ``key``): a MagneticField record (t s,
    field (x, y, z) T, covariance 9-tuple T^2) -> one global Heading (source 'compass')."""
    mount = IDENTITY if s.mount_rpy == (0.0, 0.0, 0.0) else rpy_matrix(*s.mount_rpy)
    hx, hy, hz = s.hard_iron
    decl = s.declination
    yaw_std, field_std = s.noise.get("yaw"), s.noise.get("field")
    name = s.name

    def convert(rec: tuple) -> list:
        t, b, cov = rec
        if not (math.isfinite(t) and all(math.isfinite(v) for v in b)):
            raise Reject("non-finite stamp or magnetic_field")
        b = (b[0] - hx, b[1] - hy, b[2] - hz)
        if mount is not IDENTITY:
            b = rotate(mount, b)
        h2 = b[0] * b[0] + b[1] * b[1]
        if not h2 >= MIN_HORIZONTAL_FIELD * MIN_HORIZONTAL_FIELD:
            raise Reject(f"horizontal magnetic field {math.sqrt(h2):.3g} T, below "
                         f"{MIN_HORIZONTAL_FIELD:g} T: no heading (saturated or disturbed)")
        if yaw_std is not None:
            var = yaw_std * yaw_std
        else:
            if field_std is not None:
                fvar = field_std * field_std
            else:  # the message's own, the mean of its horizontal axes; all zeros: unknown
                fvar = 0.5 * (cov[0] + cov[4])
                if not (math.isfinite(fvar) and fvar > 0.0):
                    raise Reject("magnetic_field_covariance unknown (zero); set "
                                 f"{key}.noise.field (T) or {key}.noise.yaw (rad)")
            var = fvar / h2
        return [Heading(t, magnetic_yaw(b[0], b[1], decl), var, name, "compass")]

    return convert
