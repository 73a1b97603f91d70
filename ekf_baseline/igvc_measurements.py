"""The IGVC EKF's measurement models, written once for both of its paths.

As ``ddfuse.ekf_baseline.unicycle_measurements``: each ``*_rows`` function writes one
measurement's innovation y = z - h(x), its Jacobian rows and its covariance into rows ``nr``..
of the caller's zeroed ``H`` (>= nr + m, n), ``y`` and ``R`` and returns m. ``x`` is the state
of :class:`~ddfuse.ekf_baseline.igvc.IgvcEkf` (its module docstring: states, "Measurements"),
``ks`` the index of k_v (k_w follows; -1 without scale states). The reference path calls them
on numpy arrays, the compiled kernels (``ddfuse.ekf_baseline.kalman_jit``) compile them.
"""

from __future__ import annotations

import math

from ddfuse.factors.kinematics import antenna_position

__all__ = ["gyro_rows", "heading_rows", "accel_rows", "odometry_rows", "wheel_rows", "gps_rows"]

_LAT, _LON, _THETA, _X, _Y, _PSI, _V, _W, _VL, _VR, _A = range(11)
_PI = math.pi
_TWO_PI = 2.0 * math.pi
_HALF_PI = 0.5 * math.pi


def gyro_rows(x, bi, bias, z, r, H, y, R, nr):
    """A gyro's yaw rate ``z`` (rad/s): h = psi_dot + b, b the state ``bi`` (-1: the configured
    ``bias``)."""
    if bi < 0:
        y[nr] = z - (x[_W] + bias)
    else:
        y[nr] = z - (x[_W] + x[bi])
        H[nr, bi] = 1.0
    H[nr, _W] = 1.0
    R[nr, nr] = r
    return 1


def heading_rows(x, local, hi, hoff, z, r, H, y, R, nr):
    """A heading ``z`` (rad): the compass's global heading pi/2 - theta + offset, or with
    ``local`` the seed's local heading psi + offset; the offset the state ``hi`` (-1: the
    configured ``hoff``); h and the innovation wrapped."""
    if local:
        g = x[_PSI]
        H[nr, _PSI] = 1.0
    else:
        g = _HALF_PI - x[_THETA]
        H[nr, _THETA] = -1.0
    if hi >= 0:
        offset = x[hi]
        H[nr, hi] = 1.0
    else:
        offset = hoff
    h = (g + offset + _PI) % _TWO_PI - _PI
    y[nr] = (z - h + _PI) % _TWO_PI - _PI
    R[nr, nr] = r
    return 1


def accel_rows(x, z, r, H, y, R, nr):
    """A forward acceleration ``z`` (m/s^2): h = a."""
    y[nr] = z - x[_A]
    H[nr, _A] = 1.0
    R[nr, nr] = r
    return 1


def odometry_rows(x, ks, track, has_v, has_w, z0, z1, r0, r1, H, y, R, nr):
    """Odometry speed ``z0`` (m/s, if ``has_v``) and yaw rate ``z1`` (rad/s, if ``has_w``):
    v = (v_l + v_r) / 2 and (v_r - v_l) / L (seed eqs. 18-19, ``track`` L m), divided by the
    odometry scales k_v, k_w when they are estimated. One or two rows (0: neither)."""
    if ks >= 0:
        kv = x[ks]
        kw = x[ks + 1]
    else:
        kv = 1.0
        kw = 1.0
    m = 0
    if has_v:
        v = 0.5 * (x[_VL] + x[_VR])
        y[nr] = z0 - v / kv
        H[nr, _VL] = 0.5 / kv
        H[nr, _VR] = 0.5 / kv
        if ks >= 0:
            H[nr, ks] = -v / (kv * kv)
        R[nr, nr] = r0
        m += 1
    if has_w:
        r = nr + m
        w = (x[_VR] - x[_VL]) / track
        y[r] = z1 - w / kw
        H[r, _VR] = 1.0 / (track * kw)
        H[r, _VL] = -1.0 / (track * kw)
        if ks >= 0:
            H[r, ks + 1] = -w / (kw * kw)
        R[r, r] = r1
        m += 1
    return m


