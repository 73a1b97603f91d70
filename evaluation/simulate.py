"""Differential-drive robot simulator with ground truth, writing ROS1 / ROS2 / MCAP bags.

``simulate(scenario, seed)`` drives a differential-drive robot along a named scenario's path
and samples its sensors; ``write_bag(result, path, fmt)`` writes the bag plus, next to it, the
ddfuse config (and the landmark map) that describe it. ``main(argv)`` is the
``ddfuse simulate`` command.

Model (everything SI; time in seconds since the start of the run, ``SimResult.t0`` adds the
absolute epoch that goes into the header stamps):

* Truth. Commanded body speed v(t) (m/s) and yaw rate w(t) (rad/s) are turned into wheel angular
  speeds through the TRUE wheel radius r and track width L (w_l = (v - w L/2)/r,
  w_r = (v + w L/2)/r), held constant over substeps of ``Scenario.substep`` s, and the pose is
  integrated exactly over each substep (closed-form SE(2) constant twist), so the truth is exact
  at any instant, not only on the grid (``Truth.at``). The local frame is ENU about the datum
  (x east, y north, yaw from east, CCW); the robot moves on the tangent plane (up = 0).
* Each sensor has its own random stream, derived from (seed, sensor name), so changing one
  sensor's settings does not change another's noise.
* Wheel encoders: per sample interval [t_k-1, t_k] the count is round((true wheel rotation +
  slip noise) / tick). The measured wheel speed count*tick/dt (rad/s, stamped at the interval's
  end) has error std ``EncoderSpec.speed_std`` about the TRUE interval-mean wheel speed (slip noise
  and quantisation together). Odometry twist is computed from those speeds with the NOMINAL
  radius and track, so it carries both this noise and the calibration error.
* IMU: gyro z = true yaw rate + bias + white noise, the bias a random walk; orientation = true
  yaw + constant offset + noise (roll and pitch: small noise about the true zero);
  linear_acceleration = (dv/dt, v w, g) + white noise (specific force on flat ground).
* GPS: truth at the sample time + noise (horizontal, vertical std), optional outliers (tens of
  metres), random dropouts, outage windows, and a constant latency: the fix measured at t is
  stamped t + delay. The noise is white (``GpsSpec.correlation_s`` 0) or, per axis, a first-order
  Gauss-Markov process of that correlation time with the same stationary std (a receiver's
  multipath and atmospheric error wanders slowly); outliers are added on top.
* Landmarks: range and bearing (body frame, CCW from x) from the body origin to every known
  landmark inside [min_range, max_range] and the field of view, each detected with probability
  ``detect_prob``, with white Gaussian noise.

Covariances written into the messages are the true noise variances listed above (axes a planar
robot does not have get 1e6, as in the MRCLAM bag); the config written next to the bag repeats
them as standard deviations under ``noise:``.
"""

from __future__ import annotations

import heapq
import math
import os
import shutil
import sys
import tempfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import yaml
from ddfuse.estimation.frames import GRAVITY
from ddfuse.estimation.geodesy import enu_to_geodetic

G = GRAVITY  # m/s^2 (the accelerometer's z reading at rest)
LANDMARK_MSGTYPE = "ddfuse_msgs/msg/LandmarkObservation"
LANDMARK_MSGDEF = """std_msgs/Header header
string landmark_id
float64 range
float64 bearing
float64 range_variance
float64 bearing_variance
bool has_bearing
"""
UNUSED_VAR = 1e6  # variance written for axes a planar robot does not measure
FORMATS = ("ros1", "ros2", "mcap")
# the file extension of each format's bag (ros1) or of the storage file in its directory (ROS 2)
SUFFIXES = {"ros1": ".bag", "ros2": ".db3", "mcap": ".mcap"}


# --------------------------------------------------------------------------------------------
# Scenario description
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Geometry:
    """Wheel radius and track width (distance between the wheels' contact points), m."""

    wheel_radius: float
    track_width: float


@dataclass(frozen=True)
class TrajectorySpec:
    """The commanded motion. ``kind``: 'random', 'figure-eight', 'lawnmower', 'loop-stops'.

    Every kind starts from rest at ``start`` (x m, y m, yaw rad, local frame) and ends at rest;
    ``ramp`` is the time (s) of the smooth (raised-cosine) speed ramps."""

    kind: str
    speed: float = 1.0  # m/s, cruise speed
    ramp: float = 3.0  # s
    start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # random: smooth Gaussian processes, white noise smoothed by a Gaussian kernel of std
    # corr_time (s): correlation exp(-tau^2 / (4 corr_time^2)), 1/e at 2 corr_time
    speed_rel_std: float = 0.25  # std of v / speed
    yaw_rate_std: float = 0.25  # rad/s
    corr_time: float = 4.0  # s
    # figure-eight: lemniscate of Gerono x = A sin u, y = A/2 sin 2u (then rotated by start yaw
    # minus pi/4, its tangent at the crossing)
    half_width: float = 15.0  # m, A
    # lawnmower: straight legs joined by half-circle U-turns of radius spacing/2, alternating
    # (the curvature's 2 m smoothing widens each turn: the legs end up 4.07 m apart at 4.0)
    leg_length: float = 40.0  # m
    spacing: float = 4.0  # m, distance between legs
    # loop-stops: rounded rectangle, stops of stop_time at two metres before each corner
    loop_size: tuple[float, float] = (30.0, 20.0)  # m, along the start heading, and across it
    corner_radius: float = 3.0  # m
    stop_time: float = 6.0  # s
    smooth_length: float = 2.0  # m, curvature smoothing window (keeps wheel accelerations finite)


@dataclass(frozen=True)
class EncoderSpec:
    """Wheel encoders, published as JointState (wheel speeds) and/or Odometry (twist)."""

    rate: float = 10.0  # Hz
    speed_std: float = 0.15  # rad/s, error std of one wheel-speed sample (slip + quantisation)
    counts_per_rev: int = 2000  # encoder counts per wheel revolution
    odometry_topic: str | None = "/odom"
    joint_topic: str | None = None
    joints: tuple[str, str] = ("left_wheel_joint", "right_wheel_joint")


@dataclass(frozen=True)
class ImuSpec:
    rate: float = 30.0  # Hz
    gyro_std: float = 0.01  # rad/s, white noise per sample
    gyro_bias0: float = 0.01  # rad/s, bias at t = 0
    gyro_bias_walk: float = 2e-4  # rad/s/sqrt(s), bias random-walk density
    heading_std: float = 0.02  # rad
    heading_offset: float = 0.35  # rad, sensor yaw = ENU yaw + offset
    tilt_std: float = 0.005  # rad, roll/pitch noise of the orientation
    accel_std: float = 0.05  # m/s^2
    topic: str = "/imu/data"


@dataclass(frozen=True)
class GpsSpec:
    rate: float = 2.5  # Hz
    horizontal_std: float = 1.0  # m, per axis (east, north)
    vertical_std: float = 2.0  # m
    delay: float = 0.2  # s, a fix measured at t is stamped t + delay
    dropout_prob: float = 0.01  # probability that a fix is missing
    outlier_prob: float = 0.0  # probability that a fix is an outlier
    outlier_range: tuple[float, float] = (20.0, 60.0)  # m, horizontal outlier offset magnitude
    outages: tuple[tuple[float, float], ...] = ()  # (start, end) s: no fixes measured inside
    topic: str = "/fix"
    # s, correlation time tau of the errors: 0 white; > 0 per axis e_k = a e_k-1 +
    # sqrt(1 - a^2) std w_k with a = exp(-(t_k - t_k-1) / tau), e_0 ~ N(0, std^2) (stationary)
    correlation_s: float = 0.0

    def __post_init__(self):
        if not (math.isfinite(self.correlation_s) and self.correlation_s >= 0.0):
            raise ValueError("GpsSpec.correlation_s must be a finite number of seconds >= 0 "
                             f"(0: white errors), got {self.correlation_s!r}")


