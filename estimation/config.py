"""The ddfuse YAML config: loaded, validated, with errors that name the key and the problem.

Shape (every key documented in README.md)::

    sensors:
      odometry: [{topic: /odom, use: [v, yaw_rate], noise: {v: 0.05, yaw_rate: 0.05}}]
      imu: [{topic: /imu/data, use: [yaw, yaw_rate, accel], mount: {rpy: [r, p, y]},
             noise: {yaw: 0.05, yaw_rate: 0.02, accel: 0.1, gyro_bias_walk: 1e-4,
                     heading_offset_walk: 0.02}, heading_offset: estimate, gyro_bias: estimate}]
      gps: [{topic: /fix, noise: {horizontal: 1.5}, lever_arm: [0.0, 0.0], delay: 0.0,
             min_std: 0.5}]
      wheels: [{topic: /joint_states, joints: [left, right], noise: {speed: 0.1}}]
      landmarks: [{topic: /landmarks, map: some.landmarks.yaml, noise: {range: 0.1, bearing: 0.05}}]
      magnetometer: [{topic: /imu/mag, declination: 0.052, hard_iron: [0.0, 0.0, 0.0],
                      noise: {field: 3.0e-7}, heading_offset: 0.0}]
      local_heading: [{topic: /vo/pose, noise: {yaw: 0.02}, heading_offset: estimate}]
    robot: {wheel_radius: 0.165, track_width: 0.555, wheel_radius_std: 0.002,
            track_width_std: 0.03, slip: {longitudinal: 0.05, lateral: 0.02, heading: 0.01},
            max_accel: 0.5, max_yaw_accel: 0.5, max_speed: 1.0, max_yaw_rate: 2.0,
            twist_walk: {speed: 0.3, yaw_rate: 0.3}}
    ground_truth: {topic: /ground_truth}
    frame: {datum: first_fix, local: map, base: base_link}  # datum or [lat_deg, lon_deg, alt_m]
    initial_pose: ground_truth           # or [x, y, yaw]; default origin
    smoother: {lag: 10.0, keyframe: gps, robust: huber}
    gps: {model: default}                # or gaussian, cauchy, geman_mcclure, dcs, maxmix
    ekf: {rate: event}
    ekf_igvc: {motion: euler}            # or icc: seed 000's exact arc (appendix A)
    reorder_window: 0.5
    node: {rate: 20, tf: smoother, diagnostics_period: 1.0, topic_timeout: 2.0, nis_window: 30}

Noise values are standard deviations in SI units (m, rad, m/s, rad/s, m/s^2). An IMU's
``gyro_bias_walk`` (rad/s/sqrt(s)) and ``heading_offset_walk`` (rad/sqrt(s)) are the random-walk
densities of an estimated gyro bias and heading offset (0: constant; absent: the estimator's
default). A GPS ``delay`` (s) says that a fix describes the antenna position that many seconds
before its stamp; its ``min_std`` (m) is the smallest horizontal standard deviation a fix's stated
covariance may claim (default: by the fix's NavSatStatus, DEFAULT_GPS_MIN_STD; below it the
floor is used, counted and warned about). ``robot.wheel_radius_std`` / ``track_width_std`` (m)
are the 1-sigma uncertainties of the nominal geometry; given, the estimators that can estimate
the odometry's scale errors do. ``robot.slip`` states white-noise densities of the body's motion
about its twist: longitudinal and lateral velocity (m/sqrt(s)) and yaw rate (rad/sqrt(s)).
``robot.max_accel`` (m/s^2) and ``max_yaw_accel`` (rad/s^2) are the largest accelerations the
base performs (its drive controller's limits). ``robot.twist_walk`` states the process noise of
the twist itself, the white-acceleration densities of the random walks of the forward speed
(``speed``, m/s/sqrt(s)) and yaw rate (``yaw_rate``, rad/s/sqrt(s)) between twist samples;
absent, the estimators derive them from ``max_accel`` / ``max_yaw_accel`` and the samples'
period (or their defaults), as before the key existed; with ``speed_burst`` (m/s/sqrt(s), above
``speed``) and ``burst_share`` (its probability per speed interval, default 0.05) the speed's
walk is a heavy-tailed mixture (``ddfuse.estimation.twist_tails``). ``robot.max_speed`` (m/s) and
``max_yaw_rate`` (rad/s) are what the robot can physically do (defaults DEFAULT_MAX_SPEED,
DEFAULT_MAX_YAW_RATE); a sample beyond them is a glitch (``ddfuse.estimation.robot_limits``).
A ``gate`` on a sensor is the chi-square acceptance probability of its Mahalanobis gate (e.g.
0.9999) or ``off``.

A ``magnetometer`` (sensor_msgs/MagneticField) is a global heading: ``declination`` in rad (east
of true north positive), ``hard_iron`` in T (sensor frame), ``noise.field`` T per axis or
``noise.yaw`` rad (else the message's covariance). A ``local_heading`` (the orientation of an
Odometry, Imu or PoseStamped with no north reference) is a heading in the robot's start frame,
its ``heading_offset`` 'estimate' unless given. One orientation topic gives one heading only
(docs/design/sensors.md).
"""

from __future__ import annotations

import math
import re
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml
from ddfuse.estimation.errors import ConfigError


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader with YAML 1.2's floats: 1.1's rule wants a dot in the mantissa and a
    signed exponent, so ``1e-4`` (how noise densities are written) would load as a string."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                 |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                 |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                 |[-+]?\.(?:inf|Inf|INF)
                 |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


class _DuplicateKey(yaml.constructor.ConstructorError):
    """A mapping that gives one key twice (``key``, as loaded; ``node``: the mapping)."""

    def __init__(self, key: Any, node: yaml.MappingNode, first: yaml.Mark, again: yaml.Mark):
        super().__init__(None, None, f"key {key!r} given twice (lines {first.line + 1} and "
                                     f"{again.line + 1})", again)
        self.key, self.node, self.lines = key, node, (first.line + 1, again.line + 1)


