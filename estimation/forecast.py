"""Carrying an estimate forward in time on the odometry received since it: the pose "now" for
a live robot, whose estimators lag the newest message by a reorder window.

An estimate at t_e is moved to a later t by the exact constant-twist step
(``ddfuse.factors.kinematics.se2_step``) of each twist sample after t_e, each sample covering the
interval since the previous one (as dead reckoning integrates it), then by the last twist held
up to t. Its 3x3 world-frame pose covariance (x m, y m, yaw rad) grows to first order,
P <- J_pose P J_pose^T + J_twist S J_twist^T per step, with S the twist sample's variances; a
sample held beyond its interval for tau s steps with a twist variance of var + q tau / 3 (q the
random-walk density of a held twist, as in the smoother).

``carry`` refuses (ValueError) to move an estimate more than ``horizon`` s (default
``MAX_CARRY_S`` = 5 s; an online session's is its reorder window plus that): the first-order
covariance no longer describes the error further on. ``OdometryTwist`` keeps the samples of as
long (``keep``).

The twist is the odometry's, without a scale calibration; the scale's uncertainty
(``robot.scale_std``) enters once per carry, through the pose's sensitivity to the speed and
yaw-rate scales. A gyro's yaw rate has its bias removed as the estimators remove it (gyro = w +
bias): a configured constant ``gyro_bias`` when the samples are made (``OdometryTwist.push``),
else (``gyro_bias: estimate``) the estimate's own bias state (``state_names`` 'bg:<sensor>' or
'bg') in ``carry``, its variance entering once per carry like the scale's. An estimate without
such a state is carried on the raw rate, bias included.

Design notes (held samples, the horizon, one error per carry): docs/design/forecast.md
"""

from __future__ import annotations

import math
from bisect import bisect_left, insort
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from ddfuse.estimation.config import Config
from ddfuse.estimation.estimator import Estimate, wrap_angle
from ddfuse.estimation.measurements import GyroYawRate, WheelOdometry, WheelSpeeds
from ddfuse.factors.kinematics import se2_step_jac

__all__ = ["MAX_CARRY_S", "OdometryTwist", "TwistSample", "carry"]

# s: the longest carry by default, a reorder window (0.5 s in the sample configs, rarely over
# 1-2 s) plus a few seconds of delivery latency; see the module docstring
MAX_CARRY_S = 5.0


@dataclass(frozen=True, slots=True)
class TwistSample:
    """A body twist measured over the interval ending at ``t`` (s): forward speed ``v`` (m/s),
    yaw rate ``w`` (rad/s), their variances (m/s)^2 and (rad/s)^2. ``raw_gyro``: the name of
    the gyro whose reading ``w`` is with its bias still in it, the bias being estimated
    (``carry`` removes the estimate's); None when ``w`` is bias-free (an odometry's, or a gyro's
    with its configured constant bias removed)."""

    t: float
    v: float
    w: float
    v_var: float
    w_var: float
    raw_gyro: str | None = None


