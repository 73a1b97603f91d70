"""The noise values ``ddfuse tune`` estimates: which a config and its bag have, where each one
lives in the config, and how a set of values is put into a config and a stream's measurements.

A parameter is one standard deviation (SI units, as the config states noise) or one process
noise density:

* per sensor and measured quantity, the config's ``sensors.<kind>[i].noise.<key>``: odometry
  ``v`` and ``yaw_rate`` (m/s, rad/s), wheels ``speed`` (rad/s), IMU ``yaw`` (rad),
  ``yaw_rate`` (rad/s) and ``accel`` (m/s^2), a magnetometer's or local heading's ``yaw``
  (rad; a magnetometer's config may state ``field`` (T) instead, which the reader turns into
  each sample's heading variance: tuned, its ``yaw`` is written, which the reader takes
  first), GPS ``horizontal`` (m), landmarks ``range`` (m) and ``bearing`` (rad), for the
  quantities the sensor's ``use`` fuses;
* the IMU's ``gyro_bias_walk`` (rad/s/sqrt(s)) and any heading sensor's
  ``heading_offset_walk`` (rad/sqrt(s)) where the config estimates the bias / offset;
* ``robot.slip.longitudinal``, ``lateral`` (m/sqrt(s)) and ``heading`` (rad/sqrt(s));
* a landmark sensor's ``noise.bearing_common`` (rad, kind 'common'): the part of the bearing
  error common to a frame's sightings (``estimation.landmark_frames``), searched with the
  bearing (the common part moves every sighting of a frame alike, the own part their
  differences), in a second stage after the others (``evaluation.tune._staged_search``),
  and may end 'negligible' like a process noise. Every landmark sensor fusing bearings has
  one (start 0 where the config states none, ``source`` 'frames'); the second stage runs for
  a sensor whose config states it (> 0) or whose frames' innovations under the first stage's
  independent model are correlated (``evaluation.tune_frames``); otherwise it stays as the
  config has it;
* a landmark sensor's ``correlation_time`` (s, kind 'corr'): not searched by the likelihood
  but set by the sightings' neighbour scatter at the tuned bearing sigma
  (``evaluation.tune_rules``);
  a heading sensor's yaw ``correlation_time`` (kind 'corr'): measured against the gyro's integral
  (``evaluation.compass_correlation``) before the search, which runs with it;
* ``robot.twist_walk.speed`` (m/s/sqrt(s)) and ``yaw_rate`` (rad/s/sqrt(s)), the twist's own
  random walk, where a sensor measures that component of the twist. Where the config states
  none, the search starts from what the EKF uses then: ``robot.max_accel`` sqrt(T) (T the
  shortest median sample period of the sensors measuring it), else its default density;
* ``robot.twist_walk.speed_burst`` (m/s/sqrt(s)) and ``burst_share`` (1, kind 'corr':
  measured, not searched), the heavy-tailed speed walk (``estimation.twist_tails``), where the
  config states it or the odometry speed's changes have a kurtosis of ``HEAVY_KURTOSIS`` or
  more (``_speed_tails``); not with landmarks (the landmark EKF that tunes them has no such
  walk).

A measurement's noise is fixed when the stream is read (``estimation.converters``: the
config's value, else the message's covariance), so a set of values is applied to the config (for
the process noise, which the estimators read when built) and to the variances of the stream's
measurements alike, in place.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from ddfuse.ekf_baseline.unicycle_layout import TWIST_RATE_KEYS
from ddfuse.ekf_baseline.unicycle_motion import ProcessNoise
from ddfuse.estimation.config import HEADING_KINDS, NOISE_KEYS, Config
from ddfuse.estimation.measurements import (
    ForwardAccel,
    GpsFix,
    GyroYawRate,
    Heading,
    LandmarkObservation,
    Stream,
    WheelOdometry,
    WheelSpeeds,
)

# (kind, noise key) -> (measurement class, its variance attributes, the ``use`` it needs)
_MEASURED = {
    ("odometry", "v"): (WheelOdometry, ("v_var",), "v"),
    ("odometry", "yaw_rate"): (WheelOdometry, ("yaw_rate_var",), "yaw_rate"),
    ("wheels", "speed"): (WheelSpeeds, ("left_var", "right_var"), "speeds"),
    # every heading sensor's ``yaw`` (rad; a magnetometer's the reader takes before ``field``)
    **{(kind, "yaw"): (Heading, ("var",), "yaw") for kind in HEADING_KINDS},
    ("imu", "yaw_rate"): (GyroYawRate, ("var",), "yaw_rate"),
    ("imu", "accel"): (ForwardAccel, ("var",), "accel"),
    ("gps", "horizontal"): (GpsFix, ("cov",), "position"),
    ("landmarks", "range"): (LandmarkObservation, ("range_var",), "range"),
    ("landmarks", "bearing"): (LandmarkObservation, ("bearing_var",), "bearing"),
}
SLIP_KEYS = ("longitudinal", "lateral", "heading")
TWIST_KEYS = ("speed", "yaw_rate")
# the speed's sample-to-sample changes with at least this kurtosis (3: Gaussian) turn the
# heavy-tailed speed walk on (estimation.twist_tails; rl_jackal.bag 31, rl_husky_gps.bag 3.4)
HEAVY_KURTOSIS = 10.0
BURST_SIGMAS = 4.0  # a change beyond this many robust sigmas counts as a burst's
_DEFAULTS = ProcessNoise()
# the unicycle EKF's densities where the config states none (ekf_baseline.unicycle_motion)
_DEFAULT_WALK = {"gyro_bias_walk": _DEFAULTS.gyro_bias,
                 "heading_offset_walk": _DEFAULTS.heading_offset}
_DEFAULT_SLIP = {"longitudinal": _DEFAULTS.pos_long, "lateral": _DEFAULTS.pos_lat,
                 "heading": _DEFAULTS.heading}
_DEFAULT_TWIST = {"speed": _DEFAULTS.acc, "yaw_rate": _DEFAULTS.yaw_acc}
# where a config states a density of 0 (none), the search starts from the EKF's default
# density instead (``_DEFAULT_WALK``, ``_DEFAULT_SLIP``): started at 1e-3 (session 19) a slip
# showed in no innovation (information 3e-4 on mrclam1_robot1.bag), so a config that states
# no slip could never learn that the data want one


@dataclass
class Param:
    """One tunable value. ``key`` is its place in the config as a dotted path
    (``sensors.imu[0].noise.yaw_rate``, ``robot.slip.heading``); ``label`` names it for people
    (``/imu/data yaw_rate``); ``start`` is where the search starts (std or density, SI);
    ``before`` is the config's value (None: the config states none: the messages' covariance
    or the estimator's default, ``source`` says which); ``unit`` for tables."""

    key: str
    label: str
    start: float
    before: float | None
    # 'config', 'messages' (median of the stream's), 'default', 'max_accel' (the twist walk
    # the robot's acceleration limit gives) or 'frames' (a bearing_common the config does not
    # state: fitted where the frames' innovations show one)
    source: str
    unit: str
    sensor: str | None = None  # the sensor's name (its noise or walk), None for the robot's
    kind: str = ""  # sensor kind, or 'slip' / 'walk' / 'twist' / 'corr' / 'common'
    noise_key: str = ""
    # held at ``start`` by a rule beside the likelihood, not searched (an odometry input's
    # noise measured from its own samples: ``evaluation.tune_inputs``)
    held: bool = False


