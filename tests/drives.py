"""Synthetic straight drives for filter tests: wheel speeds at 20 Hz, a gyro at 50 Hz and GPS
fixes at 5 Hz (from t = 0.2 s), the fixes at the true positions plus white noise, mapped to
WGS-84 exactly about the datum (``geodesy.enu_to_geodetic``)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import numpy as np
from ddfuse.estimation import geodesy
from ddfuse.estimation.measurements import GpsFix, GyroYawRate, WheelSpeeds


def straight_drive(datum, yaw: float, v: float, duration: float, rng: np.random.Generator, *,
                   r_wheel: float, sig_wheel: float, sig_gyro: float, sig_gps: float,
                   fix_hook: Callable[[float, float, float], tuple[float, float]] | None = None
                   ) -> Iterator:
    """The measurements of a drive from the datum at ``yaw`` (ENU, rad) and ``v`` m/s, in
    stamp order (steps of 0.01 s). ``fix_hook(t, e, n) -> (e, n)`` may move a fix (m, local
    ENU) before it is mapped to latitude and longitude."""
    wheel = v / r_wheel
    for k in range(int(round(duration / 0.01)) + 1):
        t = k * 0.01
        if k % 5 == 0:
            yield WheelSpeeds(t, wheel + rng.normal(0, sig_wheel), wheel + rng.normal(0, sig_wheel),
                              sig_wheel**2, sig_wheel**2, "wheels")
        if k % 2 == 0:
            yield GyroYawRate(t, rng.normal(0, sig_gyro), sig_gyro**2, "imu")
        if k % 20 == 0 and k > 0:
            x, y = v * t * math.cos(yaw), v * t * math.sin(yaw)
            e, n = x + rng.normal(0, sig_gps), y + rng.normal(0, sig_gps)
            if fix_hook is not None:
                e, n = fix_hook(t, e, n)
            lat, lon, alt = geodesy.enu_to_geodetic(e, n, 0.0, *datum)
            yield GpsFix(t, lat, lon, alt, np.diag([sig_gps**2, sig_gps**2, 1.0]), 0, "gps",
                         (e, n, 0.0))