def wheel_rows(x, ks, rw, z0, z1, r0, r1, H, y, R, nr):
    """Wheel speeds (left ``z0``, right ``z1``, rad/s): the rim speeds over the wheel radius
    ``rw`` (m); with scale states the rim speeds -> (v / k_v, w / k_w) -> wheel speeds through
    the nominal geometry."""
    vl = x[_VL]
    vr = x[_VR]
    if ks < 0:
        y[nr] = z0 - vl / rw
        y[nr + 1] = z1 - vr / rw
        H[nr, _VL] = 1.0 / rw
        H[nr + 1, _VR] = 1.0 / rw
    else:
        kv = x[ks]
        kw = x[ks + 1]
        a = 0.5 / (kv * rw)
        b = 0.5 / (kw * rw)
        s_ = vl + vr
        d_ = vr - vl
        dkv = -a * s_ / kv
        dkw = b * d_ / kw
        y[nr] = z0 - (a * s_ - b * d_)
        y[nr + 1] = z1 - (a * s_ + b * d_)
        H[nr, _VL] = a + b
        H[nr, _VR] = a - b
        H[nr, ks] = dkv
        H[nr, ks + 1] = dkw
        H[nr + 1, _VL] = a - b
        H[nr + 1, _VR] = a + b
        H[nr + 1, ks] = dkv
        H[nr + 1, ks + 1] = -dkw
    R[nr, nr] = r0
    R[nr + 1, nr + 1] = r1
    return 2


def gps_rows(x, radius, lx, ly, delay, lat_deg, lon_deg, r0, r1, r01, r10, H, y, R, nr):
    """A fix (``lat_deg``, ``lon_deg``, degrees; covariance [[r0, r01], [r10, r1]] in m^2 east,
    north) as rows in metres (east, north) about the current estimate: scaling z, h and H by
    the same constant leaves gain and NIS unchanged and makes the logged residuals readable.
    h: the antenna (lever arm (lx, ly) m, rotated by psi) on the sphere of ``radius`` m; with
    a ``delay`` (s) where it was that long before the state's time: moved back by v delay
    along the bearing (first order, as the seed's motion model), heading psi - w delay."""
    lat0 = x[_LAT]
    lon0 = x[_LON]
    lat = lat0
    lon = lon0
    psi = x[_PSI]
    # d(moved-back state)/d(state) - I: only these entries
    j_lat_theta = j_lat_v = j_lon_lat = j_lon_theta = j_lon_v = j_psi_w = 0.0
    if delay != 0.0:
        theta = x[_THETA]
        v = x[_V]
        w = x[_W]
        ct = math.cos(theta)
        st_ = math.sin(theta)
        cl0 = math.cos(lat0)
        lat = lat0 - delay * v * ct / radius
        lon = lon0 - delay * v * st_ / (radius * cl0)
        psi = psi - delay * w
        j_lat_theta = delay * v * st_ / radius
        j_lat_v = -delay * ct / radius
        j_lon_lat = -delay * v * st_ * math.sin(lat0) / (radius * cl0 * cl0)
        j_lon_theta = -delay * v * ct / (radius * cl0)
        j_lon_v = -delay * st_ / (radius * cl0)
        j_psi_w = -delay
    # the antenna at the moved-back state: (lat, lon) rows of its Jacobian at LAT, LON, PSI
    e_off, n_off, _, _ = antenna_position(0.0, 0.0, psi, lx, ly)
    cl = math.cos(lat)
    h_lat = lat + n_off / radius
    h_lon = lon + e_off / (radius * cl)
    a_lat_psi = e_off / radius
    b_lon_lat = e_off * math.sin(lat) / (radius * cl * cl)
    b_lon_psi = -n_off / (radius * cl)
    te = radius * math.cos(lat0)
    tn = radius
    # east row: te * (lon row of H J); north row: tn * (lat row of H J)
    re = nr
    rn = nr + 1
    H[re, _LON] = te * 1.0
    H[re, _LAT] = te * (b_lon_lat + j_lon_lat)
    H[re, _PSI] = te * b_lon_psi
    H[re, _THETA] = te * (b_lon_lat * j_lat_theta + j_lon_theta)
    H[re, _V] = te * (b_lon_lat * j_lat_v + j_lon_v)
    H[re, _W] = te * (b_lon_psi * j_psi_w)
    H[rn, _LAT] = tn * 1.0
    H[rn, _PSI] = tn * a_lat_psi
    H[rn, _THETA] = tn * j_lat_theta
    H[rn, _V] = tn * j_lat_v
    H[rn, _W] = tn * (a_lat_psi * j_psi_w)
    zlat = math.radians(lat_deg)
    zlon = math.radians(lon_deg)
    dlon_z = (zlon - lon0 + _PI) % _TWO_PI - _PI
    y[re] = te * dlon_z - te * (h_lon - lon0)
    y[rn] = tn * (zlat - lat0) - tn * (h_lat - lat0)
    R[re, re] = r0
    R[re, rn] = r01
    R[rn, re] = r10
    R[rn, rn] = r1
    return 2