class _UniqueKeyLoader(_Loader):
    """``_Loader`` that refuses a mapping key given twice (PyYAML keeps the last silently):
    raises ``_DuplicateKey``. Keys are compared as loaded, so ``1`` and ``0x1`` collide,
    ``1`` and ``"1"`` do not."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            self.flatten_mapping(node)
            seen: dict = {}
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.setdefault(key, key_node.start_mark)
                except TypeError:  # an unhashable key: the base class says so
                    break
                if first is not key_node.start_mark:
                    raise _DuplicateKey(key, node, first, key_node.start_mark)
        return super().construct_mapping(node, deep=deep)


SENSOR_KINDS = ("odometry", "imu", "gps", "wheels", "landmarks", "magnetometer",
                "local_heading")
USES = {
    "odometry": ("v", "yaw_rate"),
    "imu": ("yaw", "yaw_rate", "accel"),
    "gps": ("position",),
    "wheels": ("speeds",),
    "landmarks": ("range", "bearing"),
    "magnetometer": ("yaw",),
    "local_heading": ("yaw",),
}
NOISE_KEYS = {
    "odometry": ("v", "yaw_rate"),
    "imu": ("yaw", "yaw_rate", "accel", "gyro_bias_walk", "heading_offset_walk"),
    "gps": ("horizontal", "vertical"),
    "wheels": ("speed",),
    # bearing_common: rad, the part of the bearing error common to a frame's sightings
    # (ddfuse.estimation.landmark_frames); 0 or absent: independent bearings
    "landmarks": ("range", "bearing", "bearing_common"),
    # field: T per axis (the heading's variance follows from the horizontal field); yaw: rad,
    # stated directly instead
    "magnetometer": ("field", "yaw", "heading_offset_walk"),
    "local_heading": ("yaw", "heading_offset_walk"),
}
# the sensor kinds whose messages become Heading measurements (with ``yaw`` in their use)
HEADING_KINDS = ("imu", "magnetometer", "local_heading")
WALK_KEYS = ("gyro_bias_walk", "heading_offset_walk")  # noise keys that may be 0 (constant)
ZERO_OK_KEYS = (*WALK_KEYS, "bearing_common")  # noise keys that may be 0
DEFAULT_GATE = 0.9999
MAX_GPS_DELAY = 5.0  # s: a GPS sensor's delay beyond this is refused (``_sensor``)
# m/s^2 and rad/s^2: robot.max_accel / max_yaw_accel beyond this are refused (1e9 broke the
# unicycle EKF's covariance; 1e4 still ran; the seed002-blog simulation's steps state ~480)
MAX_ROBOT_ACCEL = 1e5
# m: robot.wheel_radius / track_width beyond these are refused, the mistake they catch being
# millimetres (a 165 mm wheel written 165); the largest haul trucks' are about 2 m and 10 m
MAX_GEOMETRY_M = {"wheel_radius": 5.0, "track_width": 20.0}
# the process noises' largest values (robot.slip m/sqrt(s) or rad/sqrt(s); robot.twist_walk
# m/s/sqrt(s) or rad/s/sqrt(s)); beyond them a value is refused: a twist walk of 1000 took the
# unicycle EKF's ATE on the sample bag from 0.12 to 3.3 m with its NEES passing, a slip of 100
# made the smoother's system indeterminate (config fuzzing, session 31). Tuned values stay
# within them (``evaluation.tune``)
MAX_PROCESS_NOISE = {"robot.slip": 10.0, "robot.twist_walk": 100.0}
# the GPS antenna's offset from the base frame, m per axis
MAX_LEVER_ARM_M = 100.0


def process_noise_max(key: str) -> float | None:
    """The largest value config key ``key`` (``robot.slip.heading``, ...) may have, or None."""
    return MAX_PROCESS_NOISE.get(key.rpartition(".")[0])
# Gate lock-out rule shared by the EKFs (ekf_baseline.kalman) and the smoother's GPS gate: this
# many consecutive rejections of one sensor spanning at least this long mean the estimate, not
# the sensor, is wrong.
DEFAULT_LOCKOUT_COUNT = 5
DEFAULT_LOCKOUT_TIME = 1.0  # s

# Standard deviations (m, rad) of a given initial pose -- the config's initial_pose, or the first
# ground-truth pose with initial_pose: ground_truth -- for every estimator alike: position and
# heading are taken as known to 1 cm and 5 mrad. A wrong start is caught by the gate's lock-out
# recovery, not by a wide initial covariance.
GIVEN_POSE_STD = (0.01, 0.005)
# The robot's physical limits when the config states none: above any wheeled ground robot's
# (a car on a motorway, a skid-steer base spinning in place), so only glitches exceed them.
DEFAULT_MAX_SPEED = 50.0  # m/s
DEFAULT_MAX_YAW_RATE = 10.0  # rad/s
# The best horizontal standard deviation a fix of each NavSatStatus can have (m): a stated
# covariance below it is a driver's placeholder, not a claim to fuse. Ground-based augmentation
# (RTK) reaches about 1 cm, satellite-based (SBAS) tens of cm, an unaugmented fix (FIX, and
# NO_FIX, which is rejected anyway) no better than half a metre: docs/design/plausibility.md
DEFAULT_GPS_MIN_STD = {-1: 0.5, 0: 0.5, 1: 0.3, 2: 0.01}  # status -> m


@dataclass
class SensorConfig:
    """One configured sensor: where it comes from and how to use it."""

    kind: str  # one of SENSOR_KINDS
    topic: str
    name: str  # unique label used in reports; defaults to the topic
    use: tuple[str, ...]
    noise: dict[str, float] = field(default_factory=dict)  # std devs, SI
    mount_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rad, base_link -> sensor
    heading_offset: str | float = 0.0  # 'estimate' or rad (sensor yaw = ENU yaw + offset)
    gyro_bias: str | float = 0.0  # 'estimate' or rad/s
    # IMU accel: 'orientation' removes gravity along body x with the message's own orientation
    # (tilt); 'level' takes the specific force as the acceleration (flat ground, seed 000 eq. 19)
    accel_gravity: str = "orientation"
    lever_arm: tuple[float, float] = (0.0, 0.0)  # m, body frame
    delay: float = 0.0  # s, GPS: a fix is the position this long before its stamp
    # s, GPS: the correlation time of the fixes' errors (first-order Gauss-Markov); 0 = white.
    # Each fix is fused with its covariance inflated by ddfuse.estimation.gps_correlation.inflation
    # (landmarks: of one landmark's sightings, ddfuse.estimation.landmark_correlation; a heading
    # sensor's: of its yaw samples, ddfuse.estimation.heading_correlation)
    correlation_time: float = 0.0
    # m, GPS: the smallest horizontal standard deviation a fix's stated covariance may claim;
    # below it the floor is used (None: DEFAULT_GPS_MIN_STD by the fix's status; the converter
    # counts and warns)
    min_std: float | None = None
    joints: tuple[str, str] | None = None  # JointState names of left and right wheel
    map: Path | None = None  # landmark map YAML
    map_name: Path | None = None  # the map path as the config gives it
    gate: float | None = DEFAULT_GATE  # chi-square acceptance probability, None = off
    # odometry: the name of the IMU sensor whose orientation gives the climb angle, by which
    # the forward speed is projected onto the horizontal plane (None: taken as horizontal)
    slope: str | None = None
    # magnetometer: the declination, rad, east of true north positive (magnetic north lies
    # this far clockwise of true north), and the hard-iron offset (x, y, z), T, in the sensor
    # frame: subtracted from each reading (ddfuse.estimation.magnetometer)
    declination: float = 0.0
    hard_iron: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass
class SmootherConfig:
    lag: float = 10.0  # s
    keyframe: str = "gps"  # 'gps' (at GPS fixes, preintegrated odometry between) or 'rate'
    keyframe_rate: float = 2.0  # Hz, for keyframe 'rate' and as the upper gap without GPS
    robust: str = "huber"  # 'huber', 'cauchy' or 'none' (GPS factors)
    # threshold on the whitened residual norm; None: the sensor's chi-square gate radius. For a
    # GPS fix inflated by its correlation_time (factor f) it is divided by sqrt(f): the same
    # residual in metres as without the inflation
    robust_k: float | None = None


# the GPS error models of the top-level ``gps`` key (GpsModelConfig; docs/design/urban_gps.md)
GPS_MODELS = ("default", "gaussian", "cauchy", "geman_mcclure", "dcs", "maxmix")
GATING_GPS_MODELS = ("default", "gaussian")  # the rest replace the gate (GpsModelConfig.robust)


@dataclass
class GpsModelConfig:
    """``gps: {model: ..., ...}``: how the smoother and the batch model a GPS fix's error
    (docs/design/urban_gps.md says when to use which), and the EKFs under a robust model
    (every model but 'default' and 'gaussian': ekf_baseline/gps_robust.py). 'default':
    today's, the fix's stated covariance under ``smoother.robust``'s kernel behind the chi-square
    gate; 'gaussian': the
    same without a kernel; 'cauchy', 'geman_mcclure', 'dcs': that M-estimator, and 'maxmix':
    an inlier/outlier max-mixture factor, each instead of the gate, with the stated covariance
    scaled by a factor learned from the fixes' innovations (``scale_window`` s of them)."""

    model: str = "default"
    scale_window: float = 60.0  # s of innovations the scale is learned from; 0: stated as is
    # the kernel's constant on the whitened residual norm (None: the model's default,
    # estimation.smoother.gps_models.KERNEL_K)
    k: float | None = None
    outlier_std: float = 30.0  # m per axis: maxmix's outlier component, added to the inlier's
    outlier_weight: float = 0.1  # maxmix: prior probability of an outlier
    # the EKFs under a robust model (ekf_baseline/gps_robust.py): the sliding window of the
    # chi-square test that declares the GPS faulty (s), and how long it may stay faulty
    # before the filter takes itself for lost (s, doubling while that recurs)
    fault_window: float = 5.0
    fault_hold: float = 30.0

    @property
    def robust(self) -> bool:
        """True for the models that replace the gate."""
        return self.model not in GATING_GPS_MODELS


