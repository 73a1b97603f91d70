"""ISAM2 fixed-lag smoother over keyframes (gtsam.IncrementalFixedLagSmoother).

Design (from shared/notes/gtsam-smoother-design-study.md, measured there as the fastest that keeps
velocity and biases as states): one 9-vector key per keyframe,
``[x, y, psi, v, w, bg, hoff, k_v, k_w]`` (``ddfuse.factors.state``), and few factors per keyframe:

* wheel speed and yaw rate between keyframes are folded into one preintegrated factor
  (``factors.preintegration``) with first-order corrections for the gyro bias and the odometry's
  speed and yaw-rate scales; its last sample ties the keyframe's v and w. Wheel odometry is the
  mean over the interval since its previous sample, stamped at the end, so it is held backward
  over that interval (messages inside it wait for it, see ``process``); gyro samples are
  instantaneous and held forward. When both a gyro and an odometry (or wheel-speed) yaw rate are
  configured, each integration step uses their inverse-variance weighted mean, the gyro's weight
  being the share of the gyro bias the fused rate carries. A held sample's error is the same over
  its whole period T, so its variance enters as a density var * T (per step of dt: var * T / dt);
* a GPS fix is a GPS factor (lever arm; motion-compensated when it does not fall on the keyframe,
  with what the motion does off the keyframe's twist over that time added to the fix's full
  east/north covariance; robust noise from the config), unless its innovation against the
  prediction fails the sensor's chi-square gate (as in the EKF). A gate lock-out
  (``ddfuse.estimation.lockout``) is recovered from as the EKFs do, by widening the belief until the
  fix is ordinary: here a link factor to a new keyframe at the fix (``FixedLagSmoother._widen``).
  A fix that arrives late goes to the window's keyframe nearest its stamp, gated against that
  keyframe's marginal; one older than the newest keyframe minus the lag is dropped and counted.
  With the sensor's ``correlation_time`` (time-correlated errors, ``estimation.gps_correlation``)
  the factor's covariance is the fix's inflated by f for the time since the previous fused fix,
  while the gate and the logged innovation keep the fix's own (``FixedLagSmoother._gps``);
* with both a gyro and an odometry yaw rate, the mean gyro rate minus k_w times the mean
  odometry rate over the interval is a measurement of the gyro bias, which the fused rate alone
  would not carry (``ddfuse.factors.gyro.bias_difference_factor``; its residual is whitened by a
  k_w-dependent sigma, since both rates are noisy);
* the absolute heading samples of the interval, each carried to the keyframe by the
  preintegrated yaw, gated as in the EKFs (``FixedLagSmoother._heading_gate``) and averaged,
  are one heading measurement (with the offset state when ``heading_offset: estimate``, and the
  carried yaw's first-order dependence on the gyro bias and yaw-rate scale,
  ``FixedLagSmoother._pending_heading``); it is linear in the state, so it is a C++ factor
  (``ddfuse.factors.linear``), not a Python CustomFactor;
* a landmark sighting is a range/bearing (or range-only) factor to the known map position.

Process noise is what the config states, as for the EKFs: the robot's slip densities
(robot.slip), the IMU's bias and offset walks, the geometry's uncertainty (robot.wheel_radius_std,
track_width_std: the prior of k_v, k_w, else they are held at 1); see ``SmootherNoise``.

Keyframes: ``smoother.keyframe: gps`` puts one at each GPS fix or landmark sighting (at most one
per ``MIN_KEYFRAME_DT``), and one after ``1/keyframe_rate`` s without any (so dead reckoning
keeps the window populated); ``rate`` puts them at ``keyframe_rate`` Hz and attaches absolute
measurements to the newest keyframe, motion-compensated by its twist. That twist is tied to one
odometry sample, so the carry regresses k_w on a noisy sample: on simulated landmark data at
2 Hz keyframes k_w ended -0.8 of its sigma off on average (docs/results/smoother_monte_carlo.md,
session 7); ``gps`` has no carry.

Outputs: the filtered estimate (newest keyframe, updated with the heading samples since it,
composed with the partial preintegration, at update time) from ``estimate()``; the lagged
estimate of each keyframe as it leaves the window (``lagged_estimates()``); both with marginal
covariance. ``BatchSmoother`` keeps every factor and solves the whole run with
Levenberg-Marquardt at the end (the offline reference).

Heading without an initial pose: GPS course. Measurements are buffered, dead-reckoned from heading
0, and once the GPS track has moved ``INIT_DISTANCE`` m (more with poor fixes: until the course's
sigma, the fixes' errors across the baseline, is at most ``COURSE_SIGMA_MAX``) the rotation that
aligns dead reckoning with it gives the initial heading, with that sigma (at least
``init_psi_sigma``); the buffer is then replayed.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, replace
from functools import lru_cache

import gtsam
import numpy as np
from ddfuse.estimation import chi2, gps_correlation
from ddfuse.estimation.config import (
    DEFAULT_GATE,
    GIVEN_POSE_STD,
    LANDMARK_NOT_IN_MAP,
    Config,
    SensorConfig,
    landmark_maps,
)
from ddfuse.estimation.estimator import Estimate, Estimator, Innovation, wrap_angle
from ddfuse.estimation.lockout import Lockout, inflation
from ddfuse.estimation.measurements import (
    GpsFix,
    GyroYawRate,
    Heading,
    LandmarkObservation,
    WheelOdometry,
    WheelSpeeds,
    is_finite,
)
from ddfuse.estimation.runner import TrackBuilder
from ddfuse.factors.gps import gps_factor, gps_predict_jacobian
from ddfuse.factors.gyro import bias_difference_factor
from ddfuse.factors.kinematics import se2_step, se2_step_jac
from ddfuse.factors.landmark import range_bearing_factor, range_factor
from ddfuse.factors.linear import linear_state_factor
from ddfuse.factors.preintegration import WheelGyroPreintegration, preintegrated_factor
from ddfuse.factors.state import BG, DIM, HOFF, KV, KW, NAMES, PSI

_ACCEPT, _REJECT, _RECOVER = 0, 1, 2  # verdicts of the GPS gate (FixedLagSmoother._gate)
MIN_KEYFRAME_DT = 0.1  # s: closer absolute measurements share a keyframe
INIT_DISTANCE = 5.0  # m of GPS travel before the heading is taken from the GPS course
COURSE_SIGMA_MAX = 0.4  # rad: with poor fixes, the travel waits for a course this good
# m/sqrt(s), m/sqrt(s), rad/sqrt(s): the least pose noise between keyframes (see
# SmootherNoise.from_config); a tenth of a millimetre per second, negligible against any sensor
POSE_NOISE_FLOOR = (1e-3, 1e-3, 1e-4)
ODOMETRY_WAIT = 0.5  # s: without odometry for this long, go on holding the last sample forward
# rad: a gap in the feed over which the yaw rate held across it leaves the heading this
# uncertain ends the window there (FixedLagSmoother._restart_after_gap)
GAP_HEADING_SIGMA = 0.5
RESTART_HEADING_WAIT = 1.0  # s: how long the new window waits for a heading sample
MAX_RECOVERIES = 3  # re-initialisations within RECOVERY_WINDOW the smoother survives
RECOVERY_WINDOW = 10.0  # s of data

# rad/s/sqrt(s), rad/sqrt(s): the least random walk of an estimated gyro bias and heading offset.
# A keyframe interval's information on the change of the state is 1 / (walk^2 dt); at walks of
# 1e-6 against a prior of 0.3 rad, Cholesky meets a condition number ~1e11 and gtsam declares
# the system indeterminate. 1e-4 rad/sqrt(s) is 2 mrad over 400 s. The bias walk is also at
# least ``walk_floor(init_bg_sigma)`` (3.1e-5: at 1e-5 and 10 Hz keyframes the smoother stopped
# within 0.5 s), and the offset's is at least ``walk_floor`` of its current sigma (above
# 1e-4 while that is over 0.065 rad).
WALK_FLOOR = (1e-5, 1e-4)


def walk_floor(prior_sigma: float) -> float:
    """The least random walk (per sqrt(s)) of a calibration state informed by nothing but its
    prior sigma ``prior_sigma`` for gtsam's Cholesky to accept the window.

    Two keyframes ``dt`` apart are tied by the walk with information 1 / (walk^2 dt) against
    the prior's 1 / sigma^2; gtsam 4.3 refuses a pivot whose information left after the
    earlier pivots is under 2^-24 of its diagonal (PR #2653, normalized all-pivot Cholesky
    checks), i.e. walk^2 dt / sigma^2 < 2^-24, and declares the system indeterminate. At the
    closest keyframes (MIN_KEYFRAME_DT) this floor keeps the ratio 4x above that: 4.6e-4
    rad/sqrt(s) for the heading offset's 0.3 rad prior, against WALK_FLOOR's 1e-4."""
    return prior_sigma * 2.0 ** -11 / math.sqrt(MIN_KEYFRAME_DT)


@dataclass
class SmootherNoise:
    """Process noise (densities) and initial uncertainty, shared by every run.

    Not tuned per bag or per estimator: the same values serve simulated and real data."""

    # m/sqrt(s) (longitudinal, lateral), rad/sqrt(s): slip and model error between keyframes
    pose_noise: tuple[float, float, float] = (0.05, 0.02, 0.01)
    gyro_bias_rw: float = 1e-4  # rad/s/sqrt(s)
    heading_offset_rw: float = 0.02
    fixed_rw: float = 1e-6  # random walk of a calibration state that is not estimated
    init_pos_sigma: float = GIVEN_POSE_STD[0]  # m, when the initial pose is given
    init_given_psi_sigma: float = GIVEN_POSE_STD[1]  # rad, when the initial pose is given
    init_psi_sigma: float = 0.2  # rad, from GPS course: at least (more on a short baseline)
    init_v_sigma: float = 1.0  # m/s
    init_w_sigma: float = 0.5  # rad/s
    init_bg_sigma: float = 0.02  # rad/s when estimated
    init_hoff_sigma: float = 0.3  # rad when estimated (initialised from the first sample)
    fixed_sigma: float = 1e-4  # prior on a calibration state that is not estimated
    # 1/sqrt(s): random walk of the odometry scales when they are estimated (the config states
    # the geometry's uncertainty), 0.2 % over 400 s (tyre wear, load); otherwise they are held
    # at 1 (fixed_rw), as the EKFs hold them. The EKFs' estimated scales are constants; here
    # 1e-5 already made gtsam's Cholesky declare the first keyframes indeterminate (simulated
    # husky, seed 1), 3e-5 did not.
    scale_rw: float = 1e-4
    # m/s^2/sqrt(Hz), rad/s^2/sqrt(Hz): white accelerations that move the twist away from a held
    # sample once it is older than its period (odometry or gyro stopped, a gap in the feed): the
    # EKFs' default (ProcessNoise.acc, yaw_acc); with robot.max_accel / max_yaw_accel the
    # density is a_max sqrt(T), T the sample's period, as the EKFs take it (twist_densities)
    acc: float = 1.0
    yaw_acc: float = 1.0

    @classmethod
    def from_config(cls, cfg: Config) -> SmootherNoise:
        """The defaults with what the config states about the robot and its IMU: the body's
        slip densities (robot.slip) and the calibration states' walks (an IMU's
        noise.gyro_bias_walk / heading_offset_walk), the same values the EKFs read. Each is
        floored (POSE_NOISE_FLOOR, WALK_FLOOR): a stated zero means 'negligible', but a
        preintegrated factor with no pose noise would have a singular covariance while the
        robot stands still."""
        n = cls()
        slip = cfg.robot.slip
        pn = tuple(max(slip.get(k, d), f) for k, d, f in zip(
            ("longitudinal", "lateral", "heading"), n.pose_noise, POSE_NOISE_FLOOR, strict=True))
        imus = cfg.of_kind("imu")
        bg = [s.noise["gyro_bias_walk"] for s in imus
              if "yaw_rate" in s.use and "gyro_bias_walk" in s.noise]
        ho = [s.noise["heading_offset_walk"] for s in imus
              if "yaw" in s.use and "heading_offset_walk" in s.noise]
        return replace(n, pose_noise=pn,
                       gyro_bias_rw=max(bg[0], WALK_FLOOR[0], walk_floor(n.init_bg_sigma))
                       if bg else n.gyro_bias_rw,
                       heading_offset_rw=max(ho[0], WALK_FLOOR[1]) if ho else n.heading_offset_rw)


# Relinearisation thresholds per state component (m, m, rad, m/s, rad/s, rad/s, rad, 1, 1).
# Positions
# and v enter every factor linearly (the GPS prior, the body-frame displacement R(psi)^T dp of the
# preintegration), so their linearisation point hardly matters; the heading enters through sin
# and cos, so it keeps a tight 0.05 rad (3 deg). On rl_husky_gps.bag this relinearises ~4x fewer
# factors than thresholds of 0.1 m / 0.02 rad, with hold-out RMSE unchanged to the millimetre.
RELINEARIZE = (1.0, 1.0, 0.05, 1.0, 0.1, 0.01, 0.05, 0.01, 0.01)
# Updates between relinearisation checks (gtsam's default). With 1 (every update), the newest
# keyframe's first correction is over a threshold at the next update almost always, so each
# preintegrated factor was linearised ~7.7 times in its window (Python callbacks) and more
# cliques re-eliminated. With 10 on rl_husky_gps.bag the hold-out RMSE moved 1.483 -> 1.484 m
# (lagged 1.067 -> 1.066), the simulated husky MC (6 seeds) RMSE 0.10599 -> 0.10599 m and ANEES
# 3.2004 -> 3.2006.
RELINEARIZE_SKIP = 10


def _threshold_map() -> gtsam.ISAM2ThresholdMap:
    tm = gtsam.ISAM2ThresholdMap()
    tm.insert(("x", np.array(RELINEARIZE)))
    return tm


def isam2_params() -> gtsam.ISAM2Params:
    """ISAM2 settings from the design study: per-component relinearisation thresholds (the
    scalar mixes m, rad and m/s), a check every RELINEARIZE_SKIP updates, Cholesky, cached
    linear factors, and findUnusedFactorSlots, which a hand-made ISAM2Params leaves off (factor
    slots would grow)."""
    p = gtsam.ISAM2Params()
    p.setRelinearizeThreshold(_threshold_map())
    p.relinearizeSkip = RELINEARIZE_SKIP
    p.cacheLinearizedFactors = True
    p.findUnusedFactorSlots = True
    p.evaluateNonlinearError = False
    p.enableDetailedResults = False
    p.setFactorization("CHOLESKY")
    return p


def _robust(cfg: Config, sensor: SensorConfig, sigmas: tuple[float, ...]) -> gtsam.noiseModel.Base:
    return _robustify(cfg, sensor, gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, float)),
                      len(sigmas))


@lru_cache(maxsize=64)
def _gate_radius(gate: float, dim: int) -> float:
    return math.sqrt(chi2.ppf(gate, dim))


def _robustify(cfg: Config, sensor: SensorConfig, base: gtsam.noiseModel.Base,
               dim: int, inflated: float = 1.0) -> gtsam.noiseModel.Base:
    """``base`` wrapped in the configured M-estimator. gtsam applies it to the norm of the
    whole whitened residual, so the default threshold is that norm at the sensor's chi-square
    gate for ``dim`` components: full weight wherever the EKF's gate would accept the same
    residual, linear (Huber) or log (Cauchy) growth beyond. With Huber's textbook k = 1.345 a
    2-D fix would be down-weighted 40 % of the time even when exactly Gaussian.

    ``inflated``: the factor f by which ``base``'s covariance is the measurement's own times f
    (a time-correlated GPS fix, ``ddfuse.estimation.gps_correlation``). The same residual in metres
    then whitens to 1/sqrt(f) of its norm against the own covariance, so the threshold (the
    gate radius, or a given ``robust_k`` alike) is scaled by 1/sqrt(f): the kernel still gives
    full weight to exactly the residuals the gate accepts (which judges the fix with its own
    covariance) and acts on the same residuals in metres. Unscaled, at f = 150 it would give
    full weight to residuals 12 times the gate's radius: no robustness left."""
    kind, k = cfg.smoother.robust, cfg.smoother.robust_k
    if k is None:
        k = _gate_radius(sensor.gate if sensor.gate is not None else DEFAULT_GATE, dim)
    if inflated != 1.0:
        k /= math.sqrt(inflated)
    if kind == "huber":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), base)
    if kind == "cauchy":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(k), base)
    return base