_UNITS = {"accel": "m/s^2", "v": "m/s", "yaw_rate": "rad/s", "speed": "rad/s", "yaw": "rad",
          "horizontal": "m",
          "range": "m", "bearing": "rad", "gyro_bias_walk": "rad/s/sqrt(s)",
          "heading_offset_walk": "rad/sqrt(s)", "longitudinal": "m/sqrt(s)",
          "lateral": "m/sqrt(s)", "heading": "rad/sqrt(s)", "twist speed": "m/s/sqrt(s)",
          "twist yaw_rate": "rad/s/sqrt(s)"}


def _median_std(stream: Stream, sensor: str, cls, attr: str) -> float | None:
    """The median standard deviation the stream's measurements of ``sensor`` state."""
    if attr == "cov":
        v = [0.5 * (m.cov[0, 0] + m.cov[1, 1]) for m in stream.measurements
             if type(m) is cls and m.sensor == sensor]
    else:
        v = [getattr(m, attr) for m in stream.measurements
             if type(m) is cls and m.sensor == sensor and getattr(m, attr) is not None]
    v = [x for x in v if x is not None and np.isfinite(x) and x > 0.0]
    return float(np.sqrt(np.median(v))) if v else None


def parameters(cfg: Config, stream: Stream) -> list[Param]:
    """The values ``cfg`` and ``stream`` allow tuning, in config order: each sensor's noise for
    the quantities it uses and that the stream has messages of, its walks where estimated, then
    the robot's slip."""
    out: list[Param] = []
    index: dict[str, int] = {}
    for s in cfg.sensors:
        i = index.get(s.kind, 0)
        index[s.kind] = i + 1
        base = f"sensors.{s.kind}[{i}].noise"
        for (kind, key), (cls, attrs, use) in _MEASURED.items():
            if kind != s.kind or use not in s.use:
                continue
            before = s.noise.get(key)
            start, source = before, "config"
            if before is None:
                start, source = _median_std(stream, s.name, cls, attrs[0]), "messages"
                if start is None:
                    continue  # no message of this sensor: nothing to tune it on
            out.append(Param(f"{base}.{key}", f"{s.name} {key}", start, before, source,
                             _UNITS[key], s.name, s.kind, key))
            if key == "yaw" and kind in HEADING_KINDS:
                out.append(_heading_correlation(cfg, stream, s, i))
            if (kind, key) == ("landmarks", "bearing"):
                common = s.noise.get("bearing_common")  # stated 0: the user says none
                out.append(Param(f"{base}.bearing_common", f"{s.name} bearing_common",
                                 common or 0.0, common, "frames" if common is None else
                                 "config", "rad", s.name, "common", "bearing_common"))
                tau = float(s.correlation_time)
                out.append(Param(f"sensors.landmarks[{i}].correlation_time",
                                 f"{s.name} correlation_time", tau, tau, "config", "s",
                                 s.name, "corr", "correlation_time"))
        if s.kind in HEADING_KINDS:
            for key, wanted, use in (("gyro_bias_walk", s.gyro_bias, "yaw_rate"),
                                     ("heading_offset_walk", s.heading_offset, "yaw")):
                if wanted != "estimate" or use not in s.use or key not in NOISE_KEYS[s.kind]:
                    continue
                before = s.noise.get(key)
                start, source = (before, "config") if before is not None else (
                    _DEFAULT_WALK[key], "default")
                out.append(Param(f"{base}.{key}", f"{s.name} {key}", start or _DEFAULT_WALK[key],
                                 before, source, _UNITS[key], s.name, "walk", key))
    for key in SLIP_KEYS:
        before = cfg.robot.slip.get(key)
        start, source = (before, "config") if before is not None else (_DEFAULT_SLIP[key],
                                                                        "default")
        out.append(Param(f"robot.slip.{key}", f"robot slip {key}", start or _DEFAULT_SLIP[key],
                         before, source, _UNITS[key], None, "slip", key))
    periods = _twist_periods(cfg, stream)
    limits = {"speed": cfg.robot.max_accel, "yaw_rate": cfg.robot.max_yaw_accel}
    for key in TWIST_KEYS:
        if periods[key] is None:
            continue  # nothing measures it: the walk only widens an unobserved state
        before = cfg.robot.twist_walk.get(key)
        if before is not None:
            start, source = before, "config"
        elif limits[key]:
            start, source = limits[key] * float(np.sqrt(periods[key])), "max_accel"
        else:
            start, source = _DEFAULT_TWIST[key], "default"
        out.append(Param(f"robot.twist_walk.{key}", f"robot twist_walk {key}", start, before,
                         source, _UNITS[f"twist {key}"], None, "twist", key))
    if periods["speed"] is not None and not cfg.of_kind("landmarks"):
        out += _speed_tails(cfg, stream, out)
    return out