@dataclass
class EkfConfig:
    rate: str | float = "event"  # 'event' (update per message) or a fixed rate in Hz


@dataclass
class IgvcConfig:
    """``ekf_igvc``: seed 000's 11-state EKF (ekf_baseline/igvc.py)."""

    motion: str = "euler"  # 'euler' (seed eq. 14) or 'icc' (the appendix's exact arc)


@dataclass
class NodeConfig:
    """``ddfuse node``'s publishing (evaluation/node.py)."""

    rate: float = 20.0  # Hz of the receive clock: each estimator's estimate published
    # the estimator whose pose is broadcast as the TF local -> base; None: the smoother when
    # it runs, else the first; 'none': no TF
    tf: str | None = None
    diagnostics_period: float = 1.0  # s between /diagnostics messages
    topic_timeout: float = 2.0  # s of silence after which a configured topic is stale
    nis_window: float = 30.0  # s of stamps the diagnostics' NIS verdict is taken over


# robot.twist_walk's keys: the forward speed's and the yaw rate's random-walk densities, and
# the heavy-tailed speed walk's burst density and share (estimation.twist_tails)
TWIST_WALK_KEYS = ("speed", "yaw_rate", "speed_burst", "burst_share")


@dataclass
class RobotConfig:
    wheel_radius: float | None = None  # m
    track_width: float | None = None  # m
    wheel_radius_std: float | None = None  # m, 1-sigma uncertainty of wheel_radius
    track_width_std: float | None = None  # m, 1-sigma uncertainty of track_width
    # how far the body's motion departs from its twist (wheel slip, terrain), white-noise
    # densities: 'longitudinal' and 'lateral' body velocity (m/sqrt(s)), 'heading' (yaw rate,
    # rad/sqrt(s)); a key absent: the estimator's default
    slip: dict[str, float] = field(default_factory=dict)
    # the largest forward (m/s^2) and yaw (rad/s^2) acceleration the base performs (a drive
    # controller's acceleration limits); given, the unicycle EKF derives its twist random-walk
    # densities from them and its twist sensors' sample periods
    max_accel: float | None = None
    max_yaw_accel: float | None = None
    # the twist's own process noise: white-acceleration densities of the random walks of the
    # forward speed ('speed', m/s/sqrt(s)) and yaw rate ('yaw_rate', rad/s/sqrt(s)); a key
    # absent: derived from max_accel / max_yaw_accel and the samples' period, else the
    # estimator's default. The glitch screen's limits stay max_accel / max_yaw_accel.
    twist_walk: dict[str, float] = field(default_factory=dict)
    # what the robot can physically do: the largest forward speed (m/s, either direction) and
    # yaw rate (rad/s). A twist sample beyond them is a glitch, rejected before any estimator
    # (None: DEFAULT_MAX_SPEED / DEFAULT_MAX_YAW_RATE, generous for any wheeled ground robot)
    max_speed: float | None = None
    max_yaw_rate: float | None = None

    @property
    def speed_limit(self) -> float:
        """The robot's top speed, m/s: the config's ``max_speed`` or DEFAULT_MAX_SPEED."""
        return DEFAULT_MAX_SPEED if self.max_speed is None else self.max_speed

    @property
    def yaw_rate_limit(self) -> float:
        """The robot's top yaw rate, rad/s: the config's ``max_yaw_rate`` or
        DEFAULT_MAX_YAW_RATE."""
        return DEFAULT_MAX_YAW_RATE if self.max_yaw_rate is None else self.max_yaw_rate

    @property
    def scale_std(self) -> tuple[float, float, float] | None:
        """Relative 1-sigma uncertainties of the odometry's speed and yaw-rate scale and their
        covariance, (sd_v, sd_w, cov_vw), from the geometry's: speed ~ r, yaw rate ~ r / L, so
        to first order d(ln v) = d(ln r) and d(ln w) = d(ln r) - d(ln L). None when the config
        gives no geometry uncertainty."""
        if self.wheel_radius_std is None and self.track_width_std is None:
            return None
        sr = self.wheel_radius_std / self.wheel_radius if self.wheel_radius_std else 0.0
        sl = self.track_width_std / self.track_width if self.track_width_std else 0.0
        return sr, math.sqrt(sr * sr + sl * sl), sr * sr