def carry(e: Estimate, twists: Sequence[TwistSample], t: float,
          q: tuple[float, float], scale_cov: np.ndarray | None = None, *,
          horizon: float = MAX_CARRY_S) -> Estimate:
    """``e`` moved to time ``t`` (s) on ``twists`` (sorted by stamp; those at or before e.t
    only give the twist held from e.t), see the module docstring. ``q``: the random-walk
    densities of (v, w), (m/s^2)^2 s and (rad/s^2)^2 s, for a twist held beyond its sample.
    ``scale_cov``: 2x2 covariance of the relative errors of the speed and yaw-rate scales
    (None: exact scales). Returns ``e`` itself when t <= e.t or no twist is known; otherwise
    an Estimate at ``t`` with the carried pose and grown covariance, in world coordinates,
    without ``state``. ValueError when ``t`` is more than ``horizon`` s (default
    ``MAX_CARRY_S``) after ``e.t`` (+inf included), or NaN."""
    if math.isnan(t):
        raise ValueError(f"at = {t!r}: expected a time in seconds on the stamps' clock")
    if not t > e.t:
        return e
    if t - e.t > horizon:
        raise ValueError(f"at = {t:.3f} s is {t - e.t:.3g} s after the estimate (t = {e.t:.3f} "
                         f"s), beyond the carry's horizon of {horizon:g} s: further on, the "
                         "pose on a held twist is a guess")
    held = None
    i = 0
    while i < len(twists) and twists[i].t <= e.t:
        held = twists[i]
        i += 1
    if held is None and i == len(twists):
        return e
    x, y, psi = e.pose
    P = np.array(e.pose_cov, dtype=float)
    K = np.zeros((3, 2))  # d pose / d (relative scale error of v, of w)
    now = e.t
    steps = []
    for s in twists[i:]:
        if s.t > t:
            break
        steps.append((s, s.t - now, 0.0))
        now, held = s.t, s
    if t > now:
        # the first sample after t (if any) measures the twist up to t; else the newest is
        # held beyond its interval
        nxt = next((s for s in twists[i:] if s.t > t), None)
        steps.append((nxt, t - now, 0.0) if nxt is not None else (held, t - now, t - now))
    biases: dict[str, tuple[float, float, np.ndarray]] = {}  # gyro -> (b, var, d pose / d b)
    for s, dt, hold in steps:
        g = s.raw_gyro
        if g is not None and g not in biases:
            biases[g] = (*_bias_of(e, g), np.zeros(3))
        b = biases[g][0] if g is not None else 0.0
        x, y, psi, P, K, Jp, Ju = _step(x, y, psi, P, K, s, s.w - b, dt, hold, q)
        for h, (bh, vh, kb) in biases.items():
            # w = reading - b: the bias error moves the steps on that gyro's samples
            kb = Jp @ kb if Ju is not None else kb
            if h == g and Ju is not None:
                kb = kb - Ju[:, 1]
            biases[h] = (bh, vh, kb)
    for _, vb, kb in biases.values():
        P = P + vb * np.outer(kb, kb)
    if scale_cov is not None:
        P = P + K @ scale_cov @ K.T
    P = 0.5 * (P + P.T)
    if not np.all(np.isfinite(P)):
        P = np.full((3, 3), math.nan)
    return Estimate(t, (x, y, wrap_angle(psi)), P, pose_error="world")


def _bias_of(e: Estimate, gyro: str) -> tuple[float, float]:
    """(bias rad/s, its variance) of ``gyro`` in estimate ``e``'s state: 'bg:<gyro>', else
    'bg' (an estimator with one bias state); (0, 0) when ``e`` has neither (module docstring)."""
    if e.state is None:
        return 0.0, 0.0
    names = e.state_names
    for name in (f"bg:{gyro}", "bg"):
        if name in names:
            i = names.index(name)
            var = float(e.state_cov[i, i]) if e.state_cov is not None else 0.0
            return float(e.state[i]), var
    return 0.0, 0.0


def _step(x: float, y: float, psi: float, P: np.ndarray, K: np.ndarray, s: TwistSample,
          w: float, dt: float, hold: float, q: tuple[float, float]):
    """One constant-twist step of ``dt`` s on sample ``s`` with yaw rate ``w`` (its reading,
    bias removed); ``hold`` s of it beyond the sample's interval (then its variances grow as
    var + q hold / 3). ``K``: the pose's sensitivity to the relative scale errors, carried
    through the step. Also returns the step's Jacobians (pose, twist), None for no step."""
    if dt <= 0.0:
        return x, y, psi, P, K, None, None
    x1, y1, p1, J = se2_step_jac(x, y, psi, s.v, w, dt)
    Jp = np.array([r[:3] for r in J])
    Ju = np.array([r[3:] for r in J])
    S = np.diag((s.v_var + q[0] * hold / 3.0, s.w_var + q[1] * hold / 3.0))
    P = Jp @ P @ Jp.T + Ju @ S @ Ju.T
    K = Jp @ K + Ju * (s.v, w)
    return x1, y1, p1, P, K, Jp, Ju


def _stamp(s: TwistSample) -> float:
    return s.t


