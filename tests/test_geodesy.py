"""Geodesy against pymap3d (an independent implementation) and round trips."""

import math

import numpy as np
import pytest
from ddfuse.estimation import geodesy as g

pymap3d = pytest.importorskip("pymap3d")

DATUMS = [(49.9, 8.9, 120.0), (-33.87, 151.21, 40.0), (0.0, 0.0, 0.0), (78.2, 15.6, 10.0),
          (37.0, -122.0, -20.0)]


@pytest.mark.parametrize("datum", DATUMS)
def test_enu_matches_pymap3d_within_10km(datum):
    rng = np.random.default_rng(1)
    lat0, lon0, alt0 = datum
    enu = rng.uniform([-10000, -10000, -200], [10000, 10000, 500], size=(200, 3))
    for e, n, u in enu:
        ref = pymap3d.enu2geodetic(e, n, u, lat0, lon0, alt0, deg=True)
        lat, lon, alt = g.enu_to_geodetic(e, n, u, lat0, lon0, alt0)
        # 1e-8 deg is about 1.1 mm of latitude.
        assert abs(lat - ref[0]) * 111_320 < 1e-3
        assert abs(lon - ref[1]) * 111_320 * math.cos(math.radians(lat0)) < 1e-3
        assert abs(alt - ref[2]) < 1e-3
        back = g.geodetic_to_enu(lat, lon, alt, lat0, lon0, alt0)
        assert np.allclose(back, (e, n, u), atol=1e-6)
        e2, n2, u2 = pymap3d.geodetic2enu(ref[0], ref[1], ref[2], lat0, lon0, alt0, deg=True)
        assert np.allclose(g.geodetic_to_enu(ref[0], ref[1], ref[2], lat0, lon0, alt0),
                           (e2, n2, u2), atol=1e-3)


def test_ecef_matches_pymap3d_and_inverts():
    rng = np.random.default_rng(2)
    lat = rng.uniform(-89.9, 89.9, 500)
    lon = rng.uniform(-180, 180, 500)
    alt = rng.uniform(-500, 9000, 500)
    x, y, z = g.geodetic_to_ecef(lat, lon, alt)
    rx, ry, rz = pymap3d.geodetic2ecef(lat, lon, alt, deg=True)
    assert np.max(np.abs(np.array([x, y, z]) - np.array([rx, ry, rz]))) < 1e-6
    la, lo, al = g.ecef_to_geodetic(x, y, z)
    assert np.max(np.abs(la - lat)) < 1e-10 and np.max(np.abs(lo - lon)) < 1e-10
    assert np.max(np.abs(al - alt)) < 1e-6


def test_vectorised_matches_scalar():
    lat0, lon0, alt0 = DATUMS[0]
    e, n, u = np.array([10.0, -300.0]), np.array([5.0, 7000.0]), np.array([0.0, 3.0])
    lat, lon, alt = g.enu_to_geodetic(e, n, u, lat0, lon0, alt0)
    for i in range(2):
        assert np.allclose((lat[i], lon[i], alt[i]),
                           g.enu_to_geodetic(e[i], n[i], u[i], lat0, lon0, alt0), atol=1e-12)


def test_great_circle_forward_inverse_and_vs_enu():
    lat0, lon0 = math.radians(42.0), math.radians(-83.0)
    for bearing_deg in (0, 45, 90, 179, 270):
        b = math.radians(bearing_deg)
        lat2, lon2 = g.great_circle_forward(lat0, lon0, b, 100.0)
        d, b2 = g.great_circle_distance_bearing(lat0, lon0, lat2, lon2)
        assert abs(d - 100.0) < 1e-6
        assert abs(math.remainder(b2 - b, 2 * math.pi)) < 1e-6
        # On a sphere vs the ellipsoid, 100 m should agree to a few decimetres at most.
        e, n, _ = g.geodetic_to_enu(math.degrees(lat2), math.degrees(lon2), 0.0,
                                    math.degrees(lat0), math.degrees(lon0), 0.0)
        assert abs(math.hypot(e, n) - 100.0) < 0.5
        assert abs(math.remainder(math.atan2(e, n) - b, 2 * math.pi)) < 1e-2


def test_zero_distance_is_identity():
    lat2, lon2 = g.great_circle_forward(0.3, 1.2, 2.0, 0.0)
    assert (lat2, lon2) == pytest.approx((0.3, 1.2), abs=1e-15)


def test_covariance_validity():
    assert g.enu_covariance_is_valid(np.diag([1.0, 1.0, 4.0]))
    assert not g.enu_covariance_is_valid(np.zeros((3, 3)))
    assert not g.enu_covariance_is_valid(np.diag([1.0, np.nan, 1.0]))