@dataclass(frozen=True)
class LandmarkSpec:
    rate: float = 10.0  # Hz, scans
    count: int = 20
    range_std: float = 0.1  # m
    bearing_std: float = 0.05  # rad
    min_range: float = 0.5  # m
    max_range: float = 15.0  # m
    fov: float = math.pi  # rad, full width, centred on body x
    detect_prob: float = 0.9
    margin: float = 5.0  # m, landmarks are drawn in the path's bounding box grown by this
    topic: str = "/landmarks"


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    duration: float  # s
    trajectory: TrajectorySpec
    true_geometry: Geometry
    nominal_geometry: Geometry  # what the config's robot: states
    encoders: EncoderSpec
    imu: ImuSpec | None = None
    gps: GpsSpec | None = None
    landmarks: LandmarkSpec | None = None
    datum: tuple[float, float, float] | None = None  # lat deg, lon deg, alt m (WGS-84)
    truth_rate: float = 20.0  # Hz, /ground_truth
    truth_fix_rate: float = 5.0  # Hz, /ground_truth/fix (only with a datum)
    substep: float = 0.01  # s, truth integration step
    t0_ns: int = 1_700_000_000 * 10**9  # header stamp of t = 0
    truth_topic: str = "/ground_truth"
    truth_fix_topic: str = "/ground_truth/fix"
    # 1-sigma uncertainty of the nominal geometry that the config states (robot.*_std): how
    # well the scenario's robot is calibrated. The true geometry lies within it.
    geometry_std: Geometry | None = None
    # s, the duration the scenario's drive is drawn for: a random drive's commands and the
    # landmark map (drawn in the path's bounding box) are those of a run of this length, cut at
    # ``duration`` (see simulate). None: ``duration``. get_scenario and simulate set it to the
    # scenario's own duration when they replace that, so --duration cuts the documented drive.
    drive_duration: float | None = None


SMOOTHER_LAG = 10.0  # s, the smoother lag of the configs written next to simulated bags

# A field site near Zurich, Switzerland: lat, lon (deg), ellipsoidal altitude (m).
OUTDOOR_DATUM = (47.397742, 8.545594, 488.0)

_HUSKY_TRUE = Geometry(wheel_radius=0.1635, track_width=0.5826)  # worn tyres, skid-steer track
_HUSKY_NOMINAL = Geometry(wheel_radius=0.165, track_width=0.555)  # Husky datasheet
# tyre wear and skid-steer slip: the datasheet radius known to 2 mm, the effective track to 3 cm
_HUSKY_STD = Geometry(wheel_radius=0.002, track_width=0.03)


def _husky(name: str, description: str, trajectory: TrajectorySpec, duration: float = 400.0,
           gps: GpsSpec | None = None, truth_rate: float = 20.0) -> Scenario:
    return Scenario(
        name=name, description=description, duration=duration, trajectory=trajectory,
        true_geometry=_HUSKY_TRUE, nominal_geometry=_HUSKY_NOMINAL,
        encoders=EncoderSpec(rate=10.0, speed_std=0.15, counts_per_rev=2000),
        imu=ImuSpec(), gps=gps or GpsSpec(), datum=OUTDOOR_DATUM, truth_rate=truth_rate,
        geometry_std=_HUSKY_STD,
    )


_LAWNMOWER = TrajectorySpec("lawnmower", speed=1.0, start=(0.0, 0.0, math.pi / 2))

SCENARIOS: dict[str, Scenario] = {
    "seed002": Scenario(
        name="seed002",
        description="Seed 002: random smooth path, wheel encoders (JointState) and a range "
        "finder to 20 landmarks, 10 Hz (dt 0.1 s), 2 min, no GPS; the map frame is the local "
        "frame.",
        duration=120.0,
        trajectory=TrajectorySpec("random", speed=0.5, yaw_rate_std=0.3, corr_time=4.0),
        true_geometry=Geometry(wheel_radius=0.1015, track_width=0.392),
        nominal_geometry=Geometry(wheel_radius=0.10, track_width=0.40),
        encoders=EncoderSpec(rate=10.0, speed_std=0.1, counts_per_rev=1024, odometry_topic=None,
                             joint_topic="/joint_states"),
        landmarks=LandmarkSpec(),
        truth_rate=10.0,
        geometry_std=Geometry(wheel_radius=0.002, track_width=0.01),
    ),
    "husky": _husky(
        "husky", "Husky-like outdoor robot mowing a field (lawnmower legs of 40 m): 10 Hz "
        "wheel odometry, 30 Hz IMU (heading offset, gyro bias), 2.5 Hz GPS, 400 s.",
        _LAWNMOWER),
    # The correlation time is measured on rl_husky_gps.bag (../shared/data): GPS displacement
    # along the odometry's chord minus the odometry distance (heading from the batch track),
    # over lags of 1-120 s, fits 2 sigma^2 (1 - exp(-lag / tau)) with tau 26.7 s, sigma 1.7 m;
    # errors simulated with tau 30 s on the same fix pairs fit a median 27.8 s (90 % of fits
    # 12-77 s). The fixes' residuals to an estimated track decorrelate faster (3.6-5.2 s, the
    # report's figure): a track takes up the slow wander. docs/results/smoother_monte_carlo.md
    "husky-multipath": _husky(
        "husky-multipath", "husky with time-correlated GPS errors (multipath, atmosphere): "
        "per axis a Gauss-Markov process of correlation time 30 s (measured on "
        "rl_husky_gps.bag) with husky's std (1 m horizontal, 2 m vertical); the config states "
        "husky's white GPS noise.",
        _LAWNMOWER, gps=GpsSpec(correlation_s=30.0)),
    "gps-outage": _husky(
        "gps-outage", "husky with a 60 s GPS outage (150-210 s) and 2 % outlier fixes.",
        _LAWNMOWER, gps=GpsSpec(outlier_prob=0.02, outages=((150.0, 210.0),))),
    "long": _husky(
        "long", "husky sensors on a 30 x 20 m loop with stops at every corner, 2 h (memory and "
        "speed tests); 0.5 % outlier fixes.",
        TrajectorySpec("loop-stops", speed=1.0), duration=7200.0,
        gps=GpsSpec(outlier_prob=0.005), truth_rate=10.0),
    "figure-eight": _husky(
        "figure-eight", "husky sensors on a 30 x 15 m figure-eight, 400 s.",
        TrajectorySpec("figure-eight", speed=1.0, start=(0.0, 0.0, math.pi / 4))),
    "loop-stops": _husky(
        "loop-stops", "husky sensors on a 30 x 20 m loop with stops at every corner, 400 s.",
        TrajectorySpec("loop-stops", speed=1.0)),
    "random": _husky(
        "random", "husky sensors on a random smooth path, 400 s.",
        TrajectorySpec("random", speed=1.0, yaw_rate_std=0.2, corr_time=5.0)),
}


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------