@dataclass
class Config:
    sensors: list[SensorConfig]
    robot: RobotConfig = field(default_factory=RobotConfig)
    ground_truth_topic: str | None = None
    datum: str | tuple[float, float, float] = "first_fix"
    # REP-105 frame names of the estimates sent out (ROS messages, estimates.mcap, live view):
    # the local ENU frame the poses are in, and the robot's base frame
    local_frame: str = "map"
    base_frame: str = "base_link"
    initial_pose: str | tuple[float, float, float] | None = None
    smoother: SmootherConfig = field(default_factory=SmootherConfig)
    gps: GpsModelConfig = field(default_factory=GpsModelConfig)
    ekf: EkfConfig = field(default_factory=EkfConfig)
    ekf_igvc: IgvcConfig = field(default_factory=IgvcConfig)
    reorder_window: float = 0.5  # s: messages older than this behind the newest are an error
    node: NodeConfig = field(default_factory=NodeConfig)
    path: Path | None = None  # the file, or the label the config was parsed under
    text: str | None = None  # the YAML it was parsed from (load_config, parse_config_text)

    def of_kind(self, kind: str) -> list[SensorConfig]:
        return [s for s in self.sensors if s.kind == kind]

    def heading_sensors(self) -> list[SensorConfig]:
        """The sensors that give Heading measurements, in config order: IMUs using ``yaw``
        (orientation, global heading), magnetometers (global heading, Theta_g) and local
        headings (Theta_l)."""
        return [s for s in self.sensors if s.kind in HEADING_KINDS and "yaw" in s.use]

    def sensor(self, name: str) -> SensorConfig:
        for s in self.sensors:
            if s.name == name:
                return s
        raise KeyError(name)

    @property
    def topics(self) -> list[str]:
        t = [s.topic for s in self.sensors]
        if self.ground_truth_topic:
            t.append(self.ground_truth_topic)
        return t