def _twist_walk(a_max: float | None, default: float, period: float) -> float:
    """Density ((unit/s)^2 per s) of the random walk that moves the twist away from a held
    sample: a_max^2 period from the robot's acceleration limit (the EKFs' twist_densities:
    Bar-Shalom's a_max sqrt(T)), else the default density squared."""
    return a_max * a_max * period if a_max is not None else default * default


def _compiled_preintegration() -> type[WheelGyroPreintegration]:
    """The compiled preintegration class (``factors.preintegration_jit``), its kernel compiled
    or loaded from numba's cache now rather than in the first timed ``process`` call; the
    Python reference if numba does not import. Imported here, not at module level, so that
    importing the smoother does not load numba."""
    try:
        from ddfuse.factors import preintegration_jit
    except ImportError:
        return WheelGyroPreintegration
    preintegration_jit.warm_up()
    return preintegration_jit.WheelGyroPreintegrationJit


def _compose(state, delta, pim_cov, pose_cov):
    """Pose of (state's pose) (+) delta and its 3x3 world-frame covariance J P J^T + R C R^T,
    with J the Jacobian of the composition wrt the keyframe pose and R the keyframe rotation.
    Scalar arithmetic: called for every output sample."""
    x, y, psi = float(state[0]), float(state[1]), float(state[2])
    dx, dy, dp = delta
    c, s = math.cos(psi), math.sin(psi)
    a, b = -s * dx - c * dy, c * dx - s * dy  # d(position)/d psi
    p = pose_cov.tolist()
    q = pim_cov.tolist()
    # J P J^T with J = [[1, 0, a], [0, 1, b], [0, 0, 1]]
    p00 = p[0][0] + 2 * a * p[0][2] + a * a * p[2][2]
    p01 = p[0][1] + a * p[1][2] + b * p[0][2] + a * b * p[2][2]
    p02 = p[0][2] + a * p[2][2]
    p11 = p[1][1] + 2 * b * p[1][2] + b * b * p[2][2]
    p12 = p[1][2] + b * p[2][2]
    # R C R^T with R the planar rotation (the yaw row is unchanged)
    q00, q01, q11 = q[0][0], q[0][1], q[1][1]
    r00 = c * c * q00 - 2 * c * s * q01 + s * s * q11
    r01 = c * s * (q00 - q11) + (c * c - s * s) * q01
    r11 = s * s * q00 + 2 * c * s * q01 + c * c * q11
    r02 = c * q[0][2] - s * q[1][2]
    r12 = s * q[0][2] + c * q[1][2]
    cov = np.array(((p00 + r00, p01 + r01, p02 + r02),
                    (p01 + r01, p11 + r11, p12 + r12),
                    (p02 + r02, p12 + r12, p[2][2] + q[2][2])))
    return (x + c * dx - s * dy, y + s * dx + c * dy, psi + dp), cov


