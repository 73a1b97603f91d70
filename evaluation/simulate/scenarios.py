"""The simulator's scenarios: the robot, its commanded motion and its sensors, by name.

A ``Scenario`` is frozen data (SI units; times in seconds since the start of the run, angles in
radians, positions in the local ENU frame about ``datum``); ``SCENARIOS`` names the documented
ones and ``get_scenario`` gives one, cut (or extended) to another duration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace


@dataclass(frozen=True)
class Geometry:
    """Wheel radius and track width (distance between the wheels' contact points), m."""

    wheel_radius: float
    track_width: float


@dataclass(frozen=True)
class TrajectorySpec:
    """The commanded motion. ``kind``: 'random', 'figure-eight', 'lawnmower', 'loop-stops',
    'wheel-steps'.

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
    # wheel-steps (seed 002's published simulation): each wheel's rim speed drawn uniformly in
    # wheel_speeds (m/s) afresh every ``hold`` s and held; the body twist is v = (l + r)/2,
    # w = (r - l)/track_width (m, the robot's true track). The speed jumps at every step: the
    # motion is not smooth and its accelerations are bounded only by the integration substep.
    wheel_speeds: tuple[float, float] = (5.0, 15.0)  # m/s
    hold: float = 0.1  # s
    track_width: float = 2.0  # m


@dataclass(frozen=True)
class EncoderSpec:
    """Wheel encoders, published as JointState (wheel speeds) and/or Odometry (twist)."""

    rate: float = 10.0  # Hz
    speed_std: float = 0.15  # rad/s, error std of one wheel-speed sample (slip + quantisation)
    counts_per_rev: int = 2000  # encoder counts per wheel revolution
    odometry_topic: str | None = "/odom"
    joint_topic: str | None = None
    joints: tuple[str, str] = ("left_wheel_joint", "right_wheel_joint")
    phase: float | None = None  # s, of the sample clock; None: random (see sample_times)


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
    # what the written config uses of it: a car's gyro alone is ("yaw_rate",)
    use: tuple[str, ...] = ("yaw", "yaw_rate", "accel")


@dataclass(frozen=True)
class UrbanGpsSpec:
    """The urban GPS error model (``evaluation/simulate/urban_gps.py``; statistics and why:
    docs/design/urban_gps.md). Stretches of open sky and street canyon alternate in time (each
    exponentially long); the error is a Gauss-Markov wander (per axis, ``base_tau_s``) of std
    ``open_std`` or ``canyon_std``, plus in a canyon multipath bursts (Poisson onsets at
    ``burst_rate`` per canyon second, each a held offset of uniform ``burst_range`` m in a
    random direction, lasting uniform ``burst_length_s``, wobbling by a fifth of it with
    correlation time ``burst_tau_s``) and NLOS jumps (a fix starts one with probability
    ``nlos_prob``, held for a geometric number of fixes of mean ``nlos_mean_fixes``, of uniform
    ``nlos_range`` m). Bridges (Poisson at ``bridge_rate`` per second, uniform
    ``bridge_length_s`` long) are outages. The stated covariance is GpsSpec.horizontal_std."""

    canyon_fraction: float = 0.35  # of the time
    canyon_mean_s: float = 60.0  # s, mean length of a canyon stretch
    open_std: float = 2.0  # m per axis
    canyon_std: float = 4.0  # m per axis
    base_tau_s: float = 10.0  # s
    burst_rate: float = 1.0 / 20.0  # 1/s of canyon
    burst_length_s: tuple[float, float] = (2.0, 10.0)  # s
    burst_range: tuple[float, float] = (10.0, 40.0)  # m
    burst_tau_s: float = 2.0  # s
    nlos_prob: float = 0.02  # per canyon fix
    nlos_mean_fixes: float = 3.0
    nlos_range: tuple[float, float] = (20.0, 80.0)  # m
    bridge_rate: float = 1.0 / 120.0  # 1/s
    bridge_length_s: tuple[float, float] = (3.0, 15.0)  # s

    def __post_init__(self):
        for name in ("canyon_fraction", "nlos_prob"):
            v = getattr(self, name)
            if not 0.0 <= v < 1.0:
                raise ValueError(f"UrbanGpsSpec.{name} must be in [0, 1), got {v!r}")
        for name in ("canyon_mean_s", "open_std", "canyon_std", "base_tau_s", "burst_tau_s",
                     "nlos_mean_fixes"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"UrbanGpsSpec.{name} must be a number > 0, got {v!r}")
        for name in ("burst_rate", "bridge_rate"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"UrbanGpsSpec.{name} must be a rate >= 0 (1/s), got {v!r}")
        for name in ("burst_length_s", "burst_range", "nlos_range", "bridge_length_s"):
            lo, hi = getattr(self, name)
            if not (0.0 <= lo <= hi and math.isfinite(hi)):
                raise ValueError(f"UrbanGpsSpec.{name} must be [low, high] with 0 <= low <= "
                                 f"high, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class MagnetometerSpec:
    """A 3-axis magnetometer (sensor_msgs/MagneticField) on the level body: the earth's field
    ``field_enu`` (T, in ENU: east, north, up) rotated into the body at the true yaw, plus a
    constant hard-iron offset (T, sensor frame) and white noise. The field's horizontal part
    points to magnetic north, ``declination`` (rad, east positive) clockwise of true north;
    ``field_enu`` must agree with it (``earth_field``)."""

    rate: float = 20.0  # Hz
    declination: float = 0.052  # rad (3.0 deg east, Zurich 2024)
    field_enu: tuple[float, float, float] | None = None  # T; None: earth_field(declination)
    noise_std: float = 3e-7  # T per axis (0.3 uT: about 0.8 deg of yaw in a 21.6 uT field)
    hard_iron: tuple[float, float, float] = (2e-6, -1.5e-6, 0.5e-6)  # T, sensor frame
    topic: str = "/imu/mag"

    @property
    def field(self) -> tuple[float, float, float]:
        return self.field_enu if self.field_enu is not None else earth_field(self.declination)


def earth_field(declination: float, horizontal: float = 21.6e-6, down: float = 43.0e-6
                ) -> tuple[float, float, float]:
    """The earth's field (T) in ENU for a declination (rad, east positive) and the horizontal
    and downward intensities (T; defaults: about Zurich's, inclination 63 deg)."""
    return (horizontal * math.sin(declination), horizontal * math.cos(declination), -down)


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
    # the urban error model instead of the white / Gauss-Markov noise above (horizontal_std is
    # then only what the receiver states)
    urban: UrbanGpsSpec | None = None

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
    # m: when set, landmarks are drawn uniformly in the square of this half-width centred on the
    # start position instead (seed 002's published simulation: +-300)
    area: float | None = None
    phase: float | None = None  # s, of the scan clock; None: random (see sample_times)
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
    magnetometer: MagnetometerSpec | None = None
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
    # the slip densities the written config states (robot.slip: longitudinal, lateral m/sqrt(s),
    # heading rad/sqrt(s)); None: 0, the simulated body moves exactly with its twist
    config_slip: tuple[float, float, float] | None = None


# A field site near Zurich, Switzerland: lat, lon (deg), ellipsoidal altitude (m).
OUTDOOR_DATUM = (47.397742, 8.545594, 488.0)

_HUSKY_TRUE = Geometry(wheel_radius=0.1635, track_width=0.5826)  # worn tyres, skid-steer track
_HUSKY_NOMINAL = Geometry(wheel_radius=0.165, track_width=0.555)  # Husky datasheet
# tyre wear and skid-steer slip: the datasheet radius known to 2 mm, the effective track to 3 cm
_HUSKY_STD = Geometry(wheel_radius=0.002, track_width=0.03)


def _husky(name: str, description: str, trajectory: TrajectorySpec, duration: float = 400.0,
           gps: GpsSpec | None = None, truth_rate: float = 20.0,
           encoders: EncoderSpec | None = None, imu: ImuSpec | None = ImuSpec(),
           magnetometer: MagnetometerSpec | None = None) -> Scenario:
    return Scenario(
        name=name, description=description, duration=duration, trajectory=trajectory,
        true_geometry=_HUSKY_TRUE, nominal_geometry=_HUSKY_NOMINAL,
        encoders=encoders or EncoderSpec(rate=10.0, speed_std=0.15, counts_per_rev=2000),
        imu=imu, gps=gps or GpsSpec(), datum=OUTDOOR_DATUM, truth_rate=truth_rate,
        geometry_std=_HUSKY_STD, magnetometer=magnetometer,
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
    # What seed 002's published code ran (its run.py and robotcar.py, 2015): wheel rim speeds
    # uniform in 5-15 m/s redrawn every 0.1 s, track 2 m, wheel radius 0.5 m, per-wheel speed
    # noise 0.4 m/s (0.8 rad/s), 20 landmarks uniform in +-300 m, every one sighted at every
    # step with range and bearing noise 0.4 m and 0.4 rad. Units: the code's "units" read as m.
    # How it compares with seed002 and the blog's 3.45: docs/results/seed002_blog.md
    "seed002-blog": Scenario(
        name="seed002-blog",
        description="Seed 002 as its published code simulates it: wheel speeds uniform in "
        "5-15 m/s redrawn every 0.1 s (track 2 m), wheel speed noise 0.4 m/s, 20 landmarks "
        "uniform in +-300 m all sighted at 10 Hz with range/bearing noise 0.4 m / 0.4 rad, "
        "2 min, no GPS.",
        duration=120.0,
        trajectory=TrajectorySpec("wheel-steps", ramp=0.1, wheel_speeds=(5.0, 15.0), hold=0.1,
                                  track_width=2.0),
        true_geometry=Geometry(wheel_radius=0.5, track_width=2.0),
        nominal_geometry=Geometry(wheel_radius=0.5, track_width=2.0),
        # encoders and range finder sampled in step with the wheel commands, as in the code
        encoders=EncoderSpec(rate=10.0, speed_std=0.8, counts_per_rev=2**20,
                             odometry_topic=None, joint_topic="/joint_states", phase=0.0),
        landmarks=LandmarkSpec(count=20, range_std=0.4, bearing_std=0.4, min_range=0.0,
                               max_range=1e4, fov=2.0 * math.pi, detect_prob=1.0, area=300.0,
                               phase=0.0),
        truth_rate=10.0,
    ),
    "husky": _husky(
        "husky", "Husky-like outdoor robot mowing a field (lawnmower legs of 40 m): 10 Hz "
        "wheel odometry, 30 Hz IMU (heading offset, gyro bias), 2.5 Hz GPS, 400 s.",
        _LAWNMOWER),
    # The 30 s correlation time is measured on rl_husky_gps.bag (../shared/data); how, and why
    # the report's residual correlation time is shorter: docs/results/smoother_monte_carlo.md
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
    # the sensors issue 30 found no bag for (docs/design/sensors.md)
    "husky-magnetometer": _husky(
        "husky-magnetometer", "husky plus a 20 Hz 3-axis magnetometer (sensor_msgs/MagneticField "
        "on /imu/mag): the earth's field at 3 deg east declination, a hard-iron offset and "
        "0.3 uT noise, the config stating both.",
        _LAWNMOWER, magnetometer=MagnetometerSpec()),
    "husky-encoders": _husky(
        "husky-encoders", "husky's wheel encoders as a robot's driver publishes them "
        "(sensor_msgs/JointState wheel speeds on /joint_states, no odometry) with GPS "
        "(NavSatFix), no IMU.",
        _LAWNMOWER, imu=None,
        encoders=EncoderSpec(rate=10.0, speed_std=0.15, counts_per_rev=2000,
                             odometry_topic=None, joint_topic="/joint_states")),
    "figure-eight": _husky(
        "figure-eight", "husky sensors on a 30 x 15 m figure-eight, 400 s.",
        TrajectorySpec("figure-eight", speed=1.0, start=(0.0, 0.0, math.pi / 4))),
    "loop-stops": _husky(
        "loop-stops", "husky sensors on a 30 x 20 m loop with stops at every corner, 400 s.",
        TrajectorySpec("loop-stops", speed=1.0)),
    "random": _husky(
        "random", "husky sensors on a random smooth path, 400 s.",
        TrajectorySpec("random", speed=1.0, yaw_rate_std=0.2, corr_time=5.0)),
    # A car in a city: docs/design/urban_gps.md
    "urban": Scenario(
        name="urban",
        description="A car in a city, 10 min at 5-15 m/s: 20 Hz wheel odometry, a 50 Hz gyro "
        "(no heading), 2 Hz GPS whose error is urban (docs/design/urban_gps.md): a few metres "
        "in the open, street canyons (35 % of the time) with multipath bursts of 10-40 m over "
        "2-10 s and NLOS jumps of 20-80 m, bridges without fixes; the receiver states 1.5 m.",
        duration=600.0,
        trajectory=TrajectorySpec("random", speed=10.0, ramp=5.0, speed_rel_std=0.25,
                                  yaw_rate_std=0.08, corr_time=8.0),
        true_geometry=Geometry(wheel_radius=0.3075, track_width=1.58),
        nominal_geometry=Geometry(wheel_radius=0.31, track_width=1.55),
        encoders=EncoderSpec(rate=20.0, speed_std=0.15, counts_per_rev=2048),
        imu=ImuSpec(rate=50.0, use=("yaw_rate",)),
        gps=GpsSpec(rate=2.0, horizontal_std=1.5, vertical_std=3.0, delay=0.1,
                    dropout_prob=0.01, urban=UrbanGpsSpec()),
        datum=OUTDOOR_DATUM,
        truth_rate=10.0,
        geometry_std=Geometry(wheel_radius=0.003, track_width=0.03),
        # at 10 m/s a slip of 0 (floored at 1e-3 m/sqrt(s)) makes the smoother's motion factors
        # too stiff for gtsam's Cholesky (docs/design/urban_gps.md); a car's tyres slip
        config_slip=(0.05, 0.02, 0.01),
    ),
}


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
