"""Seed 000 models: the generated code is current, and every Jacobian matches central differences.

Lat/lon are compared in metres (scaled by the sphere radius) so that one tolerance (1e-6 in the
units of m, rad, m/s, rad/s, m/s^2 per unit) means the same thing for every entry of F and H.
"""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
import sympy
from ddfuse.ekf_baseline import igvc_codegen, igvc_jacobians, igvc_measurements
from ddfuse.ekf_baseline.igvc import STATE_NAMES, sphere_radius
from ddfuse.estimation import geodesy
from ddfuse.factors.kinematics import SERIES_THRESHOLD

RADIUS = sphere_radius(math.radians(45.0))
LAT, LON, THETA, X, Y, PSI, V, W, VL, VR, A = range(11)
SCALE = np.array([RADIUS, RADIUS] + [1.0] * 9)  # lat, lon in metres-equivalent
TRACK = 0.555
STEPS = {"euler": igvc_jacobians.euler_step, "icc": igvc_jacobians.icc_step}


def _state(rng: random.Random, **over) -> np.ndarray:
    s = np.array([
        # lon = 0: f - lon, F and H do not depend on lon, and a small |lon| keeps the rounding
        # of the lon output (eps |lon|) small for the finite differences
        math.radians(rng.uniform(-70, 70)), 0.0,
        rng.uniform(-math.pi, math.pi), rng.uniform(-200, 200), rng.uniform(-200, 200),
        rng.uniform(-math.pi, math.pi), rng.uniform(-2, 2), rng.uniform(-1, 1),
        0.0, 0.0, rng.uniform(-1, 1),
    ])
    for k, v in over.items():
        s[STATE_NAMES.index(k)] = v
    s[VL] = s[V] - 0.5 * TRACK * s[W]
    s[VR] = s[V] + 0.5 * TRACK * s[W]
    return s


def numeric_jacobian(fun, s: np.ndarray, out_scale: np.ndarray) -> np.ndarray:
    """Five-point central differences of fun (returning a vector) in scaled coordinates.

    Lat/lon outputs carry ~1e-16 rad (up to 1.4e-9 m) of rounding, so the step must be large
    (h = 1 cm or 0.01 rad, m/s, ...): the five-point stencil's truncation error, h^4 f^(5) / 30,
    is then ~1e-10 while the rounding error, about 1.5 eps / h, stays below 2e-7."""
    s = np.asarray(s, float)
    cols = []
    h = 1e-2
    for j in range(s.size):
        d = np.zeros(s.size)
        d[j] = h / SCALE[j]
        f = [np.asarray(fun(s + k * d), float) for k in (2, 1, -1, -2)]
        cols.append((-f[0] + 8 * f[1] - 8 * f[2] + f[3]) * out_scale / (12 * h))
    return np.array(cols).T


def scaled(J: np.ndarray, out_scale: np.ndarray) -> np.ndarray:
    return out_scale[:, None] * np.asarray(J, float) / SCALE[None, :]


CASES = [
    dict(),
    dict(psi_dot=0.0),
    dict(psi_dot=1e-12),
    dict(psi_dot=-3e-7),
    dict(psi_dot=SERIES_THRESHOLD / 0.1 * (1 - 1e-9)),  # just inside the series branch
    dict(psi_dot=SERIES_THRESHOLD / 0.1 * (1 + 1e-9)),  # just outside it
    dict(theta=math.pi - 1e-9, psi=-math.pi + 1e-9),
    dict(theta=-math.pi + 1e-9, psi=math.pi - 1e-9, psi_dot=0.0),
    dict(v=0.0, psi_dot=0.0),  # standing still: the seed's sqrt distance has no derivative here
    dict(v=-1.5),  # reversing
]


@pytest.mark.parametrize("kind", ["euler", "icc"])
@pytest.mark.parametrize("case", range(len(CASES)))
def test_motion_jacobian_matches_central_differences(kind, case):
    rng = random.Random(100 + case)
    step = STEPS[kind]
    dt = 0.1
    for _ in range(5):
        s = _state(rng, **CASES[case])
        f0, F = step(s, dt, TRACK, RADIUS)
        assert len(f0) == 11 and len(F) == 11 and all(len(r) == 11 for r in F)
        num = numeric_jacobian(lambda q: step(q, dt, TRACK, RADIUS)[0], s, SCALE)
        np.testing.assert_allclose(scaled(F, SCALE), num, rtol=0, atol=1e-6)


def test_euler_latlon_rows_are_the_great_circle_formulas():
    rng = random.Random(7)
    for _ in range(50):
        s = _state(rng)
        dt = rng.uniform(0.01, 2.0)
        f, _ = igvc_jacobians.euler_step(s, dt, TRACK, RADIUS)
        lat2, lon2 = geodesy.great_circle_forward(s[LAT], s[LON], s[THETA], s[V] * dt, RADIUS)
        assert f[LAT] == pytest.approx(lat2, abs=1e-15)
        dlon = (f[LON] - lon2 + math.pi) % (2 * math.pi) - math.pi
        assert abs(dlon) < 1e-14