@dataclass
class Truth:
    """The exact motion: substep i covers [t[i], t[i] + dt) with constant wheel speeds.

    Arrays have shape (n,) except the pose arrays x, y, yaw, which have n + 1 entries (the pose
    at every substep boundary, the last at the end of the run). yaw is unwrapped (rad)."""

    dt: float  # s
    t: np.ndarray  # s, substep starts
    wheel_left: np.ndarray  # rad/s, true wheel angular speeds
    wheel_right: np.ndarray  # rad/s
    v: np.ndarray  # m/s, body forward speed
    w: np.ndarray  # rad/s, yaw rate
    x: np.ndarray  # m, east
    y: np.ndarray  # m, north
    yaw: np.ndarray  # rad, unwrapped
    angle_left: np.ndarray  # rad, wheel rotation at substep boundaries (n + 1)
    angle_right: np.ndarray  # rad

    @property
    def duration(self) -> float:
        return len(self.t) * self.dt

    def _index(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        i = np.clip(np.floor(t / self.dt).astype(np.int64), 0, len(self.t) - 1)
        return i, t - i * self.dt

    def at(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Exact (x m, y m, yaw rad unwrapped, v m/s, w rad/s) at times ``t`` (s, any shape)."""
        i, tau = self._index(t)
        x, y, yaw = se2_step(self.x[i], self.y[i], self.yaw[i], self.v[i], self.w[i], tau)
        return x, y, yaw, self.v[i], self.w[i]

    def wheel_angles(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Wheel rotation (rad, left and right) since t = 0 at times ``t`` (s)."""
        i, tau = self._index(t)
        return (self.angle_left[i] + self.wheel_left[i] * tau,
                self.angle_right[i] + self.wheel_right[i] * tau)

    def accel(self, t) -> np.ndarray:
        """Forward acceleration dv/dt (m/s^2) at ``t``: the central difference of the substep
        speeds, interpolated linearly between substep midpoints (v itself is the midpoint sample
        of a smooth command, so this is its derivative to O(dt^2))."""
        a = np.gradient(self.v, self.dt)
        return np.interp(t, self.t + 0.5 * self.dt, a)


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
class GpsData:
    t: np.ndarray  # s, header stamp = t_measured + delay
    t_measured: np.ndarray  # s, when the position was true
    enu: np.ndarray  # (n, 3) m, measured position in the local ENU frame
    lat: np.ndarray  # deg
    lon: np.ndarray  # deg
    alt: np.ndarray  # m
    outlier: np.ndarray  # bool
    true_enu: np.ndarray  # (n, 3) m, at t_measured


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


@dataclass
class SimResult:
    """Everything one run produced. Times are seconds since the start; add ``t0`` for the header
    stamps' absolute seconds."""

    scenario: Scenario
    seed: int
    truth: Truth
    ground_truth: GroundTruthData
    encoders: EncoderData
    imu: ImuData | None = None
    gps: GpsData | None = None
    landmarks: LandmarkData | None = None
    extras: dict = field(default_factory=dict)

    @property
    def t0(self) -> float:
        return self.scenario.t0_ns * 1e-9

    @property
    def duration(self) -> float:
        return self.scenario.duration

    def noise(self) -> dict[str, dict[str, float]]:
        """The true noise standard deviations by config sensor kind (SI), as the config states
        them. Odometry noise is about the NOMINAL-geometry twist of the true wheel speeds."""
        sc = self.scenario
        r, L = sc.nominal_geometry.wheel_radius, sc.nominal_geometry.track_width
        s = sc.encoders.speed_std
        out: dict[str, dict[str, float]] = {
            # v = r (wl + wr)/2, w = r (wr - wl)/L with independent wheel errors of std s
            "odometry": {"v": r * s / math.sqrt(2.0), "yaw_rate": math.sqrt(2.0) * r * s / L},
            "wheels": {"speed": s},
        }
        if sc.imu:
            # and the random walks of the gyro bias (rad/s/sqrt(s)) and of the heading offset
            # (rad/sqrt(s): none, it is constant)
            out["imu"] = {"yaw": sc.imu.heading_std, "yaw_rate": sc.imu.gyro_std,
                          "accel": sc.imu.accel_std, "gyro_bias_walk": sc.imu.gyro_bias_walk,
                          "heading_offset_walk": 0.0}
        if sc.gps:
            out["gps"] = {"horizontal": sc.gps.horizontal_std, "vertical": sc.gps.vertical_std}
        if sc.landmarks:
            out["landmarks"] = {"range": sc.landmarks.range_std,
                                "bearing": sc.landmarks.bearing_std}
        return out


# --------------------------------------------------------------------------------------------
# Maths helpers (vectorised)
# --------------------------------------------------------------------------------------------


def wrap(a):
    """Wrap angles (rad) to [-pi, pi), the convention of ddfuse.estimation.estimator.wrap_angle."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def se2_step(x, y, yaw, v, w, dt):
    """Exact pose after constant (v m/s, w rad/s) for ``dt`` s from (x, y, yaw); arrays
    broadcast. Uses sin(a)/a = sinc and (1 - cos a)/a = sin(a/2) sinc(a/2), exact at a = 0."""
    a = w * dt
    d = v * dt
    dxb = d * np.sinc(a / np.pi)
    dyb = d * np.sin(0.5 * a) * np.sinc(a / (2.0 * np.pi))
    c, s = np.cos(yaw), np.sin(yaw)
    return x + c * dxb - s * dyb, y + s * dxb + c * dyb, yaw + a


def _rng(seed: int, stream: str) -> np.random.Generator:
    """An independent generator per (seed, stream name); crc32 is stable across runs."""
    return np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32(stream.encode())]))


def _smooth_noise(rng: np.random.Generator, t: np.ndarray, corr_time: float, count: int = 1,
                  span: float | None = None) -> list[np.ndarray]:
    """``count`` independent smooth zero-mean, unit-variance Gaussian processes sampled at ``t``
    (s, from 0).

    White noise on a grid of corr_time/8 s is filtered by a Gaussian kernel of std corr_time s
    (normalised to unit L2 norm, so the output variance is one) and interpolated linearly.

    ``span`` (s) makes the processes a function of the seed alone up to ``span``: every process
    first draws the white noise of a grid that reaches ``span``, whatever ``t`` covers, and only
    then does any process draw the grid's extension to a later ``t[-1]``. So the values at any
    time up to ``span`` are the same for every ``t``. With ``span`` None (or ``t[-1]``), the
    draws are those of a grid that just covers ``t``, process after process."""
    h = corr_time / 8.0
    k = np.arange(-32, 33) * h
    kernel = np.exp(-0.5 * (k / corr_time) ** 2)
    kernel /= np.sqrt(np.sum(kernel**2))
    t_end = t[-1] if len(t) else 0.0
    n = int(math.ceil(t_end / h)) + 2  # grid points of the output, the last beyond t_end
    n0 = n if span is None else int(math.ceil(span / h)) + 2
    white = [rng.standard_normal(n0 + len(kernel) - 1) for _ in range(count)]
    if n > n0:
        # Appended after every process's first block, so that the first blocks (and with them
        # the processes up to span) are what a run of length span draws.
        white = [np.concatenate([w, rng.standard_normal(n - n0)]) for w in white]
    out = []
    for w in white:
        g = np.convolve(w, kernel, mode="valid")  # g[i] depends on w[i : i + len(kernel)] only
        out.append(np.interp(t, np.arange(len(g)) * h, g))
    return out


def _ramp(x: np.ndarray) -> np.ndarray:
    """Raised-cosine step: 0 for x <= 0, 1 for x >= 1, C1 in between."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(x, 0.0, 1.0))


def _envelope(t: np.ndarray, duration: float, ramp: float) -> np.ndarray:
    """Start from rest and end at rest: ramps of ``ramp`` s at both ends."""
    return _ramp(t / ramp) * _ramp((duration - t) / ramp)


def _periodic_curvature(lengths: list[float], kappas: list[float], smooth: float, ds: float
                        ) -> tuple[np.ndarray, np.ndarray, float]:
    """One period of a piecewise-constant curvature (1/m) over arc length, smoothed by a
    normalised Hann window of ``smooth`` m (circularly, so the smoothing preserves the total
    heading change of every segment). Returns (s grid m, kappa 1/m, period m)."""
    period = float(sum(lengths))
    n = int(round(period / ds))
    h = period / n
    # Cell averages of kappa from the exact heading function H(s) = integral of kappa (piecewise
    # linear), placed at cell centres: the cells then sum to exactly the segments' heading
    # changes, which sampling kappa at grid points would miss by up to h kappa per segment.
    seg_edges = np.cumsum([0.0] + list(lengths))
    heading = np.concatenate([[0.0], np.cumsum(np.multiply(lengths, kappas))])
    kappa = np.diff(np.interp(np.arange(n + 1) * h, seg_edges, heading)) / h
    s = (np.arange(n) + 0.5) * h
    m = max(3, int(round(smooth / h)) | 1)
    win = np.hanning(m + 2)[1:-1]
    win /= win.sum()
    half = m // 2
    padded = np.concatenate([kappa[-half:], kappa, kappa[:half]])
    return s, np.convolve(padded, win, mode="valid"), period


def _stop_profile(t: np.ndarray, sections: list[float], speed: float, ramp: float,
                  stop_time: float, dt: float) -> np.ndarray:
    """Speed (m/s) at substep midpoints ``t`` for repeated stop-to-stop sections of the given
    lengths (m): raised-cosine ramps of ``ramp`` s, cruise at ``speed``, then ``stop_time`` s at
    rest. Each section is scaled so that its substeps cover exactly its length."""
    pieces = []
    for d in sections:
        cruise = (d - speed * ramp) / speed
        if cruise < 0:
            raise ValueError(f"section of {d} m too short for a {ramp} s ramp at {speed} m/s")
        move = 2.0 * ramp + cruise
        n_move = int(math.ceil(move / dt))
        tm = (np.arange(n_move) + 0.5) * dt
        v = speed * _ramp(tm / ramp) * _ramp((move - tm) / ramp)
        v *= d / (v.sum() * dt)
        pieces += [v, np.zeros(int(round(stop_time / dt)))]
    lap = np.concatenate(pieces)
    reps = int(math.ceil(len(t) / len(lap)))
    return np.tile(lap, reps)[: len(t)]


def _substep_midpoints(duration: float, dt: float) -> np.ndarray:
    """Midpoints (s) of the substeps of ``dt`` s that cover ``duration`` s."""
    return (np.arange(int(round(duration / dt))) + 0.5) * dt


def _commands(tr: TrajectorySpec, duration: float, dt: float, rng: np.random.Generator,
              drive_duration: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Commanded (v m/s, w rad/s) at the substep midpoints, for ``duration`` s.

    A random drive is drawn for ``drive_duration`` s (default ``duration``) and then cut (or
    extended) to ``duration``: the commands agree with those of a ``drive_duration`` run up to
    min(duration, drive_duration) - tr.ramp s, where the shorter run starts ramping down to rest."""
    tm = _substep_midpoints(duration, dt)
    env = _envelope(tm, duration, tr.ramp)
    if tr.kind == "random":
        # The last midpoint of the drive_duration run, computed as that run computes it, so that
        # the run of drive_duration s itself draws exactly what it drew before span existed.
        base = _substep_midpoints(drive_duration, dt) if drive_duration is not None else tm
        span = float(base[-1]) if len(base) else 0.0
        g_v, g_w = _smooth_noise(rng, tm, tr.corr_time, count=2, span=span)
        v = tr.speed * np.clip(1.0 + tr.speed_rel_std * g_v, 0.2, 1.8) * env
        # Yaw rate scaled by the envelope too, so the robot does not turn on the spot at rest.
        return v, tr.yaw_rate_std * g_w * env
    if tr.kind == "figure-eight":
        v = tr.speed * env
        s_grid, kappa, period = _lemniscate_curvature(tr.half_width)
    elif tr.kind == "lawnmower":
        r = tr.spacing / 2.0
        half = tr.leg_length / 2.0
        # Start mid-leg so the circular smoothing does not bend the start.
        s_grid, kappa, period = _periodic_curvature(
            [half, math.pi * r, tr.leg_length, math.pi * r, half],
            [0.0, 1.0 / r, 0.0, -1.0 / r, 0.0], tr.smooth_length, 0.01)
        v = tr.speed * env
    elif tr.kind == "loop-stops":
        a, b = tr.loop_size
        r = tr.corner_radius
        arc = 0.5 * math.pi * r
        lead = 2.0  # m of straight between a stop and the next corner
        lengths = [lead, arc, b - 2 * r, arc, a - 2 * r, arc, b - 2 * r, arc, a - 2 * r - lead]
        kappas = [0.0, 1.0 / r, 0.0, 1.0 / r, 0.0, 1.0 / r, 0.0, 1.0 / r, 0.0]
        s_grid, kappa, period = _periodic_curvature(lengths, kappas, tr.smooth_length, 0.01)
        # Stops at s = 0 and two metres before every later corner: stop-to-stop distances.
        sections = [arc + b - 2 * r, arc + a - 2 * r, arc + b - 2 * r, arc + a - 2 * r]
        v = _stop_profile(tm, sections, tr.speed, tr.ramp, tr.stop_time, dt)
        v = v * _ramp((duration - tm) / tr.ramp)
    else:
        raise ValueError(f"unknown trajectory kind {tr.kind!r}")
    # Arc length at each substep midpoint; w = kappa(s) v keeps the path geometric (exact heading
    # change per segment) whatever the speed profile.
    s_mid = np.cumsum(v) * dt - 0.5 * v * dt
    k = np.interp(np.mod(s_mid, period), s_grid, kappa, period=period)
    return v, k * v


def _lemniscate_curvature(a: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Curvature (1/m) over arc length of the lemniscate of Gerono x = a sin u, y = a/2 sin 2u,
    starting at the crossing heading north-east. Returns (s grid m, kappa, lap length m)."""
    u = np.linspace(0.0, 2.0 * np.pi, 200001)
    dx, dy = a * np.cos(u), a * np.cos(2 * u)
    ddx, ddy = -a * np.sin(u), -2 * a * np.sin(2 * u)
    speed = np.hypot(dx, dy)
    kappa = (dx * ddy - dy * ddx) / speed**3
    s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(u))])
    return s[:-1], kappa[:-1], float(s[-1])