class OdometryTwist:
    """The twist samples a config's odometry gives, for ``carry``: forward speed from the
    first odometry sensor using v (else the first wheel-speed sensor, through the nominal
    robot.wheel_radius and robot.track_width), yaw rate from that same sensor when it gives
    one, else from the first gyro (imu using yaw_rate), its configured constant ``gyro_bias``
    removed (an estimated one is the estimate's, removed in ``carry``: the samples name the
    gyro in ``raw_gyro``). A sample is made at each message of either, with the other's newest
    value. ``samples`` holds those of the last ``keep`` s of stamps, sorted (default
    ``MAX_CARRY_S``: those a carry can use)."""

    def __init__(self, cfg: Config, keep: float = MAX_CARRY_S) -> None:
        odo = next((s for s in cfg.of_kind("odometry") if "v" in s.use), None)
        r, L = cfg.robot.wheel_radius, cfg.robot.track_width
        wheels = next(iter(cfg.of_kind("wheels")), None) if r is not None and L is not None \
            else None
        self.v_sensor = odo.name if odo is not None else (wheels.name if wheels else None)
        self.w_from_v = (odo is not None and "yaw_rate" in odo.use) or (
            odo is None and wheels is not None)
        gyro = next((s for s in cfg.of_kind("imu") if "yaw_rate" in s.use), None)
        self.w_sensor = self.v_sensor if self.w_from_v else (gyro.name if gyro else None)
        # the gyro's bias as the estimators take it (gyro = w + bias): a configured constant is
        # removed from each reading here, an estimated one left to the estimate (carry)
        use_gyro = not self.w_from_v and gyro is not None
        estimated = use_gyro and gyro.gyro_bias == "estimate"
        self.gyro_bias = float(gyro.gyro_bias) if use_gyro and not estimated else 0.0
        self._raw_gyro = gyro.name if estimated else None
        self._r, self._L = r, L
        sd = cfg.robot.scale_std
        # the gyro's yaw rate carries no wheel-geometry scale
        self.scale_cov = None if sd is None else np.array(
            [[sd[0] ** 2, sd[2] if self.w_from_v else 0.0],
             [sd[2] if self.w_from_v else 0.0, sd[1] ** 2 if self.w_from_v else 0.0]])
        self._a = (cfg.robot.max_accel, cfg.robot.max_yaw_accel)
        self.keep = float(keep)
        self.samples: list[TwistSample] = []
        self._v: tuple[float, float] | None = None  # newest (value, variance)
        self._w: tuple[float, float] | None = None
        self._period = math.nan  # s, the spacing of the v sensor's messages (running)
        self._last_v_t = math.nan

    @property
    def usable(self) -> bool:
        return self.v_sensor is not None and self.w_sensor is not None

    def push(self, m) -> None:
        """Take one measurement (any; those of other sensors are ignored)."""
        sensor = m.sensor
        if sensor != self.v_sensor and sensor != self.w_sensor:
            return
        if isinstance(m, WheelOdometry):
            if m.v is not None and sensor == self.v_sensor:
                self._v = (m.v, m.v_var)
            if m.yaw_rate is not None and self.w_from_v:
                self._w = (m.yaw_rate, m.yaw_rate_var)
        elif isinstance(m, WheelSpeeds):
            v, w, v_var, w_var = m.twist(self._r, self._L)
            self._v, self._w = (v, v_var), (w, w_var)
        elif isinstance(m, GyroYawRate) and sensor == self.w_sensor:
            self._w = (m.yaw_rate - self.gyro_bias, m.var)
        else:
            return
        if sensor == self.v_sensor:
            dt = m.t - self._last_v_t
            if 0.0 < dt < 1.0:
                self._period = dt if math.isnan(self._period) else 0.9 * self._period + 0.1 * dt
            self._last_v_t = m.t
        if self._v is None or self._w is None or not math.isfinite(m.t):
            return
        s = TwistSample(m.t, self._v[0], self._w[0], self._v[1], self._w[1], self._raw_gyro)
        if not all(math.isfinite(u) for u in (s.v, s.w, s.v_var, s.w_var)):
            return
        samples = self.samples
        insort(samples, s, key=_stamp)
        cut = samples[-1].t - self.keep
        if samples[0].t < cut:
            del samples[:bisect_left(samples, cut, key=_stamp)]

    def q(self) -> tuple[float, float]:
        """Random-walk densities of (v, w) for a held twist: a_max^2 T from the robot's
        acceleration limits and the sample period T (the EKFs' twist densities), else 1."""
        T = self._period if math.isfinite(self._period) else 0.1
        return tuple(a * a * T if a is not None else 1.0 for a in self._a)