def test_reversing_moves_latlon_backwards_with_xy():
    """Seed eq. 3's d is a square root, so reversing would move lat/lon forward; v dt is signed."""
    s = _state(random.Random(3), lat=math.radians(45), lon=0.0, theta=0.0, psi=math.pi / 2,
               v=-2.0, psi_dot=0.0, a=0.0)
    for kind, step in STEPS.items():
        f, _ = step(s, 1.0, TRACK, RADIUS)
        north_m = (f[LAT] - s[LAT]) * RADIUS
        assert f[Y] - s[Y] == pytest.approx(-2.0, abs=1e-12), kind
        assert north_m == pytest.approx(-2.0, abs=1e-6), kind


def test_icc_equals_seed_appendix_away_from_zero_and_euler_at_zero():
    """Eqs. 28-33 (with eq. 28 corrected to (v_r - v_l)/L) for a real turn; straight line at 0."""
    rng = random.Random(11)
    for _ in range(30):
        s = _state(rng, psi_dot=rng.choice([-1, 1]) * rng.uniform(0.2, 1.5))
        dt = rng.uniform(0.05, 1.0)
        f, _ = igvc_jacobians.icc_step(s, dt, TRACK, RADIUS)
        vl, vr = s[VL], s[VR]
        w = (vr - vl) / TRACK  # eq. 28 corrected
        R = TRACK * (vl + vr) / (2 * (vr - vl))  # eq. 29
        icx, icy = s[X] - R * math.sin(s[PSI]), s[Y] + R * math.cos(s[PSI])  # eq. 30
        c, sn = math.cos(w * dt), math.sin(w * dt)
        x1 = (s[X] - icx) * c - (s[Y] - icy) * sn + icx  # eq. 31
        y1 = (s[X] - icx) * sn + (s[Y] - icy) * c + icy  # eq. 32
        assert f[X] == pytest.approx(x1, abs=1e-9)
        assert f[Y] == pytest.approx(y1, abs=1e-9)
        assert f[PSI] == pytest.approx(s[PSI] + w * dt, abs=1e-12)  # eq. 33
    s = _state(rng, psi_dot=0.0)
    fi, Fi = igvc_jacobians.icc_step(s, 0.5, TRACK, RADIUS)
    fe, Fe = igvc_jacobians.euler_step(s, 0.5, TRACK, RADIUS)
    np.testing.assert_allclose(fi, fe, rtol=0, atol=1e-12)
    # d/dpsi_dot differs (the arc bends, the Euler step does not); every other column agrees
    cols = [j for j in range(11) if j != W]
    np.testing.assert_allclose(np.array(Fi)[:, cols], np.array(Fe)[:, cols], rtol=0, atol=1e-12)


def test_icc_is_continuous_through_zero_turn_rate():
    rng = random.Random(5)
    s = _state(rng)
    prev = None
    for w in np.linspace(-2e-3, 2e-3, 41):  # crosses 0
        s[W] = w
        f, F = igvc_jacobians.icc_step(s, 0.5, TRACK, RADIUS)
        cur = np.concatenate([np.array(f) * SCALE, (np.array(F) / SCALE[None, :]).ravel()])
        if prev is not None:
            assert np.max(np.abs(cur - prev)) < 1e-3  # smooth: small change per 1e-4 rad/s step
        prev = cur
    for a in (SERIES_THRESHOLD * (1 - 1e-12), SERIES_THRESHOLD * (1 + 1e-12)):
        s[W] = a / 0.5
        f, F = igvc_jacobians.icc_step(s, 0.5, TRACK, RADIUS)
        if a < SERIES_THRESHOLD:
            inside = np.array(f) * SCALE, np.array(F)
        else:
            np.testing.assert_allclose(np.array(f) * SCALE, inside[0], rtol=0, atol=1e-9)
            np.testing.assert_allclose(np.array(F), inside[1], rtol=0, atol=1e-9)


def test_icc_latlon_follow_the_arc_on_the_ellipsoid():
    """The chord step in lat/lon lands where the x/y arc lands, mapped through WGS-84 ENU, to the
    sphere's scale error (~0.2 % of the step)."""
    lat0, lon0 = 45.0, 7.0
    s = _state(random.Random(2), lat=math.radians(lat0), lon=math.radians(lon0), x=0.0, y=0.0,
               psi=0.3, v=1.0, psi_dot=0.8)
    s[THETA] = math.pi / 2 - s[PSI]
    f, _ = igvc_jacobians.icc_step(s, 3.0, TRACK, RADIUS)
    lat, lon, _ = geodesy.enu_to_geodetic(f[X], f[Y], 0.0, lat0, lon0, 0.0)
    e, n, _ = geodesy.geodetic_to_enu(math.degrees(f[LAT]), math.degrees(f[LON]), 0.0,
                                      lat0, lon0, 0.0)
    step = math.hypot(f[X], f[Y])
    assert math.hypot(e - f[X], n - f[Y]) < 3e-3 * step


