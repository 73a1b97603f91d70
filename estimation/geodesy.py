"""WGS-84 geodetic <-> local ENU about a datum (exact, via ECEF), and great-circle formulas.

Angles in degrees at the interface (lat, lon as in sensor_msgs/NavSatFix), metres for lengths,
altitude above the WGS-84 ellipsoid. ENU: x east, y north, z up, tangent plane at the datum.
All functions accept scalars or numpy arrays (broadcast elementwise).
"""

from __future__ import annotations

import math

import numpy as np

WGS84_A = 6378137.0  # semi-major axis, m
WGS84_F = 1.0 / 298.257223563
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)  # second eccentricity squared
EARTH_MEAN_RADIUS = 6371008.8  # m, IUGG mean radius R1, for great-circle formulas


def geodetic_to_ecef(lat, lon, alt):
    """(lat deg, lon deg, alt m) -> ECEF (X, Y, Z) in metres."""
    phi, lam = np.radians(lat), np.radians(lon)
    s, c = np.sin(phi), np.cos(phi)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s * s)
    return (n + alt) * c * np.cos(lam), (n + alt) * c * np.sin(lam), (n * (1 - WGS84_E2) + alt) * s


def ecef_to_geodetic(x, y, z):
    """ECEF (m) -> (lat deg, lon deg, alt m). Bowring's start, refined to < 1e-12 rad.

    Accurate to well below a millimetre anywhere from the Earth's centre's far side of a few km
    to orbit; not defined at the Earth's centre."""
    x, y, z = np.asarray(x, float), np.asarray(y, float), np.asarray(z, float)
    lam = np.arctan2(y, x)
    p = np.hypot(x, y)
    # Bowring's parametric-latitude start is already within ~1e-10 rad; two Newton-like
    # refinements of the exact relation make it exact to double precision.
    beta = np.arctan2(z, p * (1.0 - WGS84_F))
    phi = np.arctan2(z + WGS84_EP2 * WGS84_B * np.sin(beta) ** 3,
                     p - WGS84_E2 * WGS84_A * np.cos(beta) ** 3)
    for _ in range(2):
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(phi), np.cos(phi))
        phi = np.arctan2(z + WGS84_EP2 * WGS84_B * np.sin(beta) ** 3,
                         p - WGS84_E2 * WGS84_A * np.cos(beta) ** 3)
    s, c = np.sin(phi), np.cos(phi)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s * s)
    # Two altitude forms, each well conditioned away from the poles / the equator respectively.
    alt = np.where(np.abs(c) > 0.5, p / np.where(c == 0, 1, c) - n,
                   z / np.where(s == 0, 1, s) - n * (1.0 - WGS84_E2))
    out = np.degrees(phi), np.degrees(lam), alt
    if np.ndim(x) == 0:
        return tuple(float(v) for v in out)
    return out


def _enu_rotation(lat0, lon0):
    phi, lam = math.radians(lat0), math.radians(lon0)
    sp, cp, sl, cl = math.sin(phi), math.cos(phi), math.sin(lam), math.cos(lam)
    # Rows: east, north, up unit vectors expressed in ECEF.
    return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])


def geodetic_to_enu(lat, lon, alt, lat0, lon0, alt0):
    """(lat deg, lon deg, alt m) -> (east, north, up) m about the datum (lat0, lon0, alt0)."""
    x, y, z = geodetic_to_ecef(lat, lon, alt)
    x0, y0, z0 = geodetic_to_ecef(lat0, lon0, alt0)
    r = _enu_rotation(lat0, lon0)
    d = np.array([np.asarray(x) - x0, np.asarray(y) - y0, np.asarray(z) - z0], dtype=float)
    e, n, u = np.tensordot(r, d, axes=1)
    if np.ndim(lat) == 0 and np.ndim(lon) == 0 and np.ndim(alt) == 0:
        return float(e), float(n), float(u)
    return e, n, u


def enu_to_geodetic(e, n, u, lat0, lon0, alt0):
    """(east, north, up) m about the datum -> (lat deg, lon deg, alt m)."""
    x0, y0, z0 = geodetic_to_ecef(lat0, lon0, alt0)
    r = _enu_rotation(lat0, lon0)
    d = np.tensordot(r.T, np.array([e, n, u], dtype=float), axes=1)
    return ecef_to_geodetic(d[0] + x0, d[1] + y0, d[2] + z0)