# --------------------------------------------------------------------------------------------
# Simulation
# --------------------------------------------------------------------------------------------


def integrate_truth(sc: Scenario, v_cmd: np.ndarray, w_cmd: np.ndarray) -> Truth:
    """Wheel speeds from the commands through the TRUE geometry, then the exact pose."""
    dt = sc.substep
    r, L = sc.true_geometry.wheel_radius, sc.true_geometry.track_width
    wl = (v_cmd - 0.5 * L * w_cmd) / r
    wr = (v_cmd + 0.5 * L * w_cmd) / r
    v = 0.5 * r * (wl + wr)
    w = r * (wr - wl) / L
    x0, y0, yaw0 = sc.trajectory.start
    yaw = yaw0 + np.concatenate([[0.0], np.cumsum(w * dt)])
    dx, dy, _ = se2_step(0.0, 0.0, yaw[:-1], v, w, dt)
    x = x0 + np.concatenate([[0.0], np.cumsum(dx)])
    y = y0 + np.concatenate([[0.0], np.cumsum(dy)])
    zero = np.zeros(1)
    return Truth(dt=dt, t=np.arange(len(v)) * dt, wheel_left=wl, wheel_right=wr, v=v, w=w,
                 x=x, y=y, yaw=yaw, angle_left=np.concatenate([zero, np.cumsum(wl * dt)]),
                 angle_right=np.concatenate([zero, np.cumsum(wr * dt)]))