def _rows(model, s, *args):
    """(innovation y, H) of one ``igvc_measurements`` model at state ``s``."""
    H, y, R = np.zeros((2, len(s))), np.zeros(2), np.zeros((2, 2))
    m = model(list(s), *args, H, y, R, 0)
    return y[:m], H[:m]


def _gps(s, lever, lat_deg, lon_deg):
    return _rows(igvc_measurements.gps_rows, s, RADIUS, lever[0], lever[1], 0.0, lat_deg,
                 lon_deg, 1.0, 1.0, 0.0, 0.0)


def _antenna(s, lever):
    """The antenna's (lat, lon), rad, from the innovation of a fix at the state's own position
    (metres about the estimate)."""
    y, _ = _gps(s, lever, math.degrees(s[LAT]), math.degrees(s[LON]))
    return s[LAT] - y[1] / RADIUS, s[LON] - y[0] / (RADIUS * math.cos(s[LAT]))


@pytest.mark.parametrize("lever", [(0.0, 0.0), (0.4, -0.2)])
def test_gps_jacobian(lever):
    """The fix's rows (east, north m about the estimate): H = -d y / d state at a fix on the
    predicted antenna (where the metric scaling, a constant of the linearisation, has no
    derivative)."""
    rng = random.Random(21)
    for over in (dict(), dict(psi=math.pi - 1e-9), dict(psi=-math.pi + 1e-9)):
        s = _state(rng, **over)
        zlat, zlon = (math.degrees(a) for a in _antenna(s, lever))
        y0, H = _gps(s, lever, zlat, zlon)
        assert np.abs(y0).max() < 1e-6
        out = np.array([1.0, 1.0])
        num = numeric_jacobian(lambda q, a=zlat, b=zlon: -_gps(q, lever, a, b)[0], s, out)
        np.testing.assert_allclose(scaled(H, out), num, rtol=0, atol=1e-6)
    # the antenna offset itself: lever arm (1, 0) pointing north moves the antenna 1 m north
    s = _state(rng, psi=math.pi / 2, lat=math.radians(45))
    h = _antenna(s, (1.0, 0.0))
    assert (h[0] - s[LAT]) * RADIUS == pytest.approx(1.0, abs=1e-9)
    assert abs(h[1] - s[LON]) < 1e-15


def _heading(s, offset, local, z=0.0):
    """The predicted reading wrap(h(s)) and H from the innovation of a reading ``z``."""
    y, H = _rows(igvc_measurements.heading_rows, s, local, -1, offset, z, 1.0)
    return (z - y[0] + math.pi) % (2 * math.pi) - math.pi, H


@pytest.mark.parametrize("local", [False, True])
def test_heading_jacobian_and_wrap(local):
    rng = random.Random(9)
    for over in (dict(), dict(theta=1e-9, psi=math.pi - 1e-9), dict(theta=-1e-9, psi=-math.pi)):
        s = _state(rng, **over)
        h, H = _heading(s, 0.3, local)
        assert -math.pi <= h < math.pi

        def fun(q, h0=h):
            # unwrap against the centre value: the model wraps, the derivative does not see it
            return [h0 + ((_heading(q, 0.3, local)[0] - h0 + math.pi) % (2 * math.pi) - math.pi)]

        num = numeric_jacobian(fun, s, np.array([1.0]))
        np.testing.assert_allclose(scaled(H, np.array([1.0])), num, rtol=0, atol=1e-6)
    # a compass reading of east (yaw 0) is a bearing of 90 deg
    s = _state(rng, theta=math.pi / 2)
    assert _heading(s, 0.0, False)[0] == pytest.approx(0.0, abs=1e-15)


def test_generated_code_is_up_to_date():
    """Re-derive with sympy; the committed igvc_jacobians.py must be what the generator writes.

    With another sympy version the printed code may legitimately differ in form, so then the
    freshly generated functions are compared numerically with the committed ones instead."""
    text = igvc_codegen.generate()
    committed = igvc_codegen.TARGET.read_text()
    if sympy.__version__ == igvc_jacobians.SYMPY_VERSION:
        assert committed == text, "run: python3 -m ddfuse.ekf_baseline.igvc_codegen"
        return
    ns: dict = {}
    exec(compile(text, "<generated>", "exec"), ns)  # noqa: S102 - our own generator's output
    rng = random.Random(1)
    for kind in ("euler", "icc"):
        for _ in range(20):
            s = _state(rng, psi_dot=rng.choice([0.0, 1e-9, 0.7]))
            f1, F1 = ns[f"{kind}_step"](s, 0.1, TRACK, RADIUS)
            f2, F2 = STEPS[kind](s, 0.1, TRACK, RADIUS)
            np.testing.assert_allclose(f1, f2, rtol=1e-13, atol=1e-13)
            np.testing.assert_allclose(F1, F2, rtol=1e-11, atol=1e-13)