def speed_changes(stream: Stream) -> tuple[np.ndarray, float] | None:
    """The odometry speed's sample-to-sample changes (m/s) of the sensor with the most speed
    samples, and its median sample period (s); None with fewer than 100 samples."""
    by: dict[str, list[tuple[float, float]]] = {}
    for m in stream.measurements:
        if type(m) is WheelOdometry and m.v is not None:
            by.setdefault(m.sensor, []).append((m.t, m.v))
    if not by:
        return None
    tv = np.asarray(max(by.values(), key=len), float)
    d = np.diff(tv, axis=0)
    d = d[d[:, 0] > 0.0]
    return (d[:, 1], float(np.median(d[:, 0]))) if len(d) >= 100 else None


def speed_tails(dv: np.ndarray, period: float) -> tuple[float, float, float, float]:
    """From the speed's changes ``dv`` (m/s) over samples ``period`` s apart: their kurtosis
    (3 for a Gaussian walk), and the heavy-tailed walk's starting steady and burst densities
    (m/s/sqrt(s): the robust sigma of the changes, and the RMS of those beyond
    ``BURST_SIGMAS`` of it, over sqrt(period)) and the bursts' share of the intervals."""
    c = dv - np.median(dv)
    kurt = float(np.mean(c ** 4) / np.var(c) ** 2) if np.var(c) > 0.0 else 3.0
    robust = max(1.4826 * float(np.median(np.abs(c))), 1e-6)
    burst = np.abs(c) > BURST_SIGMAS * robust
    share = min(max(float(np.mean(burst)), 1.0 / len(c)), 0.5)
    rms = float(np.sqrt(np.mean(c[burst] ** 2))) if burst.any() else BURST_SIGMAS * robust
    root = math.sqrt(period)
    return kurt, robust / root, max(rms, 2.0 * robust) / root, share