class FixedLagSmoother(Estimator):
    """The ISAM2 fixed-lag smoother (see the module docstring)."""

    name = "smoother"
    keep_all = False  # BatchSmoother keeps every factor for a final whole-run solve

    def __init__(self, cfg: Config, *, initial_pose=None, landmarks=None, lag: float | None = None,
                 noise: SmootherNoise | None = None, reference: bool = False,
                 lagged: bool = True) -> None:
        """``reference``: preintegrate with the Python ``WheelGyroPreintegration`` instead of its
        compiled twin (``ddfuse.factors.preintegration_jit``; the same numbers, for tests).
        ``lagged``: whether to output the lagged track (``lagged_estimates``). Its covariances
        are a quarter to a third of the smoother's cost on a 10 s lag (each leaving keyframe's
        marginal walks the window's whole chain of cliques), so a caller that does not use the
        track (``online``, ``--estimators smoother``) turns it off; the filtered output is the
        same either way, and ``final_state`` is still given."""
        super().__init__()
        self.cfg = cfg
        self.lagged = lagged
        self._pim_class = WheelGyroPreintegration if reference else _compiled_preintegration()
        self.stopped: str | None = None  # why it gave up (then every process call says so)
        # after a gap (_restart_after_gap): the new window's start, and the messages held
        self._restart: tuple | None = None
        self._restart_buf: list = []
        self._realign: tuple | None = None  # calibration kept while the GPS course re-aligns
        self._pim_compiled = self._pim_class is not WheelGyroPreintegration
        self.lag = float(lag if lag is not None else cfg.smoother.lag)
        if not (self.lag > 0.0 and math.isfinite(self.lag)):
            # gtsam would take it and fail later, deep inside an update (IndexError on 'x0')
            raise ValueError(f"smoother lag: expected seconds > 0, got {self.lag:g}")
        self.noise = noise or SmootherNoise.from_config(cfg)
        # as the EKFs: the config's map and its given start pose unless the caller passes them
        self.landmarks = dict(landmark_maps(cfg) if landmarks is None else landmarks)
        self.given_pose = initial_pose if initial_pose is not None else (
            tuple(cfg.initial_pose) if isinstance(cfg.initial_pose, (tuple, list)) else None)
        self.sensors: dict[str, SensorConfig] = {s.name: s for s in cfg.sensors}
        imus = [s for s in cfg.of_kind("imu") if "yaw_rate" in s.use]
        self.gyro_names = {s.name for s in imus}
        self.est_bias = any(s.gyro_bias == "estimate" for s in imus)
        self.fixed_bias = next((float(s.gyro_bias) for s in imus if s.gyro_bias != "estimate"),
                               0.0)
        heads = [s for s in cfg.of_kind("imu") if "yaw" in s.use]
        self.heading_sensors = bool(heads)
        self.est_hoff = any(s.heading_offset == "estimate" for s in heads)
        # odometry scale states, as in the EKFs (ekf_baseline.calibration): estimated when the
        # config states how well the geometry is known and a sensor gives odometry
        self.scale_prior = cfg.robot.scale_std if (
            cfg.of_kind("odometry") or cfg.of_kind("wheels")) else None
        self._scale_rw = (max(self.noise.scale_rw, walk_floor(max(self.scale_prior[:2])))
                          if self.scale_prior is not None else self.noise.fixed_rw)
        self.has_gps = bool(cfg.of_kind("gps"))
        # GPS sensors with time-correlated errors: name -> correlation time (s), see _gps
        self._gps_tau = {s.name: s.correlation_time for s in cfg.of_kind("gps")
                         if s.correlation_time > 0.0}
        self.odometry_held_back = bool(cfg.of_kind("odometry") or cfg.of_kind("wheels"))
        # keyframes closer than MIN_KEYFRAME_DT would break walk_floor's margin: at 75 Hz and
        # more (13 ms apart) gtsam declared the window indeterminate within 0.4 s
        self.keyframe_rate = min(cfg.smoother.keyframe_rate, 1.0 / MIN_KEYFRAME_DT)
        self.kf_policy = cfg.smoother.keyframe
        self._lagged = TrackBuilder()  # compact: (t, pose, pose cov) per keyframe
        self._reset_state()

    # --- set-up -----------------------------------------------------------------------------
    def _reset_state(self) -> None:
        self.smoother = gtsam.IncrementalFixedLagSmoother(self.lag, isam2_params())
        self.pim = self._pim_class(bg_lin=self.fixed_bias, keep_samples=False)
        self.initialised = False
        self.buffer: list = []  # measurements held until the heading is known
        self._buf_fixes: tuple[GpsFix, GpsFix] | None = None  # its first and last GPS fix
        self._buf_moving = False  # whether it holds an odometry speed
        self._buf_last: GpsFix | None = None  # its last fix
        self.k = -1  # index of the newest keyframe
        self.kf_t: dict[int, float] = {}  # keyframes in the window
        self.all_kf_t: dict[int, float] = {}  # every keyframe of the run (keep_all only)
        self.kf_state: np.ndarray | None = None  # newest keyframe's estimate
        self.kf_cov: np.ndarray | None = None  # its 3x3 pose marginal (world frame)
        self.last_t: float | None = None
        # held samples (zero-order hold): value, per-sample variance and density (var * period)
        self.v = self.wo = self.wg = None  # speed, odometry yaw rate, raw gyro yaw rate
        self.v_var = self.wo_var = self.wg_var = 0.0
        self.v_q = self.wo_q = self.wg_q = 0.0
        # each held sample's period (s) and the span it measures the twist over: its period up
        # to its stamp for odometry (held backward); for the gyro (held forward) from its stamp
        # to 1.5 periods past it (a sample that comes a little late does not make it stale)
        self.v_T = self.wo_T = self.wg_T = 0.1
        self.v_span = self.wo_span = self.wg_span = (-math.inf, math.inf)
        self.sample_T: dict[tuple[str, str], float] = {}  # (sensor, quantity) -> its period
        self.sample_t: dict[tuple[str, str], float] = {}  # (sensor, quantity) -> last stamp
        # integrals of the gyro and the odometry yaw rate dt since the newest keyframe while both
        # are held, that time, and the summed noise density of the two rates (see _advance)
        self._int_g = self._int_o = self._diff_t = self._diff_qg = self._diff_qo = 0.0
        self.heading: Heading | None = None
        # heading samples since the newest keyframe: sensor, the first one carried back to the
        # keyframe (rad), the sum of the others' wrapped differences from it, summed variances
        self._h_n = 0
        self._h_sensor, self._h_ref, self._h_sum, self._h_var = "", 0.0, 0.0, 0.0
        self._h_jb = self._h_jk = self._h_c1 = self._h_c2 = 0.0
        self._pending_cache = None  # (key, (state, pose cov)) of _with_pending_heading
        self._held: list = []  # messages since the last odometry sample, waiting for the next
        self._now = -math.inf  # stamp of the newest message seen
        self._lockout = Lockout()  # GPS gate streaks per sensor (ddfuse.estimation.lockout)
        self._landmark_t = -math.inf  # stamp of the newest landmark sighting fused
        # per GPS sensor with a correlation time: the stamps (sorted) of the fixes fused, from
        # the last one before the window's lag on (_gps_inflation, _gps_fused)
        self._gps_fused_t: dict[str, list[float]] = {}
        self._gps_ok_t = -math.inf  # stamp of the newest fix the gate accepted
        self._hgate: tuple | None = None  # the compass gate's per-keyframe terms (_heading_gate)
        self._full: np.ndarray | None = None  # newest keyframe's (DIM, DIM) marginal
        self._full_k = -1  # the keyframe whose marginal _full is (behind k after _new_keyframe)
        self._skip_in_batch: int | None = None  # pending factor the batch leaves out (_widen)
        self.pending_graph = gtsam.NonlinearFactorGraph()
        self.pending_values = gtsam.Values()
        self.pending_stamps: dict[int, float] = {}
        self._scale_belief: tuple[np.ndarray, np.ndarray] | None = None  # (k_v, k_w), 2x2 cov
        self._recovery_t: list[float] = []  # stamps of the recent re-initialisations
        if self.keep_all:
            self.all_graph = gtsam.NonlinearFactorGraph()
            self.all_values = gtsam.Values()

    @staticmethod
    def key(k: int) -> int:
        return gtsam.symbol("x", k)

    def _init_state(self, t: float, pose: tuple[float, float, float], pos_sigma: float,
                    psi_sigma: float, scale: tuple[np.ndarray, np.ndarray] | None = None,
                    calib: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """A new first keyframe at ``t``: ``pose`` with the given sigmas; the odometry scales
        from ``scale`` (value, 2x2 covariance) or their prior; with ``calib`` (value, 4x4
        covariance of bg, hoff, k_v, k_w) all four calibration states as they were learnt."""
        n = self.noise
        x0 = np.array([pose[0], pose[1], pose[2], self.v or 0.0, 0.0, self.fixed_bias, 0.0,
                       1.0, 1.0])
        if self.est_hoff and self.heading is not None:
            x0[HOFF] = wrap_angle(self.heading.yaw - pose[2])
        sig = [pos_sigma, pos_sigma, psi_sigma, n.init_v_sigma, n.init_w_sigma,
               n.init_bg_sigma if self.est_bias else n.fixed_sigma,
               n.init_hoff_sigma if self.est_hoff else n.fixed_sigma,
               n.fixed_sigma, n.fixed_sigma]
        cov0 = np.diag(np.square(sig))
        if calib is not None:
            x0[BG:], cov0[BG:, BG:] = calib
        elif scale is not None:  # a re-initialisation keeps the scales it had learnt
            x0[KV:], cov0[KV:, KV:] = scale
        elif self.scale_prior is not None:
            sd_v, sd_w, c_vw = self.scale_prior
            cov0[KV:, KV:] = ((max(sd_v, n.fixed_sigma) ** 2, c_vw),
                              (c_vw, max(sd_w, n.fixed_sigma) ** 2))
        self.k += 1  # keys stay unique across re-initialisations (the batch keeps them all)
        key = self.key(self.k)
        prior = gtsam.PriorFactorVector(key, x0, gtsam.noiseModel.Gaussian.Covariance(cov0))
        self._add(prior)
        self.pending_values.insert(key, x0)
        self.pending_stamps[key] = t
        self.kf_t[self.k] = t
        if self.keep_all:
            self.all_kf_t[self.k] = t
        self.kf_state = x0
        self.kf_cov = cov0[:3, :3].copy()
        self._full, self._full_k = cov0, self.k
        self.pim.reset(x0[BG], x0[KV], x0[KW])
        self._h_n = 0
        self.initialised = True
        self.last_t = t
        self._flush()

    def _add(self, f) -> None:
        self.pending_graph.add(f)

    # --- measurement handling ---------------------------------------------------------------
    def process(self, m) -> None:
        if self.stopped is not None:
            # kf_t was emptied when it stopped: say why, not KeyError
            raise RuntimeError(f"the smoother stopped earlier: {self.stopped}")
        if not is_finite(m):
            self.log.rejected[(m.sensor, "nonfinite")] += 1
            return
        if isinstance(m, (GpsFix, Heading)) and m.sensor not in self.sensors:
            # a hand-built measurement from a sensor the config does not have: its noise, gate
            # and offsets are unknown (the EKFs take such a one with defaults)
            self.log.rejected[(m.sensor, "not in the config")] += 1
            return
        if isinstance(m, GpsFix) and (m.enu is None or m.status < 0):
            self.log.rejected[(m.sensor, "no_fix" if m.status < 0 else "no_enu")] += 1
            return
        if not self.initialised:
            if self._restart is not None:
                self._restart_now(m)
            else:
                self._process_uninitialised(m)
            return
        if m.t - self._now > ODOMETRY_WAIT and math.isfinite(self._now):
            self._restart_after_gap(m.t)
            if self._restart is not None:
                self._restart_now(m)
                return
        self._now = max(self._now, m.t)
        if isinstance(m, (WheelOdometry, WheelSpeeds)):
            # Wheel odometry is the mean over the interval since its previous sample, stamped at
            # the interval's end (encoder counts over a control period): it is held BACKWARD
            # over that interval, so the messages that arrived inside it are integrated now.
            # Held forward instead, the odometry lags by a period (0.1 s at 10 Hz); on the
            # simulated husky that alone costs 45 % of the position RMSE.
            self._set_odometry(m)
            self._release_held()
            self._step(m)
            return
        if self.odometry_held_back:
            self._held.append(m)
            if m.t - self._held[0].t > ODOMETRY_WAIT:  # odometry stopped: hold the last forward
                self._release_held()
            return
        self._step(m)

    def _restart_after_gap(self, t: float) -> None:
        """No message from ``_now`` to ``t``: if the yaw rate held over that gap leaves the
        heading more uncertain than GAP_HEADING_SIGMA, end the window at the last message and
        start a new one at ``t``, from the last estimate carried over the gap by its twist,
        with the position and heading sigmas the gap leaves and the calibration states as
        learnt (their walks grown over the gap).

        One preintegrated factor across such a gap describes a relative pose whose rotation
        is unknown: linearised at the dead-reckoned guess, ISAM2's one step per update left the
        estimate metres off with a sigma of decimetres for seconds after 20-60 s gaps (the
        EKF, whose GPS and heading updates are linear in its state, settles at the first fix).
        The restarted window's first fix and heading sample are updates of that kind."""
        gap = t - self._now
        n, robot = self.noise, self.cfg.robot
        yaw = []
        for var, period, w in ((self.wg_var, self.wg_T, self.wg), (self.wo_var, self.wo_T,
                                                                  self.wo)):
            if w is not None:
                q = _twist_walk(robot.max_yaw_accel, n.yaw_acc, period)
                yaw.append(var * gap * gap + q * gap ** 3 / 3.0)
        if not yaw or min(yaw) < GAP_HEADING_SIGMA ** 2 or self.v is None:
            return
        self._release_held()
        if self.pim.n > 0:
            self._new_keyframe(self.last_t)
        self._flush()
        x, full = self.kf_state, self._full
        if full is None or full.shape != (DIM, DIM):
            return
        qv = _twist_walk(robot.max_accel, n.acc, self.v_T)
        v = float(x[3])
        grow_pos = self.v_var * gap * gap + qv * gap ** 3 / 3.0
        psi_var = float(full[2, 2]) + min(yaw)
        # a heading this unknown spreads the carried position along the arc of |v| gap
        pos_sigma = math.sqrt(max(float(full[0, 0]), float(full[1, 1])) + grow_pos
                              + (v * gap) ** 2 * min(psi_var, 1.0))
        px, py, ppsi = se2_step(float(x[0]), float(x[1]), float(x[2]), v, float(x[4]), gap)
        calib_cov = full[BG:, BG:].copy()
        calib_cov[0, 0] += (n.gyro_bias_rw if self.est_bias else n.fixed_rw) ** 2 * gap
        calib_cov[1, 1] += (n.heading_offset_rw if self.est_hoff else n.fixed_rw) ** 2 * gap
        self.log.note(t, f"no message for {gap:.1f} s: the heading after it is unknown (sigma "
                      f"{math.sqrt(psi_var):.2f} rad); the window ends there and a new one "
                      f"starts from the estimate carried over the gap (position sigma "
                      f"{pos_sigma:.1f} m)")
        self._capture_leaving(math.inf, newest=True)  # the window as it stood: all smoothed
        self._new_smoother()
        # the held samples described the time before the gap; the next ones start afresh
        self.v = self.wo = self.wg = None
        self._int_g = self._int_o = self._diff_t = 0.0
        self._held = []
        self._restart = ((px, py, wrap_angle(ppsi)), pos_sigma, min(math.sqrt(psi_var), math.pi),
                         (x[BG:].copy(), calib_cov))
        self._restart_buf = []
        self.initialised = False  # until _restart_now: the new window's first keyframe

    def _restart_now(self, m) -> None:
        """Open the window a gap ended (``_restart_after_gap``) at the first message after it,
        once a heading sample fixes the heading (the motion factors are then linearised at
        it), or after RESTART_HEADING_WAIT s without one (the carried heading, its wide
        sigma); then replay the messages held meanwhile."""
        buf = self._restart_buf
        buf.append(m)
        head = m if isinstance(m, Heading) else None
        if head is None and m.t - buf[0].t < RESTART_HEADING_WAIT and self.heading_sensors:
            return
        pose, pos_sigma, psi_sigma, (xc, cc) = self._restart
        if head is None and not self.heading_sensors and self.has_gps:
            # no absolute heading at all: the GPS course gives it, as at the start (the
            # calibration states kept); no estimate until then
            self._restart, self._restart_buf, self._realign = None, [], (xc, cc)
            self.heading = None
            self._now = -math.inf  # as at the start: no gap to check against until then
            for b in buf:
                self._process_uninitialised(b)
            return
        if head is not None:
            s = self.sensors[head.sensor]
            if s.heading_offset == "estimate":
                psi, var = head.yaw - xc[HOFF - BG], head.var + cc[HOFF - BG, HOFF - BG]
            else:
                psi, var = head.yaw - float(s.heading_offset), head.var
            pose, psi_sigma = (pose[0], pose[1], wrap_angle(psi)), math.sqrt(var)
        self._restart, self._restart_buf = None, []
        self.heading = None  # the pre-gap sample must not set the new keyframe's offset
        self._init_state(buf[0].t, pose, pos_sigma, psi_sigma, calib=(xc, cc))
        self._now = buf[0].t
        for b in buf:
            self.process(b)

    def _release_held(self) -> None:
        """Use the messages that were waiting for an odometry sample, in order."""
        held, self._held = self._held, []
        for b in held:
            self._step(b)

    def _set_odometry(self, m) -> None:
        if isinstance(m, WheelSpeeds):
            self._wheel_speeds(m)
            return
        if m.v is not None:
            self.v, self.v_var, self.v_T = m.v, m.v_var, self._period(m, "v")
            self.v_q, self.v_span = m.v_var * self.v_T, (m.t - self.v_T, m.t)
        if m.yaw_rate is not None:
            self.wo, self.wo_var, self.wo_T = m.yaw_rate, m.yaw_rate_var, self._period(m, "w")
            self.wo_q, self.wo_span = m.yaw_rate_var * self.wo_T, (m.t - self.wo_T, m.t)

    def _step(self, m) -> None:
        """Integrate up to ``m.t`` and use ``m`` (odometry already set by ``process``)."""
        self._advance(m.t)
        if isinstance(m, GyroYawRate):
            if m.sensor in self.gyro_names:
                self.wg, self.wg_var, self.wg_T = m.yaw_rate, m.var, self._period(m, "w")
                self.wg_q, self.wg_span = m.var * self.wg_T, (m.t, m.t + 1.5 * self.wg_T)
        elif isinstance(m, Heading):
            self.heading = m
            if self._h_n == 0 or m.sensor == self._h_sensor:
                pim = self.pim
                u = m.yaw - pim.dpsi  # carried back to the interval's start
                if not self._heading_gate(m, u):
                    return
                if self._h_n == 0:
                    self._h_sensor, self._h_ref, self._h_sum, self._h_var = m.sensor, u, 0.0, 0.0
                    self._h_jb = self._h_jk = self._h_c1 = self._h_c2 = 0.0
                self._h_sum += wrap_angle(u - self._h_ref)
                self._h_var += m.var
                # what the carried yaw depends on: the gyro bias and yaw-rate scale (first
                # order), and the yaw noise integrated up to the sample (its index-weighted
                # sum gives the mean's variance, ``_pending_heading``)
                self._h_jb += pim.j_p
                self._h_jk += pim.kw_p
                c = pim.c_pp
                self._h_c1 += c
                self._h_c2 += self._h_n * c
                self._h_n += 1
        elif isinstance(m, (GpsFix, LandmarkObservation)):
            self._absolute(m)
            return
        if m.t - self.kf_t[self.k] >= 1.0 / self.keyframe_rate and self.pim.n > 0:
            self._new_keyframe(m.t)
            self._flush()

    def _period(self, m, quantity: str) -> float:
        """The period of a held sample (s): the time since the same sensor's previous sample of
        this quantity, clipped to [1 ms, 1 s]; its noise density is var * period. After a gap
        (more than twice the previous period) the previous period: the sample describes its
        own control period, not the gap, which ``_stale`` accounts for."""
        key = (m.sensor, quantity)
        last = self.sample_t.get(key)
        self.sample_t[key] = m.t
        prev = self.sample_T.get(key)
        if last is not None and m.t - last < 1e-3 and prev is not None:
            # a repeated (or re-ordered) stamp says nothing of the rate; taken as a 1 ms period
            # it made every later period "a gap" and froze the density at 1 ms for the run
            return prev
        period = min(max(m.t - last, 1e-3), 1.0) if last is not None else 0.1
        if prev is not None and period > 2.0 * prev:
            return prev
        self.sample_T[key] = period
        return period

    def _stale(self, var: float, period: float, acc: float | None, default: float,
               span: tuple[float, float], a: float, b: float) -> tuple[float, float]:
        """What holding a sample over [a, b] outside ``span`` (the time it measures the twist
        over) adds: (density to add to its var * period for this step, (unit)^2 s; its variance
        as a measurement of the twist at b, (unit)^2).

        Outside its span the sample's error e (variance ``var``) no longer averages out with the
        next sample's: it is the same for the whole hold, and the twist itself moves away from
        the sample as a random walk with the acceleration density q (``acc``^2 ``period`` from
        the robot's acceleration limit ``acc``, else ``default``^2, as the EKFs' twist
        densities). Integrated over an age tau outside the span, the error is
        var tau^2 + q tau^3 / 3; a step adds the difference between its ends' ages, as a
        density over the step (before the span for odometry held backward over a gap, after it
        for a sample held forward). Zero inside the span."""
        since, until = span
        if since <= a and b <= until:
            return 0.0, var
        q = _twist_walk(acc, default, period)

        def grown(tau: float) -> float:
            return var * tau * tau + q * tau ** 3 / 3.0

        before = grown(max(since - a, 0.0)) - grown(max(since - b, 0.0))
        after = grown(max(b - until, 0.0)) - grown(max(a - until, 0.0))
        return (before + after) / (b - a), var + q * max(b - until, 0.0)

    def _wheel_speeds(self, m: WheelSpeeds) -> None:
        self.v, self.wo, self.v_var, self.wo_var = m.twist(self.cfg.robot.wheel_radius,
                                                           self.cfg.robot.track_width)
        self.v_T = self._period(m, "v")
        self.v_q, self.v_span = self.v_var * self.v_T, (m.t - self.v_T, m.t)
        self.wo_T = self._period(m, "w")
        self.wo_q, self.wo_span = self.wo_var * self.wo_T, (m.t - self.wo_T, m.t)

    def _yaw_rate(self, qg: float, qo: float, vg: float, vo: float
                  ) -> tuple[float, float, float, float, float] | None:
        """The yaw rate to integrate, fusing the gyro and the odometry yaw rate when both are
        held, given their densities ``qg``, ``qo`` and per-sample variances ``vg``, ``vo`` for
        this step: (gyro part rad/s, odometry part rad/s, per-sample variance, density,
        gyro-bias gain). The gyro part carries the bias with that gain, the odometry part the
        odometry's yaw-rate scale (``ddfuse.factors.preintegration``)."""
        wg, wo = self.wg, self.wo
        if wg is not None and wo is not None:
            a = qo / (qo + qg)  # the gyro's weight
            return a * wg, (1.0 - a) * wo, vg * vo / (vg + vo), qg * qo / (qg + qo), a
        if wg is not None:
            return wg, 0.0, vg, qg, 1.0
        if wo is not None:
            return 0.0, wo, vo, qo, 0.0
        return None

    def _advance(self, t: float) -> None:
        """Integrate the held (v, w) from the last sample time up to ``t``."""
        a = self.last_t
        dt = t - a
        if dt <= 0.0:
            return
        if self.v is None:
            # No odometry yet: the interval waits for the first sample, which is then held
            # back over it (grown as a stale sample, ``_stale``). Moving last_t on instead left
            # the first keyframe interval's motion out of the preintegration: a 0.4 s factor
            # across 1.2 s, which gtsam declared indeterminate.
            return
        sv, so, sg = self.v_span, self.wo_span, self.wg_span
        if sv[0] <= a and t <= sv[1] and so[0] <= a and t <= so[1] and sg[0] <= a and \
                t <= sg[1]:  # every held sample fresh (almost always): no calls
            qv = qo = qg = 0.0
            v_var, vo, vg = self.v_var, self.wo_var, self.wg_var
        else:
            robot, n = self.cfg.robot, self.noise
            qv, v_var = self._stale(self.v_var, self.v_T, robot.max_accel, n.acc, sv, a, t)
            qo, vo = self._stale(self.wo_var, self.wo_T, robot.max_yaw_accel, n.yaw_acc, so,
                                 a, t) if self.wo is not None else (0.0, 0.0)
            qg, vg = self._stale(self.wg_var, self.wg_T, robot.max_yaw_accel, n.yaw_acc, sg,
                                 a, t) if self.wg is not None else (0.0, 0.0)
        fresh = qo == qg == 0.0
        yr = self._yaw_rate(self.wg_q + qg, self.wo_q + qo, vg, vo)
        if yr is not None:
            wg, wo, w_var, w_q, gain = yr
            pim = self.pim
            pim.integrate(dt, self.v, wg, (self.v_q + qv) / dt, w_q / dt, gain, wo)
            # The keyframe's v, w rows compare with the last sample itself, not with its share
            # of one integration step.
            pim.last_var_v, pim.last_var_w = v_var, w_var
            # (a stale sample's difference would carry the twist's change, not the bias)
            if 0.0 < gain < 1.0 and fresh:
                # gyro - k_w odometry = bias + noise, independent of the fused mean integrated
                # above: the bias information the fusion would otherwise throw away
                self._int_g += self.wg * dt
                self._int_o += self.wo * dt
                self._diff_t += dt
                self._diff_qg, self._diff_qo = self.wg_q, self.wo_q
        self.last_t = t

    def _absolute(self, m) -> None:
        t_kf = self.kf_t[self.k]
        if self.v is None and abs(m.t - t_kf) >= MIN_KEYFRAME_DT:
            # No odometry yet in this window (its sensors started first, or it has not resumed
            # after a gap): nothing relates a measurement away from the first keyframe to it.
            # Attached with the keyframe's guessed twist, a few such fixes made gtsam declare
            # the system indeterminate (re-initialisations; five stopped the smoother).
            self.log.rejected[(m.sensor, "before odometry began")] += 1
            return
        if m.t - t_kf >= (MIN_KEYFRAME_DT if self.kf_policy == "gps" else 1e9) and self.pim.n > 0:
            self._new_keyframe(m.t)
        k = self.k
        # A delayed measurement goes to the keyframe nearest in time inside the window; one
        # older than the lag (gtsam's own cut) is dropped, however near a keyframe it is.
        if m.t < self.kf_t[k] - MIN_KEYFRAME_DT:
            cut = self.kf_t[k] - self.lag
            window = [j for j, tj in self.kf_t.items() if tj >= cut]
            if m.t < cut or not window:
                self.log.rejected[(m.sensor, "older than the smoother lag")] += 1
                self.log.note(m.t, f"{m.sensor}: measurement {self.kf_t[self.k] - m.t:.2f} s "
                              f"older than the newest keyframe, beyond the {self.lag:g} s lag, "
                              "dropped")
                return
            k = min(window, key=lambda j: abs(self.kf_t[j] - m.t))
        dt = m.t - self.kf_t[k]
        if isinstance(m, GpsFix):
            # A fix with a configured delay is the antenna position that long before its stamp:
            # the GPS factor's motion compensation carries it from the keyframe (dt < 0).
            self._gps(m, k, dt - self.sensors[m.sensor].delay)
        else:
            self._landmark(m, k, dt)
        self._flush()

    def _gps(self, m: GpsFix, k: int, dt: float) -> None:
        s = self.sensors[m.sensor]
        e, n = m.enu[0], m.enu[1]
        if k == self.k and self.kf_state is not None:
            cov = self._gps_cov(m, self.kf_state, dt)
            nis = self._gps_innovation(m, s.lever_arm, dt, cov)
            verdict = self._gate(m, s, nis)
            if verdict == _REJECT:
                return
            if verdict == _RECOVER:
                k = self._widen(m, s, dt, cov)  # a keyframe at the newest's stamp: same dt
        else:
            cov = self._delayed_gps(m, s, k, dt)
            if cov is None:
                return
        # Time-correlated errors (the sensor's correlation_time): the factor takes the fix's
        # own covariance times f for the time since the previous fused fix (what the motion
        # carry of _gps_cov adds stays as it is); the gate, the logged innovation and a
        # lock-out's widening above used the fix's own. f = 1 without a correlation time.
        f = 1.0
        if m.sensor in self._gps_tau:
            f = self._gps_inflation(m)
            self._gps_fused(m)
        if f != 1.0:
            cov = cov + (f - 1.0) * np.asarray(m.cov[:2, :2], dtype=float)
        if s.lever_arm == (0.0, 0.0) and abs(dt) < 1e-9 and cov[0, 1] == 0.0:
            # On the keyframe and without a lever arm the fix is linear in the state: the
            # built-in prior with zero precision on unmeasured components is the same factor
            # at a fraction of a CustomFactor's cost (design study, design E).
            prec = np.zeros(DIM)
            prec[0], prec[1] = 1.0 / cov[0, 0], 1.0 / cov[1, 1]
            target = np.zeros(DIM)
            target[0], target[1] = e, n
            # the kernel's threshold scaled by 1/sqrt(f) (_robustify): the same residuals in
            # metres as without the inflation, those the gate accepts given full weight
            model = _robustify(self.cfg, s, gtsam.noiseModel.Diagonal.Precisions(prec), 2, f)
            self._add(gtsam.PriorFactorVector(self.key(k), target, model))
        else:
            # the fix's east/north correlation kept (a receiver's ellipse is rarely a circle)
            model = (gtsam.noiseModel.Diagonal.Variances(np.array((cov[0, 0], cov[1, 1])))
                     if cov[0, 1] == 0.0 else gtsam.noiseModel.Gaussian.Covariance(cov))
            self._add(gps_factor(self.key(k), e, n, _robustify(self.cfg, s, model, 2, f),
                                 s.lever_arm, dt))

    def _gps_inflation(self, m: GpsFix) -> float:
        """The factor f (>= 1) by which fix ``m``'s covariance is inflated for fusion
        (``estimation.gps_correlation.inflation``): its sensor's correlation time, and the time
        to the nearest earlier fix of that sensor fused; for a fix that comes late (older than
        one fused), the nearest fused fix on either side. 1 without a correlation time or
        before the sensor's first fused fix."""
        tau = self._gps_tau.get(m.sensor)
        fused = self._gps_fused_t.get(m.sensor)
        if tau is None or not fused:
            return 1.0
        if m.t >= fused[-1]:
            dt = m.t - fused[-1]
        else:
            i = bisect.bisect_left(fused, m.t)
            dt = min(abs(m.t - fused[j]) for j in (i - 1, i) if 0 <= j < len(fused))
        return gps_correlation.inflation(dt, tau)

    def _gps_fused(self, m: GpsFix) -> None:
        """Record fix ``m`` (of a sensor with a correlation time) as fused: its GPS factor is
        built. Stamps older than the window's lag are dropped but the last of them: a late fix
        is at most the lag older than the newest keyframe (``_absolute``), so its nearest fused
        fix on either side is still there, and memory stays bounded."""
        fused = self._gps_fused_t.setdefault(m.sensor, [])
        if not fused or m.t >= fused[-1]:
            fused.append(m.t)
        else:
            bisect.insort(fused, m.t)
        cut = self.kf_t[self.k] - self.lag
        if len(fused) > 1 and fused[1] < cut:
            drop = bisect.bisect_left(fused, cut) - 1  # keep the last stamp before the cut
            del fused[:drop]

    def _gps_cov(self, m: GpsFix, x: np.ndarray, dt: float) -> np.ndarray:
        """The fix's east/north covariance (2, 2), m^2, as a measurement of keyframe state
        ``x`` carried ``dt`` s along its constant twist: the fix's own plus what the body's
        motion does off that twist over |dt| -- slip (pose_noise) and the twist's random walk
        (the held-sample densities): along the heading  l^2 |dt| + q_v |dt|^3 / 3, across it
        t^2 |dt| + v^2 (h^2 |dt|^3 / 3 + q_w |dt|^5 / 20). Without it a fix carried 2 s onto a
        keyframe (``keyframe: rate`` at 0.5 Hz) was trusted to its 1 m while the carry alone
        was 0.14 m RMS off with the true twist, 2.5 m at worst at 4 s: NEES 10.6."""
        cov = np.array(m.cov[:2, :2], dtype=float)
        a = abs(dt)
        if a < 1e-9:
            return cov
        nz, robot = self.noise, self.cfg.robot
        pl, pt, ph = nz.pose_noise
        qv = _twist_walk(robot.max_accel, nz.acc, self.v_T)
        qw = _twist_walk(robot.max_yaw_accel, nz.yaw_acc,
                         self.wg_T if self.wg is not None else self.wo_T)
        v = float(x[3])
        along = pl * pl * a + qv * a ** 3 / 3.0
        across = pt * pt * a + v * v * (ph * ph * a ** 3 / 3.0 + qw * a ** 5 / 20.0)
        c, sn = math.cos(float(x[PSI])), math.sin(float(x[PSI]))
        cov[0, 0] += along * c * c + across * sn * sn
        cov[1, 1] += along * sn * sn + across * c * c
        cov[0, 1] += (along - across) * c * sn
        cov[1, 0] = cov[0, 1]
        return cov

    def _delayed_gps(self, m: GpsFix, s: SensorConfig, k: int, dt: float) -> np.ndarray | None:
        """A fix for an older keyframe ``k`` of the window: gated against that keyframe's
        marginal, as a fix on time is against the newest's (an outlier 1 s late was fused),
        and logged for the NIS. The lock-out is left alone: it is about the current estimate.
        Returns the fix's covariance for the factor, or None when the gate rejects it."""
        try:
            key = self.key(k)
            x = self.smoother.calculateEstimateVector(key)
            full = self.smoother.marginalCovariance(key)
        except (RuntimeError, IndexError, ValueError):
            return self._gps_cov(m, self.kf_state, dt)  # not in the smoother yet: ungated
        cov = self._gps_cov(m, x, dt)
        nis = self._gps_innovation(m, s.lever_arm, dt, cov, x, full)
        if s.gate is not None and nis > _gate_radius(s.gate, 2) ** 2:
            self.log.rejected[(m.sensor, "gate")] += 1
            self.log.innovations[-1].accepted = False
            return None
        return cov

    def _gate(self, m: GpsFix | LandmarkObservation, s: SensorConfig, nis: float) -> int:
        """The gate's verdict on a fix or a landmark sighting with innovation ``nis`` (2 dof; a
        range-only sighting 1), as in the EKFs: _ACCEPT, _REJECT (logged, counted) or _RECOVER,
        a lock-out (``ddfuse.estimation.lockout``) that nothing of the other kind accepted since the
        rejections began contradicts (landmark sightings for the GPS, GPS fixes for the
        landmarks): the estimate, not the sensor, is wrong; the caller widens the belief."""
        gps = isinstance(m, GpsFix)
        dim = 2 if gps or m.has_bearing else 1
        if s.gate is None or nis <= _gate_radius(s.gate, dim) ** 2:
            self._lockout.accepted(m.sensor)
            if gps:
                self._gps_ok_t = m.t
            return _ACCEPT
        if self._lockout.rejected(m.sensor, m.t):
            count, first = self._lockout.streak(m.sensor)
            if (self._landmark_t if gps else self._gps_ok_t) < first:
                return _RECOVER
            wait = self._lockout.corroborated(m.sensor, m.t)
            what, other, mine = (("fixes", "landmark sightings", "the GPS disagrees") if gps
                                 else ("sightings", "GPS fixes", "the landmarks disagree"))
            self.log.note(m.t, f"{m.sensor}: {count} {what} in a row failed the gate over "
                          f"{m.t - first:.1f} s while {other} were fused: {mine} with them, "
                          f"not recovering (checked again in {wait:.0f} s)")
        self.log.rejected[(m.sensor, "gate")] += 1
        self.log.innovations[-1].accepted = False
        return _REJECT

    def _heading_gate(self, m: Heading, u: float) -> bool:
        """Whether heading sample ``m`` (``u``: its yaw carried back to the newest keyframe)
        passes its sensor's chi-square gate, as in the EKFs: against the keyframe's marginal,
        the yaw preintegrated since it and the sample's own variance. A lock-out (a run of
        rejections, ``ddfuse.estimation.lockout``) with GPS fixes or landmark sightings fused since
        it began means the compass is the outlier (a wrong fixed offset, a magnetic
        disturbance): it stays gated out, with a note. Without them the estimate is lost: the
        belief is widened (``_widen_link``) and the sample used. Before, a compass 0.35 rad off
        its configured fixed offset was fused whole, dragged the heading 20 deg off and the
        GPS gate then locked out (3 re-initialisations; 2.6 m against the EKFs' 0.24 m)."""
        full = self._full
        c = self._hgate
        if c is None or c[0] is not full or c[1] != m.sensor:
            # what the test needs from the newest keyframe, once per update of it (not per
            # sample: 50-100 Hz)
            s = self.sensors.get(m.sensor)
            if s is None or s.gate is None or full is None or full.shape != (DIM, DIM):
                c = (full, m.sensor, 0.0, 0.0, 0.0, math.inf, False)
            else:
                x, use_offset = self.kf_state, s.heading_offset == "estimate"
                if use_offset:
                    pred = float(x[PSI] + x[HOFF])
                    hph = float(full[PSI, PSI] + 2.0 * full[PSI, HOFF] + full[HOFF, HOFF])
                    offset = 0.0
                else:
                    pred, hph = float(x[PSI]), float(full[PSI, PSI])
                    offset = float(s.heading_offset)
                c = (full, m.sensor, pred, hph, offset, _gate_radius(s.gate, 1) ** 2,
                     use_offset)
            self._hgate = c
        _, _, pred, hph, offset, rad2, use_offset = c
        if rad2 == math.inf:  # no gate for this sensor (or no marginal yet)
            return True
        r = m.var + self.pim.c_pp
        y = (u - offset - pred + math.pi) % (2.0 * math.pi) - math.pi  # wrap_angle, inlined
        key = (m.sensor, "heading")
        if y * y <= rad2 * (hph + r):
            self._lockout.accepted(key)
            return True
        if self._lockout.rejected(key, m.t):
            count, first = self._lockout.streak(key)
            if max(self._gps_ok_t, self._landmark_t) < first:  # lost: recover, use the sample
                H = np.zeros((1, DIM))
                H[0, PSI] = 1.0
                if use_offset:
                    H[0, HOFF] = 1.0
                # the heading is lost, not the calibration: the gyro bias and the offset are
                # held (widened x8.7e5 with the rest after a 30 s clock step, the offset's prior
                # against its walk made gtsam's Cholesky refuse the window, see walk_floor)
                self._widen_link(key, m.t, H, np.array([y]), np.array([[r]]), "heading sample",
                                 calibration=False)
                return True
            wait = self._lockout.corroborated(key, m.t)
            self.log.note(m.t, f"{m.sensor}: {count} heading samples in a row failed the gate "
                          f"over {m.t - first:.1f} s while GPS fixes or landmark sightings were "
                          f"fused: the heading disagrees with them, not recovering (checked "
                          f"again in {wait:.0f} s)")
        self.log.rejected[(m.sensor, "gate")] += 1
        return False

    def _widen(self, m: GpsFix, s: SensorConfig, dt: float, r: np.ndarray) -> int:
        """Recover from a gate lock-out on fix ``m`` (``dt`` s from the newest keyframe) as the
        EKFs do, by widening the belief by the smallest factor alpha that makes the fix's
        innovation ordinary (``estimation.lockout.inflation``), here inside the graph: the fix
        goes on a new keyframe at the same stamp, tied to the newest one by a zero-mean link with
        covariance (alpha - 1) times the newest keyframe's marginal (the odometry scales
        excepted), so its marginal is the widened one while the window stays whole (the lagged
        output keeps smoothing across the jump). The batch ties the two keyframes tightly
        instead: the robot did not jump, the filter was lost. Returns the new keyframe."""
        self._flush()  # the newest keyframe's motion and heading factors, without the fix
        pred, H = gps_predict_jacobian(self.kf_state, s.lever_arm, dt)
        y = np.array((m.enu[0] - pred[0], m.enu[1] - pred[1]))
        return self._widen_link(m.sensor, m.t, H, y, r, "fix")

    def _newest_marginal(self) -> np.ndarray:
        """The newest keyframe's marginal (DIM, DIM) as far as it is known: gtsam's after an
        update; between a new keyframe and its update the composed pose covariance with the
        previous keyframe's twist and calibration blocks (cross terms with the pose left out)."""
        full = self._full
        if self._full_k == self.k and full is not None and full.shape == (DIM, DIM):
            return full
        out = np.zeros((DIM, DIM))
        if full is not None and full.shape == (DIM, DIM):
            out[3:, 3:] = full[3:, 3:]
        out[:3, :3] = self.kf_cov
        return out

    def _widen_link(self, key, t_m: float, H: np.ndarray, y: np.ndarray, R: np.ndarray,
                    what: str, calibration: bool = True) -> int:
        """Widen the newest keyframe's belief by the smallest alpha that makes innovation ``y``
        of a measurement (H (m, DIM), R (m, m)) at ``t_m`` ordinary (``_widen``), the lock-out
        of ``key`` (a sensor, or (sensor, kind)) recovered: P + (alpha - 1) P_ww, so
        S(alpha) = alpha A + (H P H^T - A + R) with A = H_w P_ww H_w^T. Widened: the pose and
        twist, and with ``calibration`` the gyro bias and heading offset where they are
        estimated. A state held at its value is never widened: its prior against its 1e-6 walk
        is what gtsam's Cholesky then refuses at the next short keyframe interval (Husky bag
        without a compass: the closing keyframe failed). Returns the new keyframe."""
        x, full = self.kf_state, self._full
        w = [0, 1, 2, 3, 4]
        if calibration and self.est_bias:
            w.append(BG)
        if calibration and self.est_hoff:
            w.append(HOFF)
        w = np.array(w)
        hph = H @ full @ H.T
        A = H[:, w] @ full[np.ix_(w, w)] @ H[:, w].T
        alpha, rest = inflation(y, A, R + hph - A)
        if alpha <= 1.0 and rest is None:
            # already ordinary against the newest marginal (the gate judged an older one): a
            # link of only fixed_sigma would tie the keyframes at 1e-4 whatever their sigma (30
            # m after a heading recovery: gtsam refused that pivot)
            self._lockout.recovered(key, t_m)
            return self.k
        # The GPS widens every estimated state but the odometry scales, as in the EKFs (which
        # widen all but the scales too): H observes none of them, so alpha is the EKF's.
        # Widened too, the scales explain the jump: on the Husky bag with a 0.3 m GPS sigma k_v
        # went to 0.44, then the system was indeterminate. (Widening only x, y, psi, v, w
        # instead: Husky hold-out 1.001 m lagged, not 0.999, session 5, when the scales still
        # walked without a configured uncertainty.)
        q = np.zeros((DIM, DIM))
        ww = np.ix_(w, w)
        q[ww] = (alpha - 1.0) * full[ww]
        if rest is not None:
            d = np.linalg.pinv(H[:, w]) @ rest
            q[ww] += np.outer(d, d)
        q = 0.5 * (q + q.T) + np.eye(DIM) * self.noise.fixed_sigma ** 2
        i, t = self.k, self.kf_t[self.k]
        j = self.k = i + 1
        if self.keep_all:
            # the whole-run solve keeps the chain: the robot did not jump, the filter was lost
            self.all_graph.add(gtsam.BetweenFactorVector(
                self.key(i), self.key(j), np.zeros(DIM),
                gtsam.noiseModel.Isotropic.Sigma(DIM, self.noise.fixed_sigma)))
            self._skip_in_batch = self.pending_graph.size()
        self._add(gtsam.BetweenFactorVector(self.key(i), self.key(j), np.zeros(DIM),
                                            gtsam.noiseModel.Gaussian.Covariance(q)))
        self.pending_values.insert(self.key(j), np.asarray(x, dtype=float))
        self.pending_stamps[self.key(j)] = t
        del self.kf_t[i]  # the same instant as j: only j is output
        self.kf_t[j] = t
        if self.keep_all:
            del self.all_kf_t[i]
            self.all_kf_t[j] = t
        self.kf_cov = full[:3, :3] + q[:3, :3]
        self._full, self._full_k = full + q, j
        sensor = key[0] if isinstance(key, tuple) else key
        count, first = self._lockout.streak(key)
        wait = self._lockout.recovered(key, t_m)
        self.log.rejected[(sensor, "lockout_recovery")] += 1
        self.log.note(t_m, f"{sensor}: gate lock-out after {count} rejections over "
                      f"{t_m - first:.1f} s; belief widened x{alpha:.3g} and the {what} "
                      f"fused (next recovery not before {wait:.0f} s)")
        return j

    def _gps_innovation(self, m, lever, dt, r: np.ndarray, st: np.ndarray | None = None,
                        full: np.ndarray | None = None) -> float:
        """Innovation of the fix against the prediction before it is fused (logged for NIS),
        with the GPS factor's own model (``gps_predict_jacobian``) and measurement covariance
        ``r``; at keyframe state ``st`` with marginal ``full``, by default the newest's.
        Returns its NIS."""
        if st is None:
            st, full = self.kf_state, self._newest_marginal()
        if dt == 0.0 and lever == (0.0, 0.0):  # the position itself (most fixes, 15 us less)
            res = np.array((m.enu[0] - st[0], m.enu[1] - st[1]))
            cov = full[:2, :2] + r
        else:
            pred, h = gps_predict_jacobian(st, lever, dt)
            res = np.array((m.enu[0] - pred[0], m.enu[1] - pred[1]))
            cov = h[:, :5] @ full[:5, :5] @ h[:, :5].T + r
        a, b, d = cov[0, 0], cov[0, 1], cov[1, 1]
        det = a * d - b * b
        r0, r1 = res
        nis = (d * r0 * r0 - 2 * b * r0 * r1 + a * r1 * r1) / det
        self.log.innovations.append(Innovation(m.t, m.sensor, "gps", res, cov, float(nis), True))
        return float(nis)

    def _landmark(self, m: LandmarkObservation, k: int, dt: float) -> None:
        """A sighting ``dt`` s after keyframe ``k``: a range/bearing (or range) factor from the
        keyframe pose carried along its twist to the sighting (``ddfuse.factors.landmark``), if it
        passes its sensor's chi-square gate as in the landmark EKF (``_gate``; a
        delayed one against its own keyframe's marginal). Before, every sighting was fused,
        the robust kernel its only guard: 5 % misidentified landmarks on seed002 made the
        lagged output 3x worse (0.008 -> 0.024 m) while the EKF's gate kept it at 0.011."""
        lm = self.landmarks.get(m.landmark_id)
        if lm is None:
            self.log.rejected[(m.sensor, LANDMARK_NOT_IN_MAP)] += 1
            return
        s = self.sensors[m.sensor]
        if k == self.k and self.kf_state is not None:
            inn = self._landmark_innovation(m, lm, dt, self.kf_state, self._newest_marginal())
            if inn is not None:
                verdict = self._gate(m, s, inn[0])
                if verdict == _REJECT:
                    return
                if verdict == _RECOVER:
                    self._flush()  # as _widen: the keyframe's own factors first
                    again = self._landmark_innovation(m, lm, dt, self.kf_state, self._full,
                                                      log=False)
                    if again is not None:  # (None: on top of the landmark, nothing to widen)
                        _, y, H, R = again
                        k = self._widen_link(m.sensor, m.t, H, y, R, "sighting")
        elif k != self.k and s.gate is not None:
            try:
                key = self.key(k)
                inn = self._landmark_innovation(m, lm, dt,
                                                self.smoother.calculateEstimateVector(key),
                                                self.smoother.marginalCovariance(key))
            except (RuntimeError, IndexError, ValueError):
                inn = None  # not in the smoother yet: ungated
            if inn is not None and inn[0] > _gate_radius(s.gate, len(inn[1])) ** 2:
                self.log.rejected[(m.sensor, "gate")] += 1
                self.log.innovations[-1].accepted = False
                return
        if m.has_bearing:
            sig = (math.sqrt(m.range_var), math.sqrt(m.bearing_var))
            f = range_bearing_factor(self.key(k), lm, m.range, m.bearing,
                                     _robust(self.cfg, s, sig), dt=dt)
        else:
            f = range_factor(self.key(k), lm, m.range,
                             _robust(self.cfg, s, (math.sqrt(m.range_var),)), dt=dt)
        self._add(f)
        self._landmark_t = m.t

    def _landmark_innovation(self, m: LandmarkObservation, lm, dt: float, st: np.ndarray,
                             full: np.ndarray, log: bool = True):
        """Range (and bearing) innovation of a sighting ``dt`` s after a keyframe with state
        ``st`` and marginal ``full`` (DIM, DIM), before it is fused: the model of
        ``ddfuse.factors.landmark`` (the pose carried along the keyframe's twist), its covariance
        through the carry's Jacobian on pose and twist. Logged for the NIS unless ``log`` is
        False. Returns (nis, y (m,), H (m, DIM), R (m, m)), None on top of the landmark."""
        st = st.tolist() if hasattr(st, "tolist") else list(st)
        x, y, psi, j = se2_step_jac(st[0], st[1], st[2], st[3], st[4], dt)
        dx, dy = lm[0] - x, lm[1] - y
        q = dx * dx + dy * dy
        r = math.sqrt(q)
        if r < 1e-6:
            return None  # on top of the landmark: no bearing, and the range Jacobian is undefined
        hp = np.array(((-dx / r, -dy / r, 0.0), (dy / q, -dx / q, -1.0)))
        H = np.zeros((2, DIM))
        H[:, :5] = hp @ np.array(j)
        res = np.array((m.range - r, wrap_angle(m.bearing - math.atan2(dy, dx) + psi)))
        R = np.diag((m.range_var, m.bearing_var))
        if not m.has_bearing:
            H, res, R = H[:1], res[:1], R[:1, :1]
        cov = H[:, :5] @ full[:5, :5] @ H[:, :5].T + R
        nis = float(res @ np.linalg.solve(cov, res))
        if log:
            self.log.innovations.append(Innovation(m.t, m.sensor, "landmark", res, cov, nis,
                                                   True))
        return nis, res, H, R

    def _new_keyframe(self, t: float) -> None:
        if self._h_n:
            self._log_heading_innovation(t)
        i, j = self.k, self.k + 1
        ki, kj = self.key(i), self.key(j)
        n = self.noise
        pim = self._frozen()
        self._add(preintegrated_factor(
            ki, kj, pim,
            gyro_bias_rw=n.gyro_bias_rw if self.est_bias else n.fixed_rw,
            heading_offset_rw=self._hoff_rw(),
            pose_noise=n.pose_noise,
            scale_rw=self._scale_rw))
        guess = pim.predict(self.kf_state)
        pose, cov = _compose(self.kf_state, self._delta(self.kf_state, pim), pim.covariance,
                             self.kf_cov)
        self.pending_values.insert(kj, guess)
        self.pending_stamps[kj] = t
        self.kf_t[j] = t
        if self.keep_all:  # only the batch needs every stamp; the window's are in kf_t
            self.all_kf_t[j] = t
        self.k = j
        self.kf_state, self.kf_cov = guess, cov
        rows = []
        if self._h_n:
            # the interval's heading samples, each carried to this keyframe by the
            # preintegrated yaw since it, averaged: one factor
            h, z, var = self._pending_heading(pim)
            rows.append((h, z, math.sqrt(var), True))
            self._h_n = 0
        if self.est_bias and self._diff_t > 0.0:
            # mean gyro - k_w x mean odometry yaw rate over the interval: a measurement of the
            # gyro bias with variance density / time
            T = self._diff_t
            # not a linear row: its sigma depends on k_w (errors in both rates, see the factor)
            self._add(bias_difference_factor(kj, self._int_g / T, self._int_o / T,
                                             math.sqrt(self._diff_qg / T),
                                             math.sqrt(self._diff_qo / T)))
        if rows:
            # linear in the state: one C++ factor, no Python callback per relinearisation
            # (ddfuse.factors.linear)
            self._add(linear_state_factor(kj, rows, guess))
        self._int_g = self._int_o = self._diff_t = 0.0
        self.pim.reset(guess[BG], guess[KV], guess[KW])

    def _log_heading_innovation(self, t: float) -> None:
        """The interval's averaged heading measurement (closed at ``t``) against the state
        before it is fused, for the NIS: carried back to the newest keyframe, whose full
        marginal gtsam gave (psi and the offset are strongly anti-correlated: their cross
        term matters, and the logged S had left out all but psi's variance)."""
        h, z, var = self._pending_heading()
        full = self._newest_marginal()
        res = np.array([wrap_angle(z - float(h @ self.kf_state))])
        scov = np.array([[float(h @ full @ h) + var]])
        self.log.innovations.append(Innovation(
            t, self._h_sensor, "heading", res, scov, float(res[0] ** 2 / scov[0, 0]), True))

    def _hoff_rw(self) -> float:
        """The heading offset's walk for the interval ending at the next keyframe: at least
        ``walk_floor`` of its marginal sigma at the newest keyframe (an uncertain offset
        against the stated walk's tie is what gtsam's Cholesky refuses)."""
        n = self.noise
        if not self.est_hoff:
            return n.fixed_rw
        # A compass sample informs psi + offset, not the offset: while the heading is
        # uncertain the offset keeps about its prior sigma, and dropping the floor at the first
        # sample made gtsam refuse the pivot (30 of 30 runs stopped with a 0.6 rad initial
        # heading sigma). The floor follows the offset's own marginal instead.
        full = self._full
        sigma = (math.sqrt(max(float(full[HOFF, HOFF]), 0.0))
                 if full is not None and full.shape == (DIM, DIM) else n.init_hoff_sigma)
        return max(n.heading_offset_rw, walk_floor(sigma))

    def _frozen(self) -> WheelGyroPreintegration:
        """The preintegration as an object with plain float attributes, for code that reads
        many of them (the compiled one keeps them in an array read through properties)."""
        return self.pim.frozen() if self._pim_compiled else self.pim

    def _delta(self, st, pim=None) -> tuple[float, float, float]:
        """The partial preintegrated increment at the biases and scales of state ``st``."""
        pim = self.pim if pim is None else pim
        return pim.delta_at(float(st[BG]), float(st[KV]), float(st[KW]))

    def _flush(self) -> None:
        """Send the pending factors and values to the smoother; capture what leaves the window."""
        if self.pending_graph.size() == 0 and self.pending_values.size() == 0:
            return
        if self.keep_all:
            if self._skip_in_batch is None:
                self.all_graph.push_back(self.pending_graph)
            else:  # the widening link of a lock-out recovery (_widen) is the smoother's alone
                for f in range(self.pending_graph.size()):
                    if f != self._skip_in_batch:
                        self.all_graph.add(self.pending_graph.at(f))
                self._skip_in_batch = None
            self.all_values.insert(self.pending_values)
        t_max = max(self.pending_stamps.values(), default=self.kf_t[self.k])
        self._capture_leaving(t_max - self.lag)
        try:
            self.smoother.update(self.pending_graph, self.pending_values, self.pending_stamps)
        except RuntimeError as e:
            self._recover(str(e))
            return
        finally:
            self.pending_graph = gtsam.NonlinearFactorGraph()
            self.pending_values = gtsam.Values()
            self.pending_stamps = {}
        key = self.key(self.k)
        self.kf_state = self.smoother.calculateEstimateVector(key)
        full = self._full = self.smoother.marginalCovariance(key)
        self._full_k = self.k
        self.kf_cov = full[:3, :3]
        self._scale_belief = (self.kf_state[KV:].copy(), full[KV:, KV:].copy())

    def _capture_leaving(self, t_cut: float, newest: bool = False) -> None:
        """Output the window's keyframes older than ``t_cut`` (s) as lagged estimates and drop
        them from ``kf_t``; the newest keyframe too only when ``newest`` (the run's end)."""
        leaving = [j for j, tj in self.kf_t.items() if tj < t_cut and (newest or j != self.k)]
        for j in sorted(leaving):
            if not self.lagged and j != self.k:  # the newest still gives final_state
                del self.kf_t[j]
                continue
            key = self.key(j)
            try:
                x = self.smoother.calculateEstimateVector(key)
                cov = self.smoother.marginalCovariance(key)
            except (RuntimeError, IndexError, ValueError):
                del self.kf_t[j]
                continue
            self._lagged.append(Estimate(
                self.kf_t[j], (float(x[0]), float(x[1]), wrap_angle(float(x[2]))),
                cov[:3, :3].copy(), x.copy(), cov.copy(), NAMES))
            del self.kf_t[j]

    def _recover(self, reason: str) -> None:
        """gtsam failed (indeterminate system, ...): restart from the last good estimate."""
        t = self.kf_t[self.k]
        # gtsam's messages start with a blank line
        first = next((line.strip() for line in reason.splitlines() if line.strip()),
                     "gtsam error")
        self._recovery_t = [r for r in self._recovery_t if r > t - RECOVERY_WINDOW] + [t]
        if len(self._recovery_t) > MAX_RECOVERIES:
            self._capture_leaving(math.inf, newest=True)  # what the window holds is kept
            # Failing again and again (each re-initialisation's own update succeeds, the next
            # keyframes' do not): the model is ill-conditioned here, and going on would output
            # a track re-started from ever staler estimates (metres off). Stop this estimator:
            # the runner keeps what it estimated and the other estimators go on.
            self.stopped = (f"{len(self._recovery_t)} re-initialisations within "
                            f"{RECOVERY_WINDOW:g} s at t={t:.3f} ({first}): its system is "
                            "ill-conditioned here; check the config's noise values, priors and "
                            "delays")
            raise RuntimeError(f"smoother: {self.stopped}")
        self.log.note(t, f"smoother re-initialised after gtsam error: {first}")
        self.log.rejected[("smoother", "gtsam error, re-initialised")] += 1
        state, cov, full = self.kf_state, self.kf_cov, self._full
        self._capture_leaving(math.inf)  # the window's keyframes as they stood: no gap in the lag
        self._new_smoother()
        sig = np.sqrt(np.maximum(np.diag(cov), 1e-6)) * 2.0
        calib = None
        if full is not None and full.shape == (DIM, DIM):
            # the gyro bias and heading offset as learnt, their sigmas doubled as the pose's;
            # their priors instead cost 0.7 deg of yaw for seconds and, with an uncertain
            # heading, fed the next failures
            cc = 4.0 * full[BG:, BG:]
            calib = (np.array(state[BG:], dtype=float), 0.5 * (cc + cc.T))
        self._init_state(t, (state[0], state[1], state[2]), float(max(sig[0], sig[1])),
                         float(sig[2]), self._scale_belief, calib=calib)

    def _new_smoother(self) -> None:
        """An empty smoother and window (what was pending is dropped)."""
        self.smoother = gtsam.IncrementalFixedLagSmoother(self.lag, isam2_params())
        self.kf_t = {}
        self.pending_graph = gtsam.NonlinearFactorGraph()
        self.pending_values = gtsam.Values()
        self.pending_stamps = {}
        self._skip_in_batch = None

    # --- initialisation from GPS course -------------------------------------------------------
    def _process_uninitialised(self, m) -> None:
        if isinstance(m, Heading):
            self.heading = m
        if self.given_pose is not None and self._realign is None:
            self._start(m.t, tuple(self.given_pose), self.noise.init_pos_sigma,
                        self.noise.init_given_psi_sigma)
            self.process(m)
            return
        if not self.has_gps:
            psi = 0.0
            if isinstance(m, Heading) and not self.est_hoff:
                s = self.sensors[m.sensor]
                psi = wrap_angle(m.yaw - float(s.heading_offset))
            self._start(m.t, (0.0, 0.0, psi), self.noise.init_pos_sigma, 0.05 if psi else 1e-3)
            self.process(m)
            return
        self.buffer.append(m)
        # The buffer's first and last fix (no rescan per message). The window starts at a fix
        # that odometry covers: from ODOMETRY_WAIT before the first sample on (held back over
        # its period, as ``process`` holds messages); an earlier one has no motion to relate
        # it to the next.
        if isinstance(m, GpsFix):
            self._buf_last = m
            if self._buf_moving:
                self._buf_fixes = (self._buf_fixes[0] if self._buf_fixes else m, m)
        elif not self._buf_moving and (isinstance(m, WheelSpeeds) or (
                isinstance(m, WheelOdometry) and m.v is not None)):
            self._buf_moving = True
            first = next((b for b in self.buffer if isinstance(b, GpsFix)
                          and b.t >= m.t - ODOMETRY_WAIT), None)
            self._buf_fixes = (first, self._buf_last) if first is not None else None
        if self._buf_fixes is None or self._buf_fixes[0] is self._buf_fixes[1]:
            return
        f0, f1 = self._buf_fixes
        de, dn = f1.enu[0] - f0.enu[0], f1.enu[1] - f0.enu[1]
        # the course's direction error is both fixes' errors across the baseline d: stated as
        # such (a fixed 0.2 rad was 0.30 rad RMS off with 1 m fixes), and with poor fixes the
        # wait is for a baseline that gives COURSE_SIGMA_MAX (with 2 m fixes 5 m gave 0.79 rad
        # RMS, 12 % of them beyond 3 sigma)
        across = max(f0.cov[0, 0], f0.cov[1, 1]) + max(f1.cov[0, 0], f1.cov[1, 1])
        d = math.hypot(de, dn)
        if d < max(INIT_DISTANCE, math.sqrt(across) / COURSE_SIGMA_MAX):
            return
        psi0 = self._course_heading(f0, f1)
        if psi0 is None:
            return
        buffered = [b for b in self.buffer if b.t >= f0.t]
        for b in self.buffer:
            if b.t >= f0.t:
                break
            if isinstance(b, GpsFix):  # the fixes before odometry began, as ``_absolute``
                self.log.rejected[(b.sensor, "before odometry began")] += 1
        self.buffer = []
        self._buf_fixes = self._buf_last = None
        self._buf_moving = False
        sig = max(math.sqrt(f0.cov[0, 0]), math.sqrt(f0.cov[1, 1]))
        # the baseline the fixes' own errors lengthened (by 2 across in the mean square): the
        # wait ended at a noisy d that had reached the threshold early
        d_true = math.sqrt(max(d * d - 2.0 * across, 0.25 * d * d))
        self._start(f0.t, (f0.enu[0], f0.enu[1], psi0), sig,
                    max(self.noise.init_psi_sigma, math.sqrt(across) / d_true))
        for b in buffered:
            self.process(b)

    def _start(self, t: float, pose, pos_sigma: float, psi_sigma: float) -> None:
        self.last_t = t
        calib, self._realign = self._realign, None
        self._init_state(t, pose, pos_sigma, psi_sigma, calib=calib)

    def _course_heading(self, f0: GpsFix, f1: GpsFix) -> float | None:
        """Initial heading at f0: the GPS displacement's direction minus the direction of the
        dead-reckoned displacement (odometry from heading 0) over the same interval."""
        x = y = psi = 0.0
        v = w = None
        last = None
        for b in self.buffer:
            if b.t < f0.t:
                if isinstance(b, WheelOdometry):
                    v = b.v if b.v is not None else v
                    w = b.yaw_rate if b.yaw_rate is not None else w
                continue
            if b.t > f1.t:
                break
            if last is not None and v is not None and w is not None:
                dt = b.t - last
                x += v * math.cos(psi) * dt
                y += v * math.sin(psi) * dt
                psi += w * dt
            last = b.t
            if isinstance(b, WheelOdometry):
                v = b.v if b.v is not None else v
                w = b.yaw_rate if b.yaw_rate is not None else w
            elif isinstance(b, GyroYawRate) and b.sensor in self.gyro_names:
                w = b.yaw_rate - self.fixed_bias
            elif isinstance(b, WheelSpeeds):
                v, w = b.twist(self.cfg.robot.wheel_radius, self.cfg.robot.track_width)[:2]
        if math.hypot(x, y) < 0.5 * INIT_DISTANCE:
            return None  # odometry disagrees with GPS about having moved: wait
        de, dn = f1.enu[0] - f0.enu[0], f1.enu[1] - f0.enu[1]
        return wrap_angle(math.atan2(dn, de) - math.atan2(y, x))

    # --- outputs ----------------------------------------------------------------------------
    def estimate(self) -> Estimate | None:
        """The filtered estimate at the newest message's stamp: the newest keyframe composed
        with the partial preintegration up to the last odometry sample, then the held twist
        carried forward over the messages still waiting for the next odometry sample."""
        if self._restart is not None:  # a gap ended the window; the new one waits to start
            pose, pos_sigma, psi_sigma, _ = self._restart
            cov = np.diag((pos_sigma ** 2, pos_sigma ** 2, psi_sigma ** 2))
            return Estimate(self._restart_buf[-1].t if self._restart_buf else self._now, pose,
                            cov, None, None, NAMES)
        if not self.initialised or self.kf_state is None:
            return None
        st, kf_cov = self._with_pending_heading()
        pim = self._frozen()
        pose, cov = _compose(st, self._delta(st, pim), pim.covariance, kf_cov)
        t = self.last_t
        ahead = self._now - t
        if ahead > 0.0 and self.v is not None:
            yr = self._yaw_rate(self.wg_q, self.wo_q, self.wg_var, self.wo_var)
            if yr is not None:
                wg, wo, _, _, gain = yr
                sl = st.tolist()  # Python floats: numpy scalars cost 4 us in se2_step
                bg, kv, kw = sl[BG], sl[KV], sl[KW]
                pose, t = se2_step(pose[0], pose[1], pose[2], kv * self.v,
                                   wg - gain * bg + kw * wo, ahead), self._now
        return Estimate(t, (pose[0], pose[1], wrap_angle(pose[2])), cov, st.copy(), None, NAMES)

    def _pending_heading(self, closing=None) -> tuple[np.ndarray, float, float]:
        """The heading samples since the newest keyframe as one linear measurement h x = z
        (h (DIM,), z rad, variance rad^2) of the newest keyframe's state, or, with
        ``closing`` (the interval's preintegration), of the keyframe that closes it.

        Each sample u_i = yaw_i - dpsi_i is carried back to the keyframe by the preintegrated
        yaw up to it (``_step``), which depends on the gyro bias and the yaw-rate scale:
        u_i = psi + [hoff] + J_i (bg - bg_lin) + K_i (k_w - kw_lin) + noise. So the mean
        measures psi + [hoff] + J bg + K k_w, J, K the means of J_i, K_i; at the closing
        keyframe, psi_j = psi + dpsi_T + J_T (bg - bg_lin) + ..., with J - J_T, K - K_T. Left
        out, a bias still uncertain (early in a run) biased the heading: with 2 s keyframe
        intervals 1.0 deg RMS of yaw error against a stated 0.35 deg (NEES 10.6). The variance:
        the samples' own var / n plus the mean's share of the integrated yaw noise (white:
        c_i = var(dpsi_i), Var(mean_i int_0^t_i) = sum_il c_min(i,l) / n^2, and
        Var(mean_i int_t_i^T) = C_T - sum_il c_max(i,l) / n^2)."""
        s = self.sensors[self._h_sensor]
        n = self._h_n
        z = self._h_ref + self._h_sum / n
        pim = self.pim if closing is None else closing
        jb, jk = self._h_jb / n, self._h_jk / n
        c1, c2 = self._h_c1, self._h_c2
        if closing is None:
            carried = ((2 * n - 1) * c1 - 2.0 * c2) / (n * n)
        else:
            z += pim.dpsi
            jb, jk = jb - pim.j_p, jk - pim.kw_p
            carried = pim.c_pp - (2.0 * c2 + c1) / (n * n)
        h = np.zeros(DIM)
        h[PSI] = 1.0
        if s.heading_offset == "estimate":
            h[HOFF] = 1.0
        else:
            z -= float(s.heading_offset)
        if self.est_bias:
            h[BG] = jb
            z += jb * pim.bg_lin
        if self.scale_prior is not None:
            h[KW] = jk
            z += jk * pim.kw_lin
        return h, z, self._h_var / (n * n) + max(carried, 0.0)

    def _with_pending_heading(self) -> tuple[np.ndarray, np.ndarray]:
        """The newest keyframe's state and 3x3 pose covariance, updated (outside the graph)
        with the heading samples that arrived since it: they become one factor only at the next
        keyframe, but the filtered output should use them now, as the EKFs do. One scalar
        Kalman update with the keyframe's full marginal; the same averaged measurement as that
        factor (``_new_keyframe``)."""
        st, full = self.kf_state, self._full
        if not self._h_n or full is None or full.shape != (DIM, DIM):
            return st, self.kf_cov
        # the same until the next heading sample or update: estimate() asks more often
        key = (self._h_n, self.k, id(st), id(full))
        if self._pending_cache is not None and self._pending_cache[0] == key:
            return self._pending_cache[1]
        h, z, var = self._pending_heading()
        # Python floats over h's few non-zeros (psi, offset, bias, scale): numpy on 9-vectors
        # cost 10-20 us here, per output sample
        f = full.tolist()
        x = st.tolist()
        ph = [0.0] * DIM
        pred = 0.0
        for i, c in enumerate(h.tolist()):
            if c != 0.0:
                ph = [a + c * b for a, b in zip(ph, f[i], strict=True)]
                pred += c * x[i]
        s = sum(c * a for c, a in zip(h.tolist(), ph, strict=True)) + var
        g = wrap_angle(z - pred) / s  # innovation over its variance
        x = np.array([xi + pi * g for xi, pi in zip(x, ph, strict=True)])
        p = np.array([[0.5 * (f[i][j] + f[j][i]) - ph[i] * ph[j] / s for j in range(3)]
                      for i in range(3)])
        out = (x, p)
        self._pending_cache = (key, out)
        return out

    def finish(self) -> None:
        if not self.initialised:
            why = ("the GPS track never moved far enough" if self._buf_last is not None else
                   "no GPS fix came, and it takes its heading from the GPS course")
            self.log.note(self.buffer[-1].t if self.buffer else 0.0, f"never initialised: {why}")
            return
        self._release_held()
        # The odometry since the newest keyframe closes the run as a last keyframe, unless it
        # spans less than MIN_KEYFRAME_DT: a preintegrated factor over a few milliseconds has
        # walk sigmas of ~1e-6, and gtsam declared such a system indeterminate (a run cut
        # 0.03 s after a GPS keyframe: the batch lost its whole solution).
        if self.pim.n > 0 and self.last_t - self.kf_t[self.k] >= MIN_KEYFRAME_DT:
            self._new_keyframe(self.last_t)
            self._flush()
        self._capture_leaving(math.inf, newest=True)

    def lagged_estimates(self) -> TrackBuilder | None:
        return self._lagged if self.lagged else None

    def final_state(self) -> Estimate | None:
        """The newest keyframe with its full marginal (the lagged track's last entry after
        ``finish``: at the end of the run the filtered and the lagged output meet there),
        restricted to the states this run estimates (a held bias, offset or scale is left out,
        as the EKFs carry no state for it)."""
        return self._estimated_only(self._lagged.last)

    def _estimated_only(self, e: Estimate | None) -> Estimate | None:
        if e is None or e.state is None:
            return e
        keep = [i for i in range(DIM) if i < BG or (i == BG and self.est_bias)
                or (i == HOFF and self.est_hoff) or (i >= KV and self.scale_prior is not None)]
        cov = e.state_cov[np.ix_(keep, keep)] if e.state_cov is not None else None
        return replace(e, state=e.state[keep], state_cov=cov,
                       state_names=tuple(NAMES[i] for i in keep))


class BatchSmoother(FixedLagSmoother):
    """Every factor of the run, solved at the end with Levenberg-Marquardt: the offline optimum
    the fixed-lag outputs are compared with. Its trajectory is at the keyframes. The factors are
    the ones the online run builds, so a time-correlated GPS fix is inflated by the f the
    smoother gave it (for the time since the previous fused fix; a late one's nearest): batch
    and smoother model the data alike."""

    name = "batch"
    keep_all = True

    def __init__(self, cfg: Config, **kw) -> None:
        kw.setdefault("lagged", False)  # its output is the final solve's, not a lagged one
        super().__init__(cfg, **kw)
        self._final = TrackBuilder()

    def finish(self) -> None:
        super().finish()
        if not self.initialised:
            return
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(20)
        params.setRelativeErrorTol(1e-6)
        try:
            result = gtsam.LevenbergMarquardtOptimizer(self.all_graph, self.all_values,
                                                       params).optimize()
            marg = gtsam.Marginals(self.all_graph, result)
        except RuntimeError as e:
            self.log.note(self.last_t, f"batch optimisation failed: {e}")
            return
        times = {int(self.key(j)): t for j, t in self.all_kf_t.items()}
        for key, t in sorted(times.items(), key=lambda kv: kv[1]):
            x = result.atVector(key)
            cov = marg.marginalCovariance(key)
            self._final.append(Estimate(t, (float(x[0]), float(x[1]), wrap_angle(float(x[2]))),
                                        cov[:3, :3].copy(), x.copy(), cov.copy(), NAMES))

    def lagged_estimates(self):  # the batch has no lagged output of its own
        return None

    def final_estimates(self) -> TrackBuilder:
        return self._final

    def final_state(self) -> Estimate | None:
        return self._estimated_only(self._final.last)