def test_measurement_rows_with_calibration_states_match_central_differences():
    """The filter's measurement models as it applies them (IgvcEkf._measurement: innovation and
    H rows) with a gyro-bias, a heading-offset and the odometry-scale states, and a GPS
    fix 0.3 s late: H = -d(innovation)/d(state) by central differences."""
    from ddfuse.ekf_baseline.igvc import IgvcEkf
    from ddfuse.estimation.config import parse_config
    from ddfuse.estimation.measurements import (
        ForwardAccel,
        GpsFix,
        GyroYawRate,
        Heading,
        WheelOdometry,
        WheelSpeeds,
    )

    datum = (45.0, 7.0, 300.0)
    cfg = parse_config({
        "sensors": {
            "odometry": [{"topic": "/odom"}],
            "wheels": [{"topic": "/js", "joints": ["l", "r"], "noise": {"speed": 0.1}}],
            "imu": [{"topic": "/imu", "use": ["yaw", "yaw_rate", "accel"],
                     "gyro_bias": "estimate", "heading_offset": "estimate"}],
            "gps": [{"topic": "/fix", "lever_arm": [0.4, -0.2], "delay": 0.3}],
        },
        "robot": {"wheel_radius": 0.17, "track_width": TRACK, "wheel_radius_std": 0.003,
                  "track_width_std": 0.02},
        "frame": {"datum": list(datum)},
        "initial_pose": [0.0, 0.0, 0.0],
    })
    ekf = IgvcEkf(cfg)
    names = ekf.state_names
    assert names[11:] == ("bg:/imu", "hoff:/imu", "k_v", "k_w")
    ekf._hoff_ready.add(12)
    rng = random.Random(3)
    lat, lon, _ = geodesy.enu_to_geodetic(30.0, -20.0, 0.0, *datum)
    fix = GpsFix(0.0, lat, lon, 300.0, np.diag([1.0, 1.2, 4.0]), 0, "/fix", (30.0, -20.0, 0.0))
    ms = [GyroYawRate(0.0, 0.3, 1e-4, "/imu"), Heading(0.0, 2.0, 1e-3, "/imu", "compass"),
          Heading(0.0, -1.0, 1e-3, "/imu", "pose"), ForwardAccel(0.0, 0.2, 0.01, "/imu"),
          WheelOdometry(0.0, 1.0, 0.3, 0.01, 0.02, "/odom"),
          WheelSpeeds(0.0, 5.0, 7.0, 0.1, 0.2, "/js"), fix]
    for _ in range(5):
        s = _state(rng)
        # at the fix: the GPS innovation is then only the lever arm and the delay (< 1.5 m), so
        # the metric scaling about the estimate (treated as a constant, see _gps_metres)
        # changes it by < 3e-7 per metre of latitude
        s[LAT], s[LON] = math.radians(lat), math.radians(lon)
        x0 = np.concatenate([s, [0.01, 0.3, 1.02, 0.97]])
        scale = np.concatenate([SCALE, np.ones(4)])
        for m in ms:
            ekf.kf.x = x0.copy()
            y0, H = _measured(ekf, m)

            def neg_y(x, m=m, y0=y0):
                ekf.kf.x = x
                y = _measured(ekf, m)[0]
                # unwrap angle innovations against the centre value
                return -(y0 + (y - y0 + math.pi) % (2 * math.pi) - math.pi)

            cols = []
            h = 1e-2  # five-point stencil, as numeric_jacobian: lat/lon rounding needs large h
            for j in range(len(names)):
                d = np.zeros(len(names))
                d[j] = h / scale[j]
                f = [neg_y(x0 + k * d) for k in (2, 1, -1, -2)]
                cols.append((-f[0] + 8 * f[1] - 8 * f[2] + f[3]) / (12 * h))
            num = np.array(cols).T
            np.testing.assert_allclose(H / scale, num, rtol=0, atol=1e-6,
                                       err_msg=type(m).__name__)


def _measured(ekf, m):
    """(innovation y, H) of ``ekf._measurement(m)`` at the filter's state."""
    H, y, R = np.zeros((2, ekf.n)), np.zeros(2), np.zeros((2, 2))
    _kind, nr = ekf._measurement(m, H, y, R)
    return y[:nr].copy(), H[:nr].copy()