def _speed_tails(cfg: Config, stream: Stream, params: list[Param]) -> list[Param]:
    """The heavy-tailed speed walk's parameters (``estimation.twist_tails``): its burst
    density, searched with the others, and its share, measured (kind 'corr', set before the
    search). Where the config states the walk, from the config's values (the share as it
    states); else only where the speed's changes are heavy-tailed (kurtosis at least
    ``HEAVY_KURTOSIS``), when the steady density (``params``' speed walk) starts from their
    robust sigma instead."""
    tw = cfg.robot.twist_walk
    speed = next(p for p in params if p.key == "robot.twist_walk.speed")
    unit = _UNITS["twist speed"]
    if "speed_burst" in tw:
        return [Param("robot.twist_walk.speed_burst", "robot twist_walk speed_burst",
                      tw["speed_burst"], tw["speed_burst"], "config", unit, None, "twist",
                      "speed_burst")]
    changes = speed_changes(stream)
    if changes is None:
        return []
    kurt, steady, burst, share = speed_tails(*changes)
    if kurt < HEAVY_KURTOSIS:
        return []
    speed.start = steady  # (its source stays what the EKF used before: the table's 'before')
    return [Param("robot.twist_walk.speed_burst", "robot twist_walk speed_burst", burst, None,
                  "measured", unit, None, "twist", "speed_burst"),
            Param("robot.twist_walk.burst_share", "robot twist_walk burst_share", share, None,
                  "measured", "1", None, "corr", "burst_share")]


def _heading_correlation(cfg: Config, stream: Stream, s, i: int) -> Param:
    """Heading sensor ``s``'s yaw ``correlation_time`` (kind 'corr'): measured against the gyro's
    integral (``evaluation.compass_correlation``) where the data identify it (source
    'measured'), else the config's."""
    from ddfuse.evaluation.compass_correlation import measure

    tau = float(s.correlation_time)
    fit = measure(cfg, stream, s.name)
    start, source = (round(fit.tau, 1), "measured") if fit and fit.tau else (tau, "config")
    return Param(f"sensors.{s.kind}[{i}].correlation_time", f"{s.name} correlation_time", start,
                 tau, source, "s", s.name, "corr", "correlation_time")


def _twist_periods(cfg: Config, stream: Stream) -> dict[str, float | None]:
    """Per twist component ('speed', 'yaw_rate'), the shortest median sample period (s) of
    the stream's measurements of it (odometry, wheel speeds, a fused gyro), as the unicycle
    EKF's twist_densities takes it; None where nothing measures it."""
    gyros = {s.name for s in cfg.of_kind("imu") if "yaw_rate" in s.use}
    stamps: dict[tuple[str, str], list[float]] = {}
    for m in stream.measurements:
        comps = ()
        if type(m) is WheelOdometry:
            comps = (("speed",) if m.v is not None else ()) + (
                ("yaw_rate",) if m.yaw_rate is not None else ())
        elif type(m) is WheelSpeeds:
            comps = ("speed", "yaw_rate")
        elif type(m) is GyroYawRate and m.sensor in gyros:
            comps = ("yaw_rate",)
        for c in comps:
            stamps.setdefault((c, m.sensor), []).append(m.t)
    out: dict[str, float | None] = {k: None for k in TWIST_KEYS}
    for (c, _), ts in stamps.items():
        d = np.diff(np.asarray(ts, float))
        d = d[d > 0.0]
        if len(d):
            T = float(np.median(d))
            out[c] = T if out[c] is None else min(out[c], T)
    return out


