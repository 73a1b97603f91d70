"""The IGVC EKF's state layout, process noise and Earth sphere, in plain floats.

State indices (``LAT`` .. ``A``, seed 000's 11 states; ``ddfuse.ekf_baseline.igvc`` module
docstring), :class:`IgvcNoise` (the noise densities and initial uncertainty),
:func:`igvc_q_values` (the discrete process noise of one step, which the compiled kernels of
``ddfuse.ekf_baseline.kalman_jit`` compile too) and :func:`sphere_radius` (the sphere the
great-circle motion model runs on). Design notes: docs/design/igvc_ekf.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from ddfuse.ekf_baseline import GIVEN_POSE_STD
from ddfuse.ekf_baseline.unicycle_motion import ProcessNoise
from ddfuse.estimation import geodesy

__all__ = ["IgvcNoise", "igvc_q_values", "sphere_radius", "LAT", "LON", "THETA", "X", "Y", "PSI",
           "V", "W", "VL", "VR", "A", "N", "HALF_PI"]

LAT, LON, THETA, X, Y, PSI, V, W, VL, VR, A = range(11)
N = 11
HALF_PI = 0.5 * math.pi
# flat indices (row-major, 11 x 11) of the entries of Q that IgvcEkf._q_values gives, in order
_Q_INDEX = np.ravel_multi_index((
    [X, Y, LON, LAT, LON, X, LAT, Y, PSI, THETA, PSI, THETA, A, W, VL, VR],
    [X, Y, LON, LAT, X, LON, Y, LAT, PSI, THETA, THETA, PSI, A, W, VL, VR]), (N, N))

def sphere_radius(lat_rad: float) -> float:
    """Radius (m) of the sphere that best fits WGS-84 around latitude ``lat_rad``: the Gaussian
    mean radius sqrt(M N) of the meridian (M) and prime-vertical (N) radii of curvature.

    The seed's great-circle formulas assume a sphere; with this radius the north and east scale
    errors against the ellipsoid are equal and opposite, (N - M) / (2 sqrt(M N)), about 0.17 %
    at 45 deg, instead of up to 0.35 % with the seed's "either value works" polar or equatorial
    radius."""
    s2 = math.sin(lat_rad) ** 2
    w = 1.0 - geodesy.WGS84_E2 * s2
    m = geodesy.WGS84_A * (1.0 - geodesy.WGS84_E2) / w**1.5
    n = geodesy.WGS84_A / math.sqrt(w)
    return math.sqrt(m * n)


@dataclass
class IgvcNoise:
    """Process noise and initial uncertainty of the 11-state filter (SI units, std devs or PSDs).

    Continuous white-noise spectral densities (variance per second of the random walk they
    drive): ``jerk_psd`` on a, (m/s^3)^2 s; ``yaw_accel_psd`` on psi_dot, (rad/s^2)^2 s;
    ``position_psd`` on the position, m^2/s, applied to (x, y) and (lat, lon) alike (Euler and
    slip errors); ``heading_psd`` on the heading, rad^2/s, applied to psi and theta alike;
    ``frame_psd``, m^2/s, independent between (lat, lon) and (x, y): the sphere-vs-ellipsoid and
    meridian-convergence mismatch between the two position representations (it also keeps P
    positive definite); ``frame_heading_psd``, rad^2/s, likewise between theta and psi (the
    meridian convergence, d(lon) sin(lat), makes the compass bearing and the local yaw drift
    apart by ~v tan(lat) / R rad/s). ``slip_var``, (m/s)^2 per step, is the wheel speed's
    deviation from the body twist (slip); it does not accumulate because the wheel states are
    recomputed each step.

    The body-slip densities default to the unicycle EKF's (``unicycle_motion.ProcessNoise``:
    one robot, one statement of how far its motion departs from its twist): ``heading_psd`` is
    its heading density squared, ``position_psd`` its *longitudinal* density squared -- the
    isotropic density that covers the larger, along-track one in every direction (errata 000
    #42: the lower mean of along- and across-track left the filter overconfident along track).
    """

    jerk_psd: float = 0.5
    yaw_accel_psd: float = 0.1
    position_psd: float = ProcessNoise.pos_long ** 2
    heading_psd: float = ProcessNoise.heading ** 2
    frame_psd: float = 1e-6
    frame_heading_psd: float = 1e-8
    slip_var: float = 1e-4
    init_position_std: float = GIVEN_POSE_STD[0]  # m, with an initial pose given
    init_heading_std: float = GIVEN_POSE_STD[1]  # rad, with an initial pose given
    init_speed_std: float = 0.5  # m/s
    init_yaw_rate_std: float = 0.2  # rad/s
    init_accel_std: float = 0.5  # m/s^2
    # calibration states (IgvcEkf docstring); walks used when the IMU's config states none
    gyro_bias_walk: float = 1e-4  # rad/s/sqrt(s)
    heading_offset_walk: float = 0.02  # rad/sqrt(s)
    init_bias_std: float = 0.02  # rad/s


def igvc_q_values(lat: float, dt: float, radius: float, position_psd: float, frame_psd: float,
                  heading_psd: float, frame_heading_psd: float, jerk_psd: float,
                  yaw_accel_psd: float, slip_var: float) -> tuple[float, ...]:
    """The discrete process noise Q of one step of ``dt`` s at latitude ``lat`` (rad) as its
    values at the flat indices _Q_INDEX (the rest is 0), from the :class:`IgvcNoise` densities
    as floats (its units; ``radius`` m): shared position noise for (x, y) and (lat, lon), shared
    heading noise for psi and -theta, the frame noise independent between the pairs, jerk on
    a, angular acceleration on psi_dot, slip on the wheel speeds. Plain floats: the compiled
    filter (ekf_baseline.kalman_jit) runs this same code."""
    rc = radius * math.cos(lat)
    r = radius
    pos = position_psd * dt
    frame = frame_psd * dt
    head = heading_psd * dt
    fh = frame_heading_psd * dt
    lon_x = pos / rc
    lat_y = pos / r
    return (
        pos + frame, pos + frame,  # x x, y y
        pos / rc / rc + frame / rc / rc,  # lon lon
        pos / r / r + frame / r / r,  # lat lat
        lon_x, lon_x, lat_y, lat_y,  # lon x, x lon, lat y, y lat
        head + fh, head + fh, -head, -head,  # psi psi, theta theta, psi theta, theta psi
        jerk_psd * dt, yaw_accel_psd * dt, slip_var, slip_var,  # a, w, vl, vr
    )