def _sample_times(rng: np.random.Generator, rate: float, duration: float) -> np.ndarray:
    """Sample instants (s) on the sensor's own clock: a random phase within one period."""
    period = 1.0 / rate
    phase = rng.uniform(0.0, period)
    return phase + np.arange(int(math.floor((duration - phase) / period)) + 1) * period


def _sim_encoders(sc: Scenario, truth: Truth, rng: np.random.Generator) -> EncoderData:
    spec = sc.encoders
    edges = _sample_times(rng, spec.rate, sc.duration)  # t[0] opens the first interval
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


def _sim_imu(sc: Scenario, truth: Truth, rng: np.random.Generator) -> ImuData:
    spec = sc.imu
    t = _sample_times(rng, spec.rate, sc.duration)
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


def _gauss_markov(t: np.ndarray, w: np.ndarray, std: np.ndarray, tau: float) -> np.ndarray:
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


def _sim_gps(sc: Scenario, truth: Truth, rng: np.random.Generator) -> GpsData:
    spec = sc.gps
    tm = _sample_times(rng, spec.rate, sc.duration)
    n = len(tm)
    # Draw every random number for every nominal sample first, so the noise of a fix does not
    # depend on which other fixes were dropped (a correlated error runs over every nominal
    # sample; dropouts and outages remove samples from it).
    std = np.array([spec.horizontal_std, spec.horizontal_std, spec.vertical_std])
    w = rng.standard_normal((n, 3))
    noise = w * std if spec.correlation_s == 0.0 else _gauss_markov(tm, w, std,
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
    enu, true_enu, tm, out = enu[keep], true_enu[keep], tm[keep], out[keep]
    lat, lon, alt = enu_to_geodetic(enu[:, 0], enu[:, 1], enu[:, 2], *sc.datum)
    return GpsData(t=tm + spec.delay, t_measured=tm, enu=enu, lat=np.asarray(lat),
                   lon=np.asarray(lon), alt=np.asarray(alt), outlier=out, true_enu=true_enu)


def _landmark_map(sc: Scenario, truth: Truth, rng: np.random.Generator
                  ) -> tuple[list[str], np.ndarray]:
    """Landmarks uniformly in the path's bounding box grown by the margin (m)."""
    spec = sc.landmarks
    lo = np.array([truth.x.min(), truth.y.min()]) - spec.margin
    hi = np.array([truth.x.max(), truth.y.max()]) + spec.margin
    pos = lo + (hi - lo) * rng.uniform(size=(spec.count, 2))
    return [str(i + 1) for i in range(spec.count)], pos


def _sim_landmarks(sc: Scenario, truth: Truth, rng: np.random.Generator,
                   map_rng: np.random.Generator, map_truth: Truth | None = None
                   ) -> LandmarkData:
    """Sightings along ``truth`` of the landmarks drawn around ``map_truth``'s path (default
    ``truth``'s)."""
    spec = sc.landmarks
    ids, pos = _landmark_map(sc, truth if map_truth is None else map_truth, map_rng)
    t = _sample_times(rng, spec.rate, sc.duration)
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


def _sim_ground_truth(sc: Scenario, truth: Truth) -> GroundTruthData:
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


def get_scenario(scenario: str, duration: float | None = None) -> Scenario:
    """The named scenario, with its duration (s) replaced when given: the same drive cut (or
    extended) to that duration, see ``with_duration``."""
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; choose from {', '.join(SCENARIOS)}")
    sc = SCENARIOS[scenario]
    if duration is not None:
        if not duration > 2.0 * sc.trajectory.ramp:
            raise ValueError(f"duration must exceed {2.0 * sc.trajectory.ramp} s")
        sc = with_duration(sc, duration)
    return sc


def with_duration(sc: Scenario, duration: float) -> Scenario:
    """``sc`` run for ``duration`` s, its drive still drawn for its own (drive) duration.

    A shorter run is the first part of the longer drive: the same truth up to ``duration`` minus
    the trajectory's ramp (where it slows to rest) and the same landmark map. A longer run drives
    the same path up to the drive duration minus the ramp (the longer run does not slow down
    there) and then goes on; its landmark map is drawn in its own, larger, bounding box. Sensor
    samples and noise are drawn for ``duration`` s, so they are not a prefix of the longer run's."""
    drive = sc.drive_duration if sc.drive_duration is not None else sc.duration
    return replace(sc, duration=float(duration), drive_duration=drive)


def simulate(scenario: str | Scenario, seed: int = 0, duration: float | None = None
             ) -> SimResult:
    """Simulate a named scenario (see SCENARIOS) or a Scenario; deterministic per ``seed``."""
    sc = scenario if isinstance(scenario, Scenario) else get_scenario(scenario, duration)
    if isinstance(scenario, Scenario) and duration is not None:
        sc = with_duration(sc, duration)
    truth = _drive(sc, seed, sc.duration)
    res = SimResult(scenario=sc, seed=seed, truth=truth,
                    ground_truth=_sim_ground_truth(sc, truth),
                    encoders=_sim_encoders(sc, truth, _rng(seed, "encoders")))
    if sc.imu:
        res.imu = _sim_imu(sc, truth, _rng(seed, "imu"))
    if sc.gps:
        if sc.datum is None:
            raise ValueError(f"scenario {sc.name}: GPS needs a datum")
        res.gps = _sim_gps(sc, truth, _rng(seed, "gps"))
    if sc.landmarks:
        # A run cut short of its drive keeps the whole drive's map, so that it is the same world
        # (the map is drawn in the path's bounding box, which a shorter path would shrink).
        drive = sc.drive_duration if sc.drive_duration is not None else sc.duration
        map_truth = truth if drive <= sc.duration else _drive(sc, seed, drive)
        res.landmarks = _sim_landmarks(sc, truth, _rng(seed, "landmarks"),
                                       _rng(seed, "landmark_map"), map_truth)
    return res


def _drive(sc: Scenario, seed: int, duration: float) -> Truth:
    """The true motion of ``sc``'s drive for ``seed``, run for ``duration`` s."""
    v_cmd, w_cmd = _commands(sc.trajectory, duration, sc.substep, _rng(seed, "trajectory"),
                             sc.drive_duration)
    return integrate_truth(sc, v_cmd, w_cmd)


# --------------------------------------------------------------------------------------------
# Config and landmark map
# --------------------------------------------------------------------------------------------


def sidecar_paths(path: str | Path) -> tuple[Path, Path]:
    """(config YAML, landmark map YAML) written next to a bag file or bag directory."""
    p = Path(path)
    stem = p.with_suffix("") if p.suffix in (".bag", ".mcap", ".db3") else p
    return stem.parent / (stem.name + ".yaml"), stem.parent / (stem.name + ".landmarks.yaml")


def sim_config(res: SimResult, landmark_map: str | None = None) -> dict:
    """The ddfuse config (as a YAML tree) describing a simulated bag, with the true noise."""
    sc = res.scenario
    noise = res.noise()
    sensors: dict[str, list] = {}
    if sc.encoders.odometry_topic:
        sensors["odometry"] = [{"topic": sc.encoders.odometry_topic, "use": ["v", "yaw_rate"],
                                "noise": noise["odometry"]}]
    if sc.encoders.joint_topic:
        sensors["wheels"] = [{"topic": sc.encoders.joint_topic,
                              "joints": list(sc.encoders.joints), "noise": noise["wheels"]}]
    if sc.imu:
        sensors["imu"] = [{"topic": sc.imu.topic, "use": ["yaw", "yaw_rate", "accel"],
                           "noise": noise["imu"], "heading_offset": "estimate",
                           "gyro_bias": "estimate"}]
    if sc.gps:
        sensors["gps"] = [{"topic": sc.gps.topic, "noise": noise["gps"], "delay": sc.gps.delay}]
        if sc.gps.correlation_s > 0.0:  # the true error model, as the noise values are
            sensors["gps"][0]["correlation_time"] = sc.gps.correlation_s
    if sc.landmarks:
        if landmark_map is None:
            raise ValueError("a scenario with landmarks needs the landmark map's file name")
        sensors["landmarks"] = [{"topic": sc.landmarks.topic, "map": landmark_map,
                                 "noise": noise["landmarks"]}]
    robot = {"wheel_radius": sc.nominal_geometry.wheel_radius,
             "track_width": sc.nominal_geometry.track_width}
    if sc.geometry_std is not None:
        robot.update(wheel_radius_std=sc.geometry_std.wheel_radius,
                     track_width_std=sc.geometry_std.track_width)
    # the largest accelerations of the simulated motion (the commands are smooth; the
    # unicycle EKF derives its twist random walks from these)
    tr = res.truth
    for key, rate in (("max_accel", tr.v), ("max_yaw_accel", tr.w)):
        a_max = float(np.max(np.abs(np.gradient(rate, tr.dt))))
        if a_max > 0.0:  # a drive without any (a short straight one) states no limit
            robot[key] = a_max
    # the simulated body moves exactly with its twist (the encoders' slip noise is in their
    # counts, not in the motion)
    robot["slip"] = {"longitudinal": 0.0, "lateral": 0.0, "heading": 0.0}
    cfg: dict = {
        "sensors": sensors,
        "robot": robot,
        "ground_truth": {"topic": sc.truth_topic},
    }
    if sc.datum is not None:
        cfg["frame"] = {"datum": list(sc.datum)}
    cfg["initial_pose"] = "ground_truth"
    # a keyframe at every absolute measurement (GPS fix or landmark scan): attached to a rate
    # keyframe instead, a scan is carried there by the keyframe's twist, which one noisy
    # odometry sample ties, and k_w came out biased (seed002, docs/results/smoother_monte_carlo.md)
    cfg["smoother"] = {"lag": SMOOTHER_LAG, "keyframe": "gps", "robust": "huber"}
    cfg["ekf"] = {"rate": "event"}
    return cfg


def _truth_comment(res: SimResult, fmt: str) -> str:
    """Header comment with the true values a config cannot state (for evaluation by eye)."""
    sc = res.scenario
    lines = [
        f"ddfuse config for a simulated bag: scenario {sc.name}, seed {res.seed}, "
        f"{sc.duration:g} s.",
        f"Regenerate: ddfuse simulate {sc.name} --seed {res.seed} "
        f"--duration {sc.duration:g} --format {fmt} -o <bag>",
        "Noise values are the simulator's true standard deviations (SI).",
        f"True geometry: wheel_radius {sc.true_geometry.wheel_radius} m, track_width "
        f"{sc.true_geometry.track_width} m (robot: below is the nominal one).",
    ]
    if sc.imu:
        lines.append(f"True IMU heading offset {sc.imu.heading_offset} rad; gyro bias starts at "
                     f"{sc.imu.gyro_bias0} rad/s, random walk {sc.imu.gyro_bias_walk} "
                     "rad/s/sqrt(s).")
    if sc.gps:
        g = sc.gps
        lines.append(f"GPS: latency {g.delay} s (fix stamped late), dropouts {g.dropout_prob}, "
                     f"outliers {g.outlier_prob} ({g.outlier_range[0]:g}-{g.outlier_range[1]:g} "
                     f"m), outages {list(g.outages)} s after the start.")
        if g.correlation_s > 0.0:
            lines.append(f"GPS errors are time-correlated: per axis a first-order Gauss-Markov "
                         f"process, correlation time {g.correlation_s:g} s (correlation_time "
                         "below), stationary std as stated below.")
    return "".join(f"# {s}\n" for s in lines)


def write_sidecars(res: SimResult, path: str | Path, fmt: str = "ros1"
                   ) -> tuple[Path, Path | None]:
    """Write the config YAML (and the landmark map YAML) next to the bag at ``path``."""
    cfg_path, map_path = sidecar_paths(path)
    if res.landmarks is not None:
        lm = res.landmarks
        body = {"frame": "local",
                "landmarks": {i: [float(p[0]), float(p[1])] for i, p in zip(lm.ids, lm.positions,
                                                                            strict=True)}}
        map_path.write_text(f"# Simulated landmarks (scenario {res.scenario.name}, seed "
                            f"{res.seed}): id -> [x, y] m in the local frame\n"
                            + yaml.safe_dump(body, sort_keys=False))
    else:
        map_path = None
    cfg = sim_config(res, map_path.name if map_path else None)
    cfg_path.write_text(_truth_comment(res, fmt) + yaml.safe_dump(cfg, sort_keys=False))
    return cfg_path, map_path


# --------------------------------------------------------------------------------------------
# Bag writing
# --------------------------------------------------------------------------------------------


def make_typestore(fmt: str):
    """rosbags typestore for the format (Noetic for ROS1, Humble for ROS2/MCAP) with the
    LandmarkObservation type registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg(LANDMARK_MSGDEF, LANDMARK_MSGTYPE))
    return ts


class _Msgs:
    """Builds messages of one typestore; hides the ROS1 Header's seq field."""

    def __init__(self, ts, fmt: str, t0_ns: int):
        self.ts = ts
        self.T = ts.types
        self.t0_ns = t0_ns
        self.ros1 = fmt == "ros1"
        self.serialize = ts.serialize_ros1 if self.ros1 else ts.serialize_cdr

    def ns(self, t: float) -> int:
        return self.t0_ns + int(round(t * 1e9))

    def header(self, ns: int, frame: str, seq: int):
        stamp = self.T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        H = self.T["std_msgs/msg/Header"]
        if self.ros1:
            return H(seq=seq, stamp=stamp, frame_id=frame)
        return H(stamp=stamp, frame_id=frame)

    def vec(self, x: float, y: float, z: float):
        return self.T["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))

    def quat(self, x: float, y: float, z: float, w: float):
        return self.T["geometry_msgs/msg/Quaternion"](x=float(x), y=float(y), z=float(z),
                                                     w=float(w))

    def odometry(self, ns, seq, frame, child, px, py, yaw, v, w, pose_cov, twist_cov):
        T = self.T
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(px), y=float(py), z=0.0),
            orientation=self.quat(0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)))
        twist = T["geometry_msgs/msg/Twist"](linear=self.vec(v, 0.0, 0.0),
                                            angular=self.vec(0.0, 0.0, w))
        return T["nav_msgs/msg/Odometry"](
            header=self.header(ns, frame, seq), child_frame_id=child,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=pose_cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=twist_cov))

    def navsatfix(self, ns, seq, frame, lat, lon, alt, cov9, cov_type):
        T = self.T
        st = T["sensor_msgs/msg/NavSatStatus"]
        return T["sensor_msgs/msg/NavSatFix"](
            header=self.header(ns, frame, seq),
            status=st(status=st.STATUS_FIX, service=st.SERVICE_GPS),
            latitude=float(lat), longitude=float(lon), altitude=float(alt),
            position_covariance=cov9, position_covariance_type=cov_type)