class _Checker:
    """Validates one YAML tree, building error messages that carry the key path."""

    def __init__(self, source: str):
        self.source = source

    def fail(self, key: str, problem: str) -> ConfigError:
        return ConfigError(f"{self.source}: {key}: {problem}")

    def mapping(self, value: Any, key: str, allowed: tuple[str, ...]) -> dict:
        if not isinstance(value, dict):
            raise self.fail(key, f"must be a mapping, got {type(value).__name__}")
        # sorted by text: YAML keys may be of mixed types (an unquoted on/off is a bool)
        unknown = sorted(set(value) - set(allowed), key=str)
        if unknown:
            bad = unknown[0]
            why = (" (YAML reads an unquoted on/off/yes/no as a boolean; quote it)"
                   if isinstance(bad, bool) else "")
            raise self.fail(
                f"{key}.{bad}" if key else str(bad),
                f"unknown key{why} (allowed: {', '.join(allowed)})",
            )
        return value

    def number(self, value: Any, key: str, positive: bool = False, nonneg: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(key, f"must be a number, got {value!r}")
        try:
            v = float(value)
        except OverflowError:  # an integer beyond any float
            raise self.fail(key, f"must be finite, got an integer of {len(str(value))} "
                                 "digits") from None
        if not math.isfinite(v):
            raise self.fail(key, f"must be finite, got {value!r}")
        if positive and v <= 0:
            raise self.fail(key, f"must be > 0, got {value!r}")
        if nonneg and v < 0:
            raise self.fail(key, f"must be >= 0, got {value!r}")
        return v

    def vector(self, value: Any, key: str, n: int) -> tuple[float, ...]:
        if not isinstance(value, (list, tuple)) or len(value) != n:
            raise self.fail(key, f"must be a list of {n} numbers, got {value!r}")
        return tuple(self.number(v, f"{key}[{i}]") for i, v in enumerate(value))

    def string(self, value: Any, key: str) -> str:
        if not isinstance(value, str) or not value:
            raise self.fail(key, f"must be a non-empty string, got {value!r}")
        return value

    def choice(self, value: Any, key: str, options: tuple[str, ...]) -> str:
        if value not in options:
            raise self.fail(key, f"must be one of {', '.join(options)}; got {value!r}")
        return value

    def estimate_or_number(self, value: Any, key: str) -> str | float:
        if value == "estimate":
            return "estimate"
        if isinstance(value, str):
            raise self.fail(key, f"must be 'estimate' or a number, got {value!r}")
        return self.number(value, key)


def _std(ck: _Checker, value: Any, key: str, walk: bool = False) -> float:
    """A noise standard deviation (a random walk's may be 0) whose square, the variance the
    estimators use, is a normal float: 1e-200 squares to 0, 1e200 to inf."""
    v = ck.number(value, key, positive=not walk, nonneg=True)
    var = v * v
    if not math.isfinite(var) or (var < sys.float_info.min and not (walk and v == 0.0)):
        raise ck.fail(key, f"{value!r} squared is {var:g} as a float: not a usable variance")
    return v


def _sensor(ck: _Checker, kind: str, i: int, raw: Any, base: Path) -> SensorConfig:
    key = f"sensors.{kind}[{i}]"
    allowed = ("topic", "name", "use", "noise", "gate")
    allowed += {
        "imu": ("mount", "heading_offset", "gyro_bias", "accel_gravity", "correlation_time"),
        "gps": ("lever_arm", "delay", "correlation_time", "min_std"),
        "wheels": ("joints",),
        "landmarks": ("map", "correlation_time"),
        "odometry": ("mount", "slope"),
        "magnetometer": ("mount", "heading_offset", "declination", "hard_iron",
                         "correlation_time"),
        "local_heading": ("mount", "heading_offset", "correlation_time"),
    }.get(kind, ())
    d = ck.mapping(raw, key, allowed)
    if "topic" not in d:
        raise ck.fail(f"{key}.topic", "missing (every sensor needs the topic it is read from)")
    topic = ck.string(d["topic"], f"{key}.topic")
    use = d.get("use", list(USES[kind]))
    if isinstance(use, str):
        use = [use]
    if not isinstance(use, list) or not use:
        raise ck.fail(f"{key}.use", f"must be a non-empty list from {list(USES[kind])}")
    for u in use:
        if u not in USES[kind]:
            raise ck.fail(f"{key}.use", f"{u!r} is not one of {list(USES[kind])}")
    noise_raw = d.get("noise")
    if noise_raw is None:
        noise_raw = {}
    ck.mapping(noise_raw, f"{key}.noise", NOISE_KEYS[kind])  # noise: 0 or [] is no mapping
    noise = {k: _std(ck, v, f"{key}.noise.{k}", walk=k in ZERO_OK_KEYS)
             for k, v in noise_raw.items()}
    if noise.get("bearing_common") and "bearing" not in use:
        raise ck.fail(f"{key}.noise.bearing_common", "needs 'bearing' in use: it is the "
                      "bearing error common to a frame's sightings")
    if "vertical" in noise and "horizontal" not in noise:
        raise ck.fail(f"{key}.noise.vertical", "needs noise.horizontal: without it the fix's own "
                      "covariance is used, vertical included")
    s = SensorConfig(kind=kind, topic=topic, name=topic, use=tuple(use), noise=noise)
    if "name" in d:
        s.name = ck.string(d["name"], f"{key}.name")
    gate = d.get("gate", DEFAULT_GATE)
    if gate is None or gate is False or gate == "off":
        s.gate = None
    else:
        g = ck.number(gate, f"{key}.gate")
        if not 0.0 < g < 1.0:
            raise ck.fail(f"{key}.gate", f"must be a probability in (0, 1) or 'off', got {gate!r}")
        s.gate = g
    if "mount" in d:
        m = ck.mapping(d["mount"], f"{key}.mount", ("rpy",))
        s.mount_rpy = ck.vector(m.get("rpy", [0, 0, 0]), f"{key}.mount.rpy", 3)
        for i, a in enumerate(s.mount_rpy):  # 90 for a y-up IMU: degrees
            _radians(ck, f"{key}.mount.rpy[{i}]", a, "rpy is")
    if "slope" in d and d["slope"] is not None:
        s.slope = ck.string(d["slope"], f"{key}.slope")  # checked against the IMUs below
    if "heading_offset" in d:
        s.heading_offset = ck.estimate_or_number(d["heading_offset"], f"{key}.heading_offset")
        if s.heading_offset != "estimate":
            _radians(ck, f"{key}.heading_offset", float(s.heading_offset), "the offset is")
    elif kind == "local_heading":
        # a heading in the robot's start frame: its offset to ENU is the start's unknown yaw
        s.heading_offset = "estimate"
    if kind == "magnetometer":
        _magnetometer(ck, key, d, s)
    if "gyro_bias" in d:
        s.gyro_bias = ck.estimate_or_number(d["gyro_bias"], f"{key}.gyro_bias")
    if "accel_gravity" in d:
        s.accel_gravity = ck.choice(d["accel_gravity"], f"{key}.accel_gravity",
                                    ("orientation", "level"))
    if "lever_arm" in d:
        s.lever_arm = ck.vector(d["lever_arm"], f"{key}.lever_arm", 2)
        if max(abs(x) for x in s.lever_arm) > MAX_LEVER_ARM_M:
            raise ck.fail(f"{key}.lever_arm", f"must be within {MAX_LEVER_ARM_M:g} m of the base "
                          f"frame on each axis, got {list(s.lever_arm)}: the antenna's offset "
                          "in metres")
    if "delay" in d:
        s.delay = ck.number(d["delay"], f"{key}.delay", nonneg=True)
        if s.delay > MAX_GPS_DELAY:
            raise ck.fail(f"{key}.delay", f"must be at most {MAX_GPS_DELAY:g} s, got "
                          f"{d['delay']!r}: every estimator carries a fix back to the time it "
                          "describes along the robot's twist at its stamp, which over longer is "
                          "a guess (a receiver's latency is 0.05-0.5 s; the value is in "
                          "seconds, not milliseconds)")
    if "correlation_time" in d:
        s.correlation_time = ck.number(d["correlation_time"], f"{key}.correlation_time",
                                       nonneg=True)
    if "min_std" in d:
        s.min_std = ck.number(d["min_std"], f"{key}.min_std", positive=True)
    if kind == "wheels":
        j = d.get("joints")
        if not isinstance(j, list) or len(j) != 2 or not all(isinstance(x, str) for x in j):
            raise ck.fail(f"{key}.joints", "must list the left and right wheel joint names")
        if j[0] == j[1]:
            raise ck.fail(f"{key}.joints", f"names joint {j[0]!r} twice; give the left and the "
                          "right wheel's")
        s.joints = (j[0], j[1])
        if "speed" not in s.noise:
            raise ck.fail(f"{key}.noise.speed", "missing (JointState carries no covariance)")
    if kind == "landmarks":
        if "map" not in d:
            raise ck.fail(f"{key}.map", "missing (a landmark map YAML is needed)")
        p = Path(ck.string(d["map"], f"{key}.map"))
        s.map_name = p
        s.map = p if p.is_absolute() else base / p
        if p.is_absolute() and not s.map.is_file():
            raise ck.fail(f"{key}.map", f"file not found: {s.map}")
        # a relative one may sit next to the bag instead (resolve_landmark_maps)
    return s


def _magnetometer(ck: _Checker, key: str, d: dict, s: SensorConfig) -> None:
    """A magnetometer's declination (rad) and hard-iron offset (T) into ``s``."""
    if "declination" in d:
        s.declination = ck.number(d["declination"], f"{key}.declination")
        if abs(s.declination) > math.pi:
            raise ck.fail(f"{key}.declination", f"{s.declination:g} is beyond pi: the "
                          f"declination is in radians ({s.declination:g} deg would be "
                          f"{math.radians(s.declination):.4f})")
    if "hard_iron" in d:
        s.hard_iron = ck.vector(d["hard_iron"], f"{key}.hard_iron", 3)
        if any(abs(v) > 1e-3 for v in s.hard_iron):
            raise ck.fail(f"{key}.hard_iron", f"{list(s.hard_iron)} is beyond 1 mT: the offset "
                          "is in tesla, as sensor_msgs/MagneticField (the earth's field is "
                          "25-65 uT; 30 uT is 3e-5)")


def _one_heading_per_reading(ck: _Checker, cfg: Config) -> None:
    """Refuse two heading rows from one orientation topic (an IMU's yaw as the global heading
    Theta_g and again as a local heading Theta_l): one reading fused twice with independent
    errors counts it twice (errata 000 #40, docs/design/sensors.md). Likewise an odometry's
    pose yaw as a local heading beside the same odometry's yaw rate: the pose is the twist
    integrated."""
    seen: dict[str, str] = {}
    for s in cfg.of_kind("local_heading"):
        twist = next((o for o in cfg.of_kind("odometry")
                      if o.topic == s.topic and "yaw_rate" in o.use), None)
        if twist is not None:
            raise ck.fail("sensors.local_heading", (
                f"{s.topic}'s pose yaw is the integral of the yaw rate {twist.name!r} already "
                "fuses: its errors are that twist's, summed, not independent of it; use the "
                f"odometry's yaw_rate or its pose as a local heading, not both "
                "(docs/design/sensors.md)"))
    for s in cfg.heading_sensors():
        other = seen.setdefault(s.topic, s.name)
        if other != s.name:
            raise ck.fail(f"sensors.{s.kind}", (
                f"{s.topic} gives a heading to {other!r} and again to {s.name!r}: one reading "
                "would be fused twice as if its errors were independent (seed 000's Theta_g and "
                "Theta_l from one sensor, errata 000 #40); configure it once"))


def parse_config(raw: Any, source: str = "<config>", base: Path | None = None) -> Config:
    """Validate a YAML tree (as loaded) into a Config. Relative paths resolve against ``base``."""
    ck = _Checker(source)
    base = base or Path.cwd()
    top = (
        "sensors", "robot", "ground_truth", "frame", "initial_pose", "smoother", "ekf",
        "ekf_igvc", "reorder_window", "node", "gps",
    )
    d = ck.mapping(raw if raw is not None else {}, "", top)
    sensors_raw = ck.mapping(d.get("sensors") or {}, "sensors", SENSOR_KINDS)
    sensors: list[SensorConfig] = []
    for kind, lst in sensors_raw.items():
        if isinstance(lst, dict):
            lst = [lst]
        if not isinstance(lst, list):
            raise ck.fail(f"sensors.{kind}", "must be a list of sensors")
        sensors += [_sensor(ck, kind, i, item, base) for i, item in enumerate(lst)]
    if not sensors:
        raise ck.fail("sensors", "no sensor configured (need at least one)")
    names = [s.name for s in sensors]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ck.fail("sensors", f"sensor name {sorted(dup)[0]!r} used twice; give each a 'name'")
    cfg = Config(sensors=sensors, path=Path(source) if source != "<config>" else None)
    _one_heading_per_reading(ck, cfg)
    for kind in ("odometry",):
        for i, s in enumerate(cfg.of_kind(kind)):
            if s.slope is None:
                continue
            imus = cfg.of_kind("imu")
            imu = next((m for m in imus if s.slope in (m.name, m.topic)), None)
            if imu is None:
                raise ck.fail(f"sensors.{kind}[{i}].slope", (
                    f"no imu sensor named {s.slope!r} (imu sensors: "
                    f"{', '.join(m.name for m in imus) or 'none'}): slope names the IMU whose "
                    "orientation gives the climb angle"))
            s.slope = imu.name

    if "robot" in d:
        r = ck.mapping(d["robot"], "robot", ("wheel_radius", "track_width", "wheel_radius_std",
                                             "track_width_std", "slip", "max_accel",
                                             "max_yaw_accel", "max_speed", "max_yaw_rate",
                                             "twist_walk"))
        for k in ("max_speed", "max_yaw_rate"):
            if k in r and ck.number(r[k], f"robot.{k}") <= 0.0:
                raise ck.fail(f"robot.{k}", "must be > 0: a sample beyond it is rejected as "
                              "impossible for the robot (leave it out for the default)")
        for k in ("max_accel", "max_yaw_accel"):
            v = ck.number(r[k], f"robot.{k}") if k in r else None
            if v == 0.0:
                raise ck.fail(f"robot.{k}", "must be > 0: the twist's process noise is derived "
                              "from it, and 0 would hold the twist fixed (leave it out for the "
                              "estimators' default)")
            if v is not None and v > MAX_ROBOT_ACCEL:
                unit = "m/s^2" if k == "max_accel" else "rad/s^2"
                raise ck.fail(f"robot.{k}", f"must be at most {MAX_ROBOT_ACCEL:g} {unit}, got "
                              f"{r[k]!r}: the twist's process noise is derived from it (a "
                              "ground robot's is a few; leave it out for the estimators' "
                              "default)")
        cfg.robot = RobotConfig(**{
            k: ck.number(r[k], f"robot.{k}", positive=k in ("wheel_radius", "track_width"),
                         nonneg=True)
            for k in r if k not in ("slip", "twist_walk")})
        if "twist_walk" in r:
            tw = ck.mapping(r["twist_walk"], "robot.twist_walk", TWIST_WALK_KEYS)
            cfg.robot.twist_walk = {k: ck.number(v, f"robot.twist_walk.{k}") for k, v in
                                    tw.items()}
            for k, v in cfg.robot.twist_walk.items():
                if v <= 0.0:
                    raise ck.fail(f"robot.twist_walk.{k}", f"must be > 0, got {v:g}: it is the "
                                  "density of the twist's random walk, and 0 would hold the "
                                  "twist fixed (leave it out for the estimators' default)")
                _at_most(ck, f"robot.twist_walk.{k}", v)
            _check_speed_tails(ck, cfg.robot.twist_walk)
        if "slip" in r:
            slip = ck.mapping(r["slip"], "robot.slip", ("longitudinal", "lateral", "heading"))
            cfg.robot.slip = {k: ck.number(v, f"robot.slip.{k}", nonneg=True)
                              for k, v in slip.items()}
            for k, v in cfg.robot.slip.items():
                _at_most(ck, f"robot.slip.{k}", v)
        for k in ("wheel_radius", "track_width"):
            if f"{k}_std" in r and k not in r:
                raise ck.fail(f"robot.{k}_std", f"needs robot.{k} (the nominal value)")
            v = getattr(cfg.robot, k)
            if v is not None and v > MAX_GEOMETRY_M[k]:
                raise ck.fail(f"robot.{k}", f"must be at most {MAX_GEOMETRY_M[k]:g} m, got "
                              f"{r[k]!r}: it is in metres ({v:g} mm is {v / 1000:g} m)")
            sd = getattr(cfg.robot, f"{k}_std")
            if v is not None and sd is not None and sd > v:
                raise ck.fail(f"robot.{k}_std", f"must be at most robot.{k} ({v:g} m), got "
                              f"{sd:g}: the 1-sigma uncertainty of that nominal value (the "
                              "odometry's scale error it gives is estimated; over 100 % the "
                              "scale could change sign)")
    if cfg.of_kind("wheels") and (cfg.robot.wheel_radius is None or cfg.robot.track_width is None):
        raise ck.fail("robot", "wheel speed sensors need robot.wheel_radius and robot.track_width")
    if d.get("ground_truth") is not None:
        g = ck.mapping(d["ground_truth"], "ground_truth", ("topic",))
        cfg.ground_truth_topic = ck.string(g.get("topic"), "ground_truth.topic")
    if "frame" in d:
        f = ck.mapping(d["frame"], "frame", ("datum", "local", "base"))
        for key, attr in (("local", "local_frame"), ("base", "base_frame")):
            if key in f:
                name = ck.string(f[key], f"frame.{key}")
                if not name or name.startswith("/") or any(c.isspace() for c in name):
                    raise ck.fail(f"frame.{key}", f"a tf2 frame id has no leading '/' and no "
                                  f"spaces, got {name!r}")
                setattr(cfg, attr, name)
        if cfg.local_frame == cfg.base_frame:
            raise ck.fail("frame", f"local and base name the same frame {cfg.local_frame!r}")
        datum = f.get("datum", "first_fix")
        if datum == "first_fix":
            cfg.datum = "first_fix"
        else:
            lat, lon, alt = ck.vector(datum, "frame.datum", 3)
            if not (-90 <= lat <= 90 and -180 <= lon <= 180):
                raise ck.fail("frame.datum", f"latitude/longitude out of range: {datum!r}")
            cfg.datum = (lat, lon, alt)
    if d.get("initial_pose") is not None:
        ip = d["initial_pose"]
        if ip == "ground_truth":
            if not cfg.ground_truth_topic:
                raise ck.fail("initial_pose", "'ground_truth' needs a ground_truth.topic")
            cfg.initial_pose = "ground_truth"
        elif isinstance(ip, str):
            raise ck.fail("initial_pose", f"must be 'ground_truth' or [x, y, yaw], got {ip!r}")
        else:
            cfg.initial_pose = ck.vector(ip, "initial_pose", 3)
            _radians(ck, "initial_pose[2]", cfg.initial_pose[2], "the yaw is")
    if "smoother" in d:
        s = ck.mapping(d["smoother"], "smoother", ("lag", "keyframe", "keyframe_rate", "robust",
                                                    "robust_k"))
        sc = SmootherConfig()
        if "lag" in s:
            sc.lag = ck.number(s["lag"], "smoother.lag", positive=True)
        if "keyframe" in s:
            sc.keyframe = ck.choice(s["keyframe"], "smoother.keyframe", ("gps", "rate"))
        if "keyframe_rate" in s:
            sc.keyframe_rate = ck.number(s["keyframe_rate"], "smoother.keyframe_rate",
                                         positive=True)
        if "robust" in s:
            sc.robust = ck.choice(s["robust"], "smoother.robust", ("huber", "cauchy", "none"))
        if s.get("robust_k") is not None:
            sc.robust_k = ck.number(s["robust_k"], "smoother.robust_k", positive=True)
        cfg.smoother = sc
    if "gps" in d:
        cfg.gps = _gps_model(ck, d["gps"])
    if "ekf" in d:
        e = ck.mapping(d["ekf"], "ekf", ("rate",))
        rate = e.get("rate", "event")
        cfg.ekf = EkfConfig(rate="event" if rate == "event"
                            else ck.number(rate, "ekf.rate", positive=True))
    if "ekf_igvc" in d:
        g = ck.mapping(d["ekf_igvc"] or {}, "ekf_igvc", ("motion",))
        if "motion" in g:
            cfg.ekf_igvc = IgvcConfig(motion=ck.choice(g["motion"], "ekf_igvc.motion",
                                                       ("euler", "icc")))
    if "reorder_window" in d:
        cfg.reorder_window = ck.number(d["reorder_window"], "reorder_window", nonneg=True)
    if "node" in d:
        cfg.node = _node(ck, d["node"])
    return cfg


def _gps_model(ck: _Checker, raw: Any) -> GpsModelConfig:
    g = ck.mapping(raw if raw is not None else {}, "gps",
                   ("model", "scale_window", "k", "outlier_std", "outlier_weight",
                    "fault_window", "fault_hold"))
    gm = GpsModelConfig()
    if "model" in g:
        gm.model = ck.choice(g["model"], "gps.model", GPS_MODELS)
    if "scale_window" in g:
        gm.scale_window = ck.number(g["scale_window"], "gps.scale_window", nonneg=True)
    if g.get("k") is not None:
        gm.k = ck.number(g["k"], "gps.k", positive=True)
    if "outlier_std" in g:
        gm.outlier_std = ck.number(g["outlier_std"], "gps.outlier_std", positive=True)
    for key in ("fault_window", "fault_hold"):
        if key in g:
            setattr(gm, key, ck.number(g[key], f"gps.{key}", positive=True))
    if "outlier_weight" in g:
        w = ck.number(g["outlier_weight"], "gps.outlier_weight")
        if not 0.0 < w < 1.0:
            raise ck.fail("gps.outlier_weight", f"must be a probability in (0, 1), got {w!r}")
        gm.outlier_weight = w
    return gm


def _node(ck: _Checker, raw: Any) -> NodeConfig:
    n = ck.mapping(raw, "node", ("rate", "tf", "diagnostics_period", "topic_timeout",
                                 "nis_window"))
    nc = NodeConfig(**{k: ck.number(n[k], f"node.{k}", positive=True) for k in n if k != "tf"})
    if n.get("tf") is not None:
        nc.tf = ck.string(n["tf"], "node.tf")
    return nc


def _radians(ck: _Checker, key: str, a: float, what: str) -> None:
    """ConfigError where angle ``a`` at ``key`` is beyond 2 pi: given in degrees (90 ran as
    90 rad, 116.6 deg after wrapping: an initial_pose yaw of 90 left the batch 2.2 m off on the
    sample bag, the filters' NEES near 500)."""
    if abs(a) > 2.0 * math.pi:
        raise ck.fail(key, f"{a:g} is beyond 2 pi: {what} in radians ({a:g} deg would be "
                      f"{math.radians(a):.4f})")


def _at_most(ck: _Checker, key: str, v: float) -> None:
    """ConfigError where process noise ``key`` exceeds ``process_noise_max``."""
    top = process_noise_max(key)
    if top is not None and v > top:
        raise ck.fail(key, f"must be at most {top:g}, got {v:g}: a density of the robot's motion "
                      "(per sqrt(s)); a ground robot's is well under 1 (leave it out for the "
                      "estimators' default, or let `ddfuse tune` estimate it)")


def _check_speed_tails(ck, tw: dict[str, float]) -> None:
    """The heavy-tailed speed walk's keys (``estimation.twist_tails``): speed_burst needs the
    steady ``speed`` and exceeds it; burst_share needs speed_burst and lies in (0, 1)."""
    if "burst_share" in tw:
        if "speed_burst" not in tw:
            raise ck.fail("robot.twist_walk.burst_share", "needs robot.twist_walk.speed_burst "
                          "(the burst's density)")
        if not tw["burst_share"] < 1.0:
            raise ck.fail("robot.twist_walk.burst_share", f"must be < 1, got "
                          f"{tw['burst_share']:g}: it is the probability of a burst per speed "
                          "interval")
    if "speed_burst" in tw:
        if "speed" not in tw:
            raise ck.fail("robot.twist_walk.speed_burst", "needs robot.twist_walk.speed (the "
                          "steady walk's density)")
        if not tw["speed_burst"] > tw["speed"]:
            raise ck.fail("robot.twist_walk.speed_burst", f"must be > robot.twist_walk.speed "
                          f"({tw['speed']:g}), got {tw['speed_burst']:g}: it is the density "
                          "of the bursts")


def with_gps_model(cfg: Config, model: str | None) -> Config:
    """``cfg`` with ``gps.model`` replaced by ``model`` (one of ``GPS_MODELS``), a copy; ``cfg``
    itself where ``model`` is None. ConfigError for an unknown model."""
    if model is None:
        return cfg
    if model not in GPS_MODELS:
        raise ConfigError(f"gps model {model!r}: expected one of {', '.join(GPS_MODELS)}")
    return replace(cfg, gps=replace(cfg.gps, model=model))


def load_config(path: str | Path) -> Config:
    """Load and validate a config file. Raises ConfigError naming the file and key."""
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"{p}: is a directory, not a config file")
    if not p.is_file():
        raise ConfigError(f"{p}: config file not found")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{p}: cannot read config: {e}") from None
    return parse_config_text(text, str(p), p.parent)


