"""The simulated sensors: wheel encoders, IMU, landmark range-bearing, and the ground truth.

Each sensor samples on its own clock (a random phase within one period) and draws from its own
random stream (``simulator._rng``). Times are seconds since the start of the run.

* Wheel encoders: per sample interval [t_k-1, t_k] the count is round((true wheel rotation +
  slip noise) / tick). The measured wheel speed count*tick/dt (rad/s, stamped at the interval's
  end) has error std ``EncoderSpec.speed_std`` about the TRUE interval-mean wheel speed (slip noise
  and quantisation together). Odometry twist is computed from those speeds with the NOMINAL
  radius and track, so it carries both this noise and the calibration error.
* IMU: gyro z = true yaw rate + bias + white noise, the bias a random walk; orientation = true
  yaw + constant offset + noise (roll and pitch: small noise about the true zero);
  linear_acceleration = (dv/dt, v w, g) + white noise (specific force on flat ground).
* Magnetometer: the earth's field rotated into the level body at the true yaw, plus the
  hard-iron offset and white noise (``simulate_magnetometer``).
* Landmarks: range and bearing (body frame, CCW from x) from the body origin to every known
  landmark inside [min_range, max_range] and the field of view, each detected with probability
  ``detect_prob``, with white Gaussian noise.

GPS is ``gps.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from ddfuse.estimation.frames import GRAVITY
from ddfuse.estimation.geodesy import enu_to_geodetic
from ddfuse.evaluation.simulate.motion import Truth, se2_step, wrap
from ddfuse.evaluation.simulate.scenarios import Scenario

G = GRAVITY  # m/s^2 (the accelerometer's z reading at rest)


@dataclass
class EncoderData:
    """Encoder samples, stamped at the end of each counting interval. Shapes (n,)."""

    t: np.ndarray  # s
    counts_left: np.ndarray  # int64, cumulative encoder counts
    counts_right: np.ndarray
    left: np.ndarray  # rad/s, measured wheel speed over the interval
    right: np.ndarray
    true_left: np.ndarray  # rad/s, true mean wheel speed over the interval
    true_right: np.ndarray
    v: np.ndarray  # m/s, odometry twist from the measured speeds, NOMINAL geometry
    yaw_rate: np.ndarray  # rad/s
    tick: float  # rad per count
    x: np.ndarray  # m, odometry pose: dead reckoning of (v, yaw_rate) in the odom frame
    y: np.ndarray
    yaw: np.ndarray  # rad, wrapped


@dataclass
class ImuData:
    t: np.ndarray  # s
    yaw_rate: np.ndarray  # rad/s, gyro z
    gyro_xy: np.ndarray  # (n, 2) rad/s, gyro x, y (true value zero)
    bias: np.ndarray  # rad/s, true gyro z bias at each sample
    yaw: np.ndarray  # rad, measured orientation yaw, wrapped
    roll: np.ndarray  # rad, measured
    pitch: np.ndarray  # rad, measured
    accel: np.ndarray  # (n, 3) m/s^2, specific force in the body frame
    true_yaw_rate: np.ndarray
    true_yaw: np.ndarray  # rad, wrapped
    true_accel: np.ndarray  # (n, 3)


@dataclass
class MagnetometerData:
    t: np.ndarray  # s
    field: np.ndarray  # (n, 3) T, measured, sensor frame (hard iron and noise included)
    true_yaw: np.ndarray  # rad, wrapped


@dataclass
class LandmarkData:
    t: np.ndarray  # s; several sightings can share a stamp (one scan)
    index: np.ndarray  # int, into ``ids``
    range: np.ndarray  # m
    bearing: np.ndarray  # rad, wrapped
    true_range: np.ndarray
    true_bearing: np.ndarray
    ids: list[str]  # landmark id strings
    positions: np.ndarray  # (m, 2) m, local frame
    scan_t: np.ndarray  # s, every scan, including those that saw nothing


@dataclass
class GroundTruthData:
    t: np.ndarray  # s
    x: np.ndarray  # m
    y: np.ndarray  # m
    yaw: np.ndarray  # rad, wrapped
    v: np.ndarray  # m/s
    w: np.ndarray  # rad/s
    fix_t: np.ndarray  # s
    fix_lat: np.ndarray  # deg
    fix_lon: np.ndarray  # deg
    fix_alt: np.ndarray  # m


def gauss_markov(t: np.ndarray, w: np.ndarray, std: np.ndarray, tau: float) -> np.ndarray:
    """First-order Gauss-Markov errors at times ``t`` (N,) s from unit white draws ``w`` (N, D):
    e_0 = std w_0 (the stationary distribution), e_k = a_k e_k-1 + sqrt(1 - a_k^2) std w_k with
    a_k = exp(-(t_k - t_k-1) / tau), the exact discretisation over any spacing, so every e_k
    has std ``std`` (D,) and corr(e_j, e_k) = exp(-|t_k - t_j| / tau)."""
    a = np.exp(-np.diff(t) / tau)
    b = np.sqrt(1.0 - a * a)
    e = np.empty_like(w)
    if len(t):
        e[0] = w[0]
    for k in range(1, len(t)):
        e[k] = a[k - 1] * e[k - 1] + b[k - 1] * w[k]
    return e * std


def sample_times(rng: np.random.Generator, rate: float, duration: float,
                 phase: float | None = None) -> np.ndarray:
    """Sample instants (s) on the sensor's own clock: a random phase within one period, or the
    given ``phase`` (s), e.g. 0 for a sensor sampled in step with the commands."""
    period = 1.0 / rate
    drawn = rng.uniform(0.0, period)  # drawn either way: the stream's later draws stay the same
    phase = drawn if phase is None else phase
    return phase + np.arange(int(math.floor((duration - phase) / period)) + 1) * period


def simulate_encoders(sc: Scenario, truth: Truth, rng: np.random.Generator) -> EncoderData:
    spec = sc.encoders
    edges = sample_times(rng, spec.rate, sc.duration, spec.phase)  # t[0] opens the first interval
    t = edges[1:]
    dt = np.diff(edges)
    tick = 2.0 * math.pi / spec.counts_per_rev
    # Slip noise per interval so that slip plus quantisation (uniform, variance tick^2/12) give
    # the specified speed error std.
    slip_var = (spec.speed_std * dt) ** 2 - tick**2 / 12.0
    if np.any(slip_var <= 0):
        raise ValueError("encoder speed_std below the quantisation floor; raise counts_per_rev")
    al, ar = truth.wheel_angles(edges)
    dl, dr = np.diff(al), np.diff(ar)
    nl = np.rint((dl + rng.standard_normal(len(t)) * np.sqrt(slip_var)) / tick).astype(np.int64)
    nr = np.rint((dr + rng.standard_normal(len(t)) * np.sqrt(slip_var)) / tick).astype(np.int64)
    left, right = nl * tick / dt, nr * tick / dt
    r, L = sc.nominal_geometry.wheel_radius, sc.nominal_geometry.track_width
    v = 0.5 * r * (left + right)
    w = r * (right - left) / L
    # Odometry pose: what a wheel-odometry node integrates (exact constant twist per interval).
    yaw = np.concatenate([[0.0], np.cumsum(w * dt)])
    ddx, ddy, _ = se2_step(0.0, 0.0, yaw[:-1], v, w, dt)
    return EncoderData(t=t, counts_left=np.cumsum(nl), counts_right=np.cumsum(nr), left=left,
                       right=right, true_left=dl / dt, true_right=dr / dt, v=v, yaw_rate=w,
                       tick=tick, x=np.cumsum(ddx), y=np.cumsum(ddy), yaw=wrap(yaw[1:]))


def simulate_imu(sc: Scenario, truth: Truth, rng: np.random.Generator) -> ImuData:
    spec = sc.imu
    t = sample_times(rng, spec.rate, sc.duration)
    n = len(t)
    _, _, yaw, v, w = truth.at(t)
    steps = np.diff(np.concatenate([[0.0], t]))
    bias = spec.gyro_bias0 + np.cumsum(spec.gyro_bias_walk * np.sqrt(steps)
                                       * rng.standard_normal(n))
    gz = w + bias + spec.gyro_std * rng.standard_normal(n)
    gxy = spec.gyro_std * rng.standard_normal((n, 2))
    yaw_m = wrap(yaw + spec.heading_offset + spec.heading_std * rng.standard_normal(n))
    roll = spec.tilt_std * rng.standard_normal(n)
    pitch = spec.tilt_std * rng.standard_normal(n)
    true_acc = np.stack([truth.accel(t), v * w, np.full(n, G)], axis=1)
    acc = true_acc + spec.accel_std * rng.standard_normal((n, 3))
    return ImuData(t=t, yaw_rate=gz, gyro_xy=gxy, bias=bias, yaw=yaw_m, roll=roll, pitch=pitch,
                   accel=acc, true_yaw_rate=w, true_yaw=wrap(yaw), true_accel=true_acc)


def simulate_magnetometer(sc: Scenario, truth: Truth, rng: np.random.Generator
                          ) -> MagnetometerData:
    """The earth's field in the level body at the true yaw, plus hard iron and white noise."""
    from ddfuse.estimation.magnetometer import body_field

    spec = sc.magnetometer
    t = sample_times(rng, spec.rate, sc.duration)
    _, _, yaw, _, _ = truth.at(t)
    b = np.stack(body_field(yaw, spec.field), axis=1) + np.asarray(spec.hard_iron)
    b = b + spec.noise_std * rng.standard_normal(b.shape)
    return MagnetometerData(t=t, field=b, true_yaw=wrap(yaw))