def _diag(values: list[float], n: int) -> np.ndarray:
    c = np.zeros((n, n))
    c[np.diag_indices(n)] = values
    return c.ravel()


def _quat_rpy(roll, pitch, yaw) -> tuple[float, float, float, float]:
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


def _topic_messages(res: SimResult, mk: _Msgs) -> list[tuple[str, str, Iterator]]:
    """(topic, msgtype, iterator of (stamp ns, message)) for every topic of the result."""
    sc = res.scenario
    T = mk.T
    noise = res.noise()
    out: list[tuple[str, str, Iterator]] = []
    enc = res.encoders

    if sc.encoders.odometry_topic:
        n = noise["odometry"]
        pose_cov = _diag([UNUSED_VAR] * 6, 6)
        twist_cov = _diag([n["v"] ** 2, UNUSED_VAR, UNUSED_VAR, UNUSED_VAR, UNUSED_VAR,
                           n["yaw_rate"] ** 2], 6)

        def odom():
            for k in range(len(enc.t)):
                yield mk.ns(enc.t[k]), mk.odometry(
                    mk.ns(enc.t[k]), k, "odom", "base_link", enc.x[k], enc.y[k], enc.yaw[k],
                    enc.v[k], enc.yaw_rate[k], pose_cov, twist_cov)

        out.append((sc.encoders.odometry_topic, "nav_msgs/msg/Odometry", odom()))

    if sc.encoders.joint_topic:
        names = list(sc.encoders.joints)

        def joints():
            J = T["sensor_msgs/msg/JointState"]
            for k in range(len(enc.t)):
                ns = mk.ns(enc.t[k])
                yield ns, J(header=mk.header(ns, "base_link", k), name=names,
                            position=np.array([enc.counts_left[k], enc.counts_right[k]],
                                              dtype=float) * enc.tick,
                            velocity=np.array([enc.left[k], enc.right[k]]),
                            effort=np.zeros(0))

        out.append((sc.encoders.joint_topic, "sensor_msgs/msg/JointState", joints()))

    if res.imu is not None:
        imu, spec = res.imu, sc.imu
        ocov = _diag([spec.tilt_std**2, spec.tilt_std**2, spec.heading_std**2], 3)
        wcov = _diag([spec.gyro_std**2] * 3, 3)
        acov = _diag([spec.accel_std**2] * 3, 3)

        def imus():
            Imu = T["sensor_msgs/msg/Imu"]
            for k in range(len(imu.t)):
                ns = mk.ns(imu.t[k])
                yield ns, Imu(
                    header=mk.header(ns, "imu_link", k),
                    orientation=mk.quat(*_quat_rpy(imu.roll[k], imu.pitch[k], imu.yaw[k])),
                    orientation_covariance=ocov,
                    angular_velocity=mk.vec(imu.gyro_xy[k, 0], imu.gyro_xy[k, 1],
                                            imu.yaw_rate[k]),
                    angular_velocity_covariance=wcov,
                    linear_acceleration=mk.vec(*imu.accel[k]),
                    linear_acceleration_covariance=acov)

        out.append((spec.topic, "sensor_msgs/msg/Imu", imus()))

    if res.gps is not None:
        gps, spec = res.gps, sc.gps
        cov = _diag([spec.horizontal_std**2, spec.horizontal_std**2, spec.vertical_std**2], 3)
        diag_known = T["sensor_msgs/msg/NavSatFix"].COVARIANCE_TYPE_DIAGONAL_KNOWN

        def fixes():
            for k in range(len(gps.t)):
                ns = mk.ns(gps.t[k])
                yield ns, mk.navsatfix(ns, k, "gps", gps.lat[k], gps.lon[k], gps.alt[k], cov,
                                       diag_known)

        out.append((spec.topic, "sensor_msgs/msg/NavSatFix", fixes()))

    if res.landmarks is not None:
        lm, spec = res.landmarks, sc.landmarks
        rv, bv = spec.range_std**2, spec.bearing_std**2

        def sightings():
            L = T[LANDMARK_MSGTYPE]
            for k in range(len(lm.t)):
                ns = mk.ns(lm.t[k])
                yield ns, L(header=mk.header(ns, "base_link", k),
                            landmark_id=lm.ids[lm.index[k]], range=float(lm.range[k]),
                            bearing=float(lm.bearing[k]), range_variance=rv,
                            bearing_variance=bv, has_bearing=True)

        out.append((spec.topic, LANDMARK_MSGTYPE, sightings()))

    gt = res.ground_truth
    zero36 = np.zeros(36)

    def truth():
        for k in range(len(gt.t)):
            ns = mk.ns(gt.t[k])
            yield ns, mk.odometry(ns, k, "map", "base_link", gt.x[k], gt.y[k], gt.yaw[k],
                                  gt.v[k], gt.w[k], zero36, zero36)

    out.append((sc.truth_topic, "nav_msgs/msg/Odometry", truth()))

    if len(gt.fix_t):
        known = T["sensor_msgs/msg/NavSatFix"].COVARIANCE_TYPE_KNOWN
        zero9 = np.zeros(9)

        def truth_fixes():
            for k in range(len(gt.fix_t)):
                ns = mk.ns(gt.fix_t[k])
                yield ns, mk.navsatfix(ns, k, "base_link", gt.fix_lat[k], gt.fix_lon[k],
                                       gt.fix_alt[k], zero9, known)

        out.append((sc.truth_fix_topic, "sensor_msgs/msg/NavSatFix", truth_fixes()))
    return out