# where the first stage of ``ddfuse tune`` (evaluation.tune, module docstring) starts the
# density (m/s^2/sqrt(s), rad/s^2/sqrt(s)) of the white jerk driving each twist component's rate
RATE_START = 0.3


def twist_rate_params(cfg: Config, stream: Stream) -> list[Param]:
    """The twist's rates, one per twist component a sensor measures, for the first stage of
    ``ddfuse tune`` (the unicycle EKF's acceleration states; no config states them)."""
    periods = _twist_periods(cfg, stream)
    return [Param(f"robot.twist_walk.{key}", f"robot twist_walk {key}", RATE_START, None,
                  "default", _UNITS[f"twist {comp}"].replace("/s/", "/s^2/"), None, "twist",
                  key) for comp, key in TWIST_RATE_KEYS.items() if periods[comp] is not None]


class Applier:
    """Puts a set of values into ``cfg`` (the process noise, read when an estimator is built)
    and the variances of ``stream``'s measurements, in place. A value of None leaves what was
    read: the config's, or each message's own covariance."""

    def __init__(self, cfg: Config, stream: Stream, params: list[Param]) -> None:
        self.cfg, self.stream, self.params = cfg, stream, params
        by_sensor: dict[tuple, list] = {}
        for m in stream.measurements:
            by_sensor.setdefault((type(m), m.sensor), []).append(m)
        self._targets: list[tuple[list, tuple[str, ...]]] = []
        for p in params:
            if p.kind in ("slip", "walk", "twist", "corr", "common"):
                self._targets.append(([], ()))
                continue
            cls, attrs, _ = _MEASURED[(p.kind, p.noise_key)]
            self._targets.append((by_sensor.get((cls, p.sensor), []), attrs))
        # the messages' own values, to restore a parameter set back to None
        self._read = [[tuple(_get(m, a) for a in attrs) for m in ms] for ms, attrs in
                      self._targets]
        self._noise0 = {s.name: dict(s.noise) for s in cfg.sensors}
        self._slip0 = dict(cfg.robot.slip)
        self._twist0 = dict(cfg.robot.twist_walk)
        self._tau0 = {s.name: s.correlation_time for s in cfg.sensors}

    def apply(self, values: list[float | None]) -> None:
        """Set every parameter to its value in ``values`` (same order as the params)."""
        cfg = self.cfg
        slip, twist = dict(self._slip0), dict(self._twist0)
        for s in cfg.sensors:
            s.noise = dict(self._noise0[s.name])
            s.correlation_time = self._tau0[s.name]
        for p, v, (ms, attrs), read in zip(self.params, values, self._targets, self._read,
                                           strict=True):
            if p.kind == "corr":
                if v is not None and p.sensor is None:  # the speed walk's burst share
                    twist[p.noise_key] = float(v)
                elif v is not None:
                    cfg.sensor(p.sensor).correlation_time = float(v)
                continue
            if p.kind in ("slip", "twist"):
                if v is not None:
                    (slip if p.kind == "slip" else twist)[p.noise_key] = float(v)
                continue
            sensor = cfg.sensor(p.sensor)
            if v is not None:
                sensor.noise[p.noise_key] = float(v)
            if not ms:  # (and a 'common': the estimators read it from the config)
                continue
            if v is None:
                for m, old in zip(ms, read, strict=True):
                    for a, x in zip(attrs, old, strict=True):
                        setattr(m, a, x)
            elif attrs == ("cov",):
                vert = sensor.noise.get("vertical", 2.0 * v)
                cov = np.diag([v * v, v * v, vert * vert])
                for m in ms:
                    m.cov = cov.copy()
            else:
                var = float(v) * float(v)
                for a in attrs:
                    for m in ms:
                        setattr(m, a, var)
        cfg.robot.slip = slip
        cfg.robot.twist_walk = twist


def _get(m, attr: str):
    v = getattr(m, attr)
    return v.copy() if isinstance(v, np.ndarray) else v