def parse_config_text(text: str, source: str = "<config>", base: Path | None = None) -> Config:
    """Validate a config's YAML text (as a file holds it: 1e-4 is a number here, a string to
    PyYAML's safe loader). Raises ConfigError naming ``source`` and the key."""
    try:
        # a key given twice (two `gps:` blocks) is an error: PyYAML would keep only the last
        raw = yaml.load(text, Loader=_UniqueKeyLoader)
    except _DuplicateKey as e:
        raise ConfigError(f"{source}: {e.problem}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{source}: not valid YAML: {_yaml_problem(e)}") from None
    cfg = parse_config(raw, source, base)
    cfg.text = text  # what ran, whatever the file holds later
    return cfg


def _yaml_problem(e: yaml.YAMLError) -> str:
    """PyYAML's complaint in one line, with where (its first line alone, "while parsing a
    flow node", said neither what nor where)."""
    problem = getattr(e, "problem", None)
    mark = getattr(e, "problem_mark", None)
    if problem is None:
        return str(e).splitlines()[0]
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    context = getattr(e, "context", None)
    return f"{problem}{where}" + (f" ({context})" if context else "")


def resolve_landmark_maps(cfg: Config, bag: str | Path | None = None) -> None:
    """Find each landmark sensor's map: a relative path is looked up next to the config, then
    next to ``bag`` (a dataset's map sits beside its bag, which a shipped config cannot point
    to from every checkout). Sets the sensors' ``map``; raises ConfigError naming the key and
    every place tried when none has it."""
    for i, s in enumerate(cfg.of_kind("landmarks")):
        if s.map is None or s.map.is_file():
            continue
        tried = [s.map]
        if bag is not None and s.map_name is not None and not s.map_name.is_absolute():
            beside = Path(bag).parent / s.map_name
            if beside.is_file():
                s.map = beside
                continue
            tried.append(beside)
        where = " or ".join(str(t) for t in tried)
        raise ConfigError(f"{cfg.path or '<config>'}: sensors.landmarks[{i}].map: file not "
                          f"found: {where}")