def storage_file(path: str | Path, fmt: str = "ros1") -> Path:
    """The file holding the messages of the bag ``write_bag(res, path, fmt)`` writes: the
    ros1 bag itself; for ros2 and mcap, the file in the bag directory ``path``, named after it
    without the extension the file carries: ``h.mcap`` -> ``h.mcap/h.mcap``, ``run`` ->
    ``run/run.mcap``, ``x.db3`` -> ``x.db3/x.db3``."""
    p = Path(path)
    if fmt == "ros1":
        return p
    suffix = SUFFIXES[fmt]
    name = p.name[:-len(suffix)] if p.name.endswith(suffix) and p.name != suffix else p.name
    return p / (name + suffix)


def _check_output(path: str | Path, fmt: str) -> Path:
    """The bag path, after checking the format name, that the path's extension (if it has one
    of .bag, .db3, .mcap) is the format's (another would name a bag that is read as that
    format: an mcap directory called x.bag is taken for a ROS 1 bag), and that nothing would
    be overwritten."""
    p = Path(path)
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    other = {v: k for k, v in SUFFIXES.items()}.get(p.suffix, fmt)
    if other != fmt:
        raise ValueError(f"{p}: a name ending in {p.suffix} says {other} (and is read as "
                         f"one); a {fmt} bag's name ends in {SUFFIXES[fmt]} or has no "
                         "extension")
    if p.exists():
        raise FileExistsError(f"{p} exists; remove it first (bags are never overwritten)")
    # the config and map go beside the bag: another bag of the same stem (h.bag and h.mcap)
    # has its own there, and a bag left beside another run's config would be read with it
    for side in sidecar_paths(p):
        if side.exists():
            raise FileExistsError(f"{side} exists (the config or landmark map of another "
                                  f"bag named like {p.name}); remove it or choose another name")
    return p


