"""The simulated GPS receiver: fixes of the true position with white or time-correlated errors.

A fix measured at t is the truth at t + noise (horizontal, vertical std), optional outliers
(tens of metres, added on top), random dropouts, outage windows, and a constant latency: it is
stamped t + delay. The noise is white (``GpsSpec.correlation_s`` 0) or, per axis, a first-order
Gauss-Markov process of that correlation time with the same stationary std (a receiver's
multipath and atmospheric error wanders slowly), or with ``GpsSpec.urban`` the urban model of
``urban_gps`` (canyons, multipath bursts, NLOS jumps, bridges). Positions are ENU metres about
the datum, converted to WGS-84 latitude and longitude (deg) and ellipsoidal altitude (m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ddfuse.estimation.geodesy import enu_to_geodetic
from ddfuse.evaluation.simulate.motion import Truth
from ddfuse.evaluation.simulate.scenarios import Scenario
from ddfuse.evaluation.simulate.sensors import gauss_markov, sample_times
from ddfuse.evaluation.simulate.urban_gps import MULTIPATH, urban_errors


@dataclass
class GpsData:
    t: np.ndarray  # s, header stamp = t_measured + delay
    t_measured: np.ndarray  # s, when the position was true
    enu: np.ndarray  # (n, 3) m, measured position in the local ENU frame
    lat: np.ndarray  # deg
    lon: np.ndarray  # deg
    alt: np.ndarray  # m
    outlier: np.ndarray  # bool
    true_enu: np.ndarray  # (n, 3) m, at t_measured
    # urban scenarios: per fix its environment (urban_gps.OPEN, CANYON, MULTIPATH, NLOS)
    environment: np.ndarray | None = None


def simulate_gps(sc: Scenario, truth: Truth, rng: np.random.Generator) -> GpsData:
    spec = sc.gps
    tm = sample_times(rng, spec.rate, sc.duration)
    n = len(tm)
    # Draw every random number for every nominal sample first, so the noise of a fix does not
    # depend on which other fixes were dropped (a correlated error runs over every nominal
    # sample; dropouts and outages remove samples from it).
    std = np.array([spec.horizontal_std, spec.horizontal_std, spec.vertical_std])
    w = rng.standard_normal((n, 3))
    noise = w * std if spec.correlation_s == 0.0 else gauss_markov(tm, w, std,
                                                                    spec.correlation_s)
    drop = rng.uniform(size=n) < spec.dropout_prob
    out = rng.uniform(size=n) < spec.outlier_prob
    mag = rng.uniform(*spec.outlier_range, size=n)
    ang = rng.uniform(-np.pi, np.pi, size=n)
    x, y, _, _, _ = truth.at(tm)
    true_enu = np.stack([x, y, np.zeros(n)], axis=1)
    enu = true_enu + noise
    enu[:, 0] += np.where(out, mag * np.cos(ang), 0.0)
    enu[:, 1] += np.where(out, mag * np.sin(ang), 0.0)
    keep = ~drop & (tm + spec.delay <= sc.duration)
    for a, b in spec.outages:
        keep &= ~((tm >= a) & (tm < b))
    env = None
    if spec.urban is not None:
        # drawn after everything above, so the other scenarios' streams are unchanged
        u = urban_errors(tm, sc.duration, spec.urban, rng)
        enu = true_enu.copy()
        enu[:, :2] += u.error
        enu[:, 2] += noise[:, 2]
        keep &= ~u.bridge
        out = out | (u.label >= MULTIPATH)
        env = u.label[keep]
    enu, true_enu, tm, out = enu[keep], true_enu[keep], tm[keep], out[keep]
    lat, lon, alt = enu_to_geodetic(enu[:, 0], enu[:, 1], enu[:, 2], *sc.datum)
    return GpsData(t=tm + spec.delay, t_measured=tm, enu=enu, lat=np.asarray(lat),
                   lon=np.asarray(lon), alt=np.asarray(alt), outlier=out, true_enu=true_enu,
                   environment=env)