# The reason a landmark sighting is dropped (by the bag reader, the live converter and each
# estimator fed directly) when its id is not in the map.
LANDMARK_NOT_IN_MAP = "landmark id not in the map"


def landmark_maps(cfg: Config, bag: str | Path | None = None) -> dict[str, tuple[float, float]]:
    """Every landmark sensor's map merged (id -> (x, y) m), each found as
    ``resolve_landmark_maps`` says (next to the config, then next to ``bag``). An id in two
    maps must have the same position in both: ConfigError naming the map file and the id."""
    resolve_landmark_maps(cfg, bag)
    out: dict[str, tuple[float, float]] = {}
    source: dict[str, Path] = {}  # id -> the map that gave it
    for s in cfg.of_kind("landmarks"):
        for k, xy in load_landmark_map(s.map).items():
            if k in out and out[k] != xy:
                raise ConfigError(
                    f"{s.map}: landmarks.{k}: duplicate id: at ({xy[0]:g}, {xy[1]:g}) here but "
                    f"at ({out[k][0]:g}, {out[k][1]:g}) in {source[k]} (two landmark sensors' "
                    "maps must agree on the ids they share)")
            out[k] = xy
            source.setdefault(k, s.map)
    return out


def load_landmark_map(path: Path) -> dict[str, tuple[float, float]]:
    """Landmark map YAML: ``landmarks: {id: [x, y]}`` (m, in the map/local frame), ids as
    strings. ConfigError naming the file and key for a map without landmarks, a key given twice
    or two ids that are one as strings (``1:`` and ``"1":``)."""
    ck = _Checker(str(path))
    loader = lm_node = None
    try:
        loader = _UniqueKeyLoader(Path(path).read_text(encoding="utf-8"))
        root = loader.get_single_node()
        pairs = root.value if isinstance(root, yaml.MappingNode) else []
        lm_node = next((v for k, v in pairs
                        if isinstance(k, yaml.ScalarNode) and k.value == "landmarks"), None)
        raw = loader.construct_document(root) if root is not None else None
    except _DuplicateKey as e:
        if e.node is lm_node:
            raise ck.fail(f"landmarks.{e.key}", f"duplicate id (lines {e.lines[0]} and "
                          f"{e.lines[1]})") from None
        raise ck.fail(str(e.key), f"given twice (lines {e.lines[0]} and {e.lines[1]})") from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        raise ConfigError(f"{path}: cannot read landmark map: {e}") from None
    finally:
        if loader is not None:
            loader.dispose()
    if not isinstance(raw, dict) or not isinstance(raw.get("landmarks"), dict):
        raise ck.fail("landmarks", "missing: expected 'landmarks: {id: [x, y]}'")
    if not raw["landmarks"]:
        raise ck.fail("landmarks", "empty: the map names no landmark, so no sighting can be "
                      "used")
    out: dict[str, tuple[float, float]] = {}
    given: dict[str, Any] = {}  # id -> the key as the file wrote it
    for k, v in raw["landmarks"].items():
        if str(k) in out:
            raise ck.fail(f"landmarks.{k}", f"duplicate id: keys {given[str(k)]!r} and {k!r} "
                          f"are both id {str(k)!r} (ids are text)")
        given[str(k)] = k
        out[str(k)] = ck.vector(v, f"landmarks.{k}", 2)
    return out