def _tagged(i: int, it: Iterator) -> Iterator[tuple[int, int, object]]:
    """(stamp ns, topic index, message): a function, so each generator keeps its own index."""
    for ns, msg in it:
        yield ns, i, msg


def write_bag(res: SimResult, path: str | Path, fmt: str = "ros1", compress: bool = True
              ) -> tuple[Path, Path, Path | None]:
    """Write the bag (ROS1 file, or ROS2 directory with sqlite3 or MCAP storage: the file in it
    is ``storage_file(path, fmt)``), then the config YAML and landmark map YAML next to it
    (``sidecar_paths``). Messages are written in stamp order with the record time equal to the
    header stamp. ``compress``: LZ4 chunks for ROS1 (no effect on ROS2).

    Returns (bag path, config path, landmark map path or None)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    p = _check_output(path, fmt)
    ts = make_typestore(fmt)
    mk = _Msgs(ts, fmt, res.scenario.t0_ns)
    topics = _topic_messages(res, mk)
    if fmt == "ros1":
        writer = Writer1(p)
        if compress:
            writer.set_compression(Writer1.CompressionFormat.LZ4)
        _write_messages(writer, topics, ts, mk)
    else:
        # rosbags names the storage file after the directory it makes (<dir>/<dir name>.mcap):
        # the bag is made as a directory named like the file's stem in a temporary directory
        # beside ``p``, then renamed to ``p`` (complete, or not at all).
        plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
        p.parent.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{p.name}.", dir=p.parent))
        try:
            made = stage / storage_file(p, fmt).stem
            _write_messages(Writer2(made, version=9, storage_plugin=plugin), topics, ts, mk)
            if p.exists():  # made meanwhile by someone else
                raise FileExistsError(f"{p} exists; remove it first (bags are never "
                                      "overwritten)")
            os.rename(made, p)
        finally:
            shutil.rmtree(stage, ignore_errors=True)
    cfg_path, map_path = write_sidecars(res, p, fmt)
    return p, cfg_path, map_path


def _write_messages(writer, topics, ts, mk: _Msgs) -> None:
    """Every message of ``topics`` (``_topic_messages``) into the opened-on-entry ``writer``."""
    with writer:
        conns = [writer.add_connection(topic, msgtype, typestore=ts)
                 for topic, msgtype, _ in topics]
        # Merge the per-topic streams by stamp; ties keep topic order, so output is reproducible.
        merged = heapq.merge(*[_tagged(i, it) for i, (_, _, it) in enumerate(topics)],
                             key=lambda item: (item[0], item[1]))
        for ns, i, msg in merged:
            writer.write(conns[i], ns, mk.serialize(msg, topics[i][1]))


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def _main(argv: list[str] | None) -> int:
    from ddfuse.estimation.errors import DdfuseError
    from ddfuse.evaluation.cli import (
        DdfuseParser,
        check_output_file,
        int_at_least,
        simulated_scenario,
    )

    ap = DdfuseParser(
        prog="ddfuse simulate",
        description="Simulate a differential-drive robot and write a bag with ground truth, "
        "plus the ddfuse config (and landmark map) next to it.",
        epilog="Scenarios: " + "; ".join(f"{k}: {v.description}" for k, v in SCENARIOS.items()),
    )
    ap.add_argument("scenario", choices=list(SCENARIOS))
    ap.add_argument("--seed", type=int_at_least(0), default=0, help="random seed (default 0)")
    ap.add_argument("--duration", type=float, default=None, metavar="S",
                    help="seconds to simulate (default: the scenario's). The run is the "
                    "scenario's drive for this seed cut to S s: the truth (and seed002's "
                    "landmark map) is that of the default-duration run up to S - 3 s, where the "
                    "robot starts slowing to rest. Longer than the default, the path is the "
                    "default run's up to its duration - 3 s and then goes on (seed002 then draws "
                    "its landmark map around the longer path). Sensor noise is drawn for the S s "
                    "run, so it is not the default run's")
    ap.add_argument("--format", choices=FORMATS, default="ros1",
                    help="ros1 (a .bag file), ros2 (a directory: NAME.db3 and metadata.yaml) "
                    "or mcap (a directory: NAME.mcap and metadata.yaml)")
    ap.add_argument("-o", "--output", required=True,
                    help="bag path to create: for ros2 and mcap the directory, whose file is "
                    "named after it (-o h.mcap: h.mcap/h.mcap; -o run: run/run.mcap); the "
                    "config goes beside it, the path with .yaml (h.yaml, run.yaml)")
    args = ap.parse_args(argv)
    simulated_scenario(args.scenario, args.duration)
    # Before simulating (the long scenario takes a while): the bag must not exist, and its
    # directory must be one (it is created, as a ROS 2 writer creates its own).
    out = Path(args.output)
    try:
        _check_output(out, args.format)
    except (FileExistsError, ValueError) as e:
        raise DdfuseError(f"-o {e}") from None
    check_output_file(out, "-o", create_parents=True)
    res = simulate(args.scenario, seed=args.seed, duration=args.duration)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        bag, cfg, lmap = write_bag(res, out, args.format)
    except FileExistsError as e:  # made meanwhile by someone else
        raise DdfuseError(f"-o {e}") from None
    what = f"{res.duration:g} s, scenario {args.scenario}, seed {args.seed}"
    if args.format == "ros1":
        print(f"wrote {bag} (ros1, {what})")
    else:  # say that it is a directory, and what is in it
        print(f"wrote {bag}{os.sep} (ROS 2 bag directory, {args.format}, {what}): "
              f"{storage_file(bag, args.format)} and {bag / 'metadata.yaml'}")
    print(f"wrote {cfg}")
    if lmap:
        print(f"wrote {lmap}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``ddfuse simulate SCENARIO [--seed N] [--duration S] [--format F] -o PATH``; a user error
    ends in one line on stderr and exit code 2."""
    from ddfuse.evaluation.cli import guarded

    return guarded(_main, argv)


if __name__ == "__main__":
    sys.exit(main())