def enu_covariance_is_valid(cov) -> bool:
    """True when an ENU position covariance (3x3, or its 9 entries row-major) is finite,
    symmetric and has a positive definite east/north block: what a NavSatFix must carry to be
    usable without a configured noise (the estimators invert that block; the vertical is
    unused). Plain floats: the reader calls it per fix (docs/design/performance.md)."""
    c = tuple(np.asarray(cov, float).ravel().tolist()) if isinstance(cov, np.ndarray) else cov
    if len(c) != 9 or not all(math.isfinite(v) for v in c) or not (c[0] > 0.0 and c[4] > 0.0):
        return False
    tol = 1e-9 * max(1.0, max(abs(v) for v in c))
    for i, j in ((1, 3), (2, 6), (5, 7)):  # np.allclose(c, c.T, atol=tol): rtol 1e-5 too
        if abs(c[i] - c[j]) > tol + 1e-5 * abs(c[j]) or abs(c[j] - c[i]) > tol + 1e-5 * abs(c[i]):
            return False
    return c[0] * c[4] - c[1] * c[3] > 0.0


def great_circle_forward(lat, lon, bearing, distance, radius=EARTH_MEAN_RADIUS):
    """Destination on a sphere from (lat, lon) [rad] after ``distance`` [m] along the initial
    ``bearing`` [rad, clockwise from north]: the forward formulas of seed document 000, eqs. 4-5,
    with distance and radius in the same unit (the document mixes km and a polar radius).

    Returns (lat2, lon2) in radians, lon2 wrapped to [-pi, pi)."""
    delta = distance / radius
    sl, cl = math.sin(lat), math.cos(lat)
    sd, cd = math.sin(delta), math.cos(delta)
    lat2 = math.asin(sl * cd + cl * sd * math.cos(bearing))
    lon2 = lon + math.atan2(math.sin(bearing) * sd * cl, cd - sl * math.sin(lat2))
    return lat2, (lon2 + math.pi) % (2.0 * math.pi) - math.pi


def great_circle_distance_bearing(lat1, lon1, lat2, lon2, radius=EARTH_MEAN_RADIUS):
    """Inverse of great_circle_forward: (distance m, initial bearing rad clockwise from north)
    from (lat1, lon1) to (lat2, lon2), radians. Haversine distance (well conditioned when short)."""
    dlat, dlon = lat2 - lat1, lon2 - lon1
    a = math.sin(dlat / 2) ** 2 + math.cos(lat1) * math.cos(lat2) * math.sin(dlon / 2) ** 2
    d = 2.0 * radius * math.asin(min(1.0, math.sqrt(a)))
    y = math.sin(dlon) * math.cos(lat2)
    x = math.cos(lat1) * math.sin(lat2) - math.sin(lat1) * math.cos(lat2) * math.cos(dlon)
    b = math.atan2(y, x)
    return d, b


FAR_DATUM_M = 100e3  # m: a stated datum this far from the first fix is not the robot's site


def far_datum(fix, datum: tuple[float, float, float], topic: str) -> str | None:
    """The warning for a config whose ``frame.datum`` (lat deg, lon deg, alt m) is over
    ``FAR_DATUM_M`` from the first GPS ``fix`` (its ``enu`` filled, m): a mistyped datum, or one
    of another site. The fixes are still converted exactly; what breaks is what the config
    states in that frame (a ground-truth initial pose, a landmark map). None when near."""
    d = math.hypot(fix.enu[0], fix.enu[1])
    if not d > FAR_DATUM_M:
        return None
    return (f"topic {topic}: the first fix ({fix.lat:.6f}, {fix.lon:.6f}) is {d / 1e3:.0f} km "
            f"from frame.datum ({datum[0]:g}, {datum[1]:g}): the local ENU frame's origin "
            "should be where the robot drives; a ground-truth initial pose or a landmark map is "
            "read in that frame (leave frame.datum out to take the first fix)")