def _landmark_map(sc: Scenario, truth: Truth, rng: np.random.Generator
                  ) -> tuple[list[str], np.ndarray]:
    """Landmarks uniformly in the path's bounding box grown by the margin (m), or in the square
    of half-width ``area`` (m) about the start position where the spec sets one."""
    spec = sc.landmarks
    if spec.area is not None:
        start = np.array([truth.x[0], truth.y[0]])
        pos = start + spec.area * rng.uniform(-1.0, 1.0, size=(spec.count, 2))
        return [str(i + 1) for i in range(spec.count)], pos
    lo = np.array([truth.x.min(), truth.y.min()]) - spec.margin
    hi = np.array([truth.x.max(), truth.y.max()]) + spec.margin
    pos = lo + (hi - lo) * rng.uniform(size=(spec.count, 2))
    return [str(i + 1) for i in range(spec.count)], pos


def simulate_landmarks(sc: Scenario, truth: Truth, rng: np.random.Generator,
                   map_rng: np.random.Generator, map_truth: Truth | None = None
                   ) -> LandmarkData:
    """Sightings along ``truth`` of the landmarks drawn around ``map_truth``'s path (default
    ``truth``'s)."""
    spec = sc.landmarks
    ids, pos = _landmark_map(sc, truth if map_truth is None else map_truth, map_rng)
    t = sample_times(rng, spec.rate, sc.duration, spec.phase)
    x, y, yaw, _, _ = truth.at(t)
    dx = pos[None, :, 0] - x[:, None]
    dy = pos[None, :, 1] - y[:, None]
    rng_true = np.hypot(dx, dy)
    brg_true = wrap(np.arctan2(dy, dx) - yaw[:, None])
    shape = rng_true.shape
    # Noise and detection draws for every (scan, landmark) pair, visible or not, so that the
    # draws of one pair do not depend on the visibility of the others.
    n_r = spec.range_std * rng.standard_normal(shape)
    n_b = spec.bearing_std * rng.standard_normal(shape)
    detect = rng.uniform(size=shape) < spec.detect_prob
    seen = ((rng_true >= spec.min_range) & (rng_true <= spec.max_range)
            & (np.abs(brg_true) <= 0.5 * spec.fov) & detect)
    scan, lm = np.nonzero(seen)  # row-major: by scan time, then landmark index
    return LandmarkData(t=t[scan], index=lm, range=rng_true[scan, lm] + n_r[scan, lm],
                        bearing=wrap(brg_true[scan, lm] + n_b[scan, lm]),
                        true_range=rng_true[scan, lm], true_bearing=brg_true[scan, lm],
                        ids=ids, positions=pos, scan_t=t)


def simulate_ground_truth(sc: Scenario, truth: Truth) -> GroundTruthData:
    t = np.arange(int(math.floor(sc.duration * sc.truth_rate + 1e-9)) + 1) / sc.truth_rate
    x, y, yaw, v, w = truth.at(t)
    if sc.datum is not None:
        ft = np.arange(int(math.floor(sc.duration * sc.truth_fix_rate + 1e-9)) + 1) \
            / sc.truth_fix_rate
        fx, fy, _, _, _ = truth.at(ft)
        lat, lon, alt = enu_to_geodetic(fx, fy, np.zeros_like(fx), *sc.datum)
        lat, lon, alt = np.asarray(lat), np.asarray(lon), np.asarray(alt)
    else:
        ft = lat = lon = alt = np.zeros(0)
    return GroundTruthData(t=t, x=x, y=y, yaw=wrap(yaw), v=v, w=w, fix_t=ft, fix_lat=lat,
                           fix_lon=lon, fix_alt=alt)
