"""The smoother's noise: process-noise densities and priors (``SmootherNoise``), the floors that
keep gtsam's Cholesky accepting the window (``walk_floor``), the twist's random walk while a
sample is held, and the robust kernels of the measurement factors.

Units: densities per sqrt(s) as stated on each field; sigmas in the state's units (m, rad, m/s,
rad/s, 1). Not tuned per bag or per estimator. Why each floor is where it is:
docs/design/smoother.md (Noise and floors).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import gtsam
import numpy as np
from ddfuse.estimation import chi2
from ddfuse.estimation.config import DEFAULT_GATE, GIVEN_POSE_STD, Config, SensorConfig

MIN_KEYFRAME_DT = 0.1  # s: closer absolute measurements share a keyframe
# m/sqrt(s), m/sqrt(s), rad/sqrt(s): the least pose noise between keyframes (see
# SmootherNoise.from_config); a tenth of a millimetre per second, negligible against any sensor
POSE_NOISE_FLOOR = (1e-3, 1e-3, 1e-4)

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
    # the geometry's uncertainty; tyre wear, load); otherwise they are held at 1 (fixed_rw), as
    # the EKFs hold them. Much less and gtsam's Cholesky refuses the first keyframes.
    scale_rw: float = 1e-4
    # m/s^2/sqrt(Hz), rad/s^2/sqrt(Hz): white accelerations that move the twist away from a held
    # sample once it is older than its period (odometry or gyro stopped, a gap in the feed): the
    # EKFs' default (ProcessNoise.acc, yaw_acc); robot.twist_walk's when stated; else with
    # robot.max_accel / max_yaw_accel the density is a_max sqrt(T), T the sample's period, as
    # the EKFs take it (twist_densities)
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
        ho = [s.noise["heading_offset_walk"] for s in cfg.heading_sensors()
              if "heading_offset_walk" in s.noise]
        return replace(n, pose_noise=pn,
                       gyro_bias_rw=max(bg[0], WALK_FLOOR[0], walk_floor(n.init_bg_sigma))
                       if bg else n.gyro_bias_rw,
                       heading_offset_rw=max(ho[0], WALK_FLOOR[1]) if ho else n.heading_offset_rw)




def twist_walk(a_max: float | None, default: float, period: float,
               stated: float | None = None) -> float:
    """Density ((unit/s)^2 per s) of the random walk that moves the twist away from a held
    sample: the config's ``robot.twist_walk`` density squared (``stated``, unit/s/sqrt(s)),
    else a_max^2 period from the robot's acceleration limit (the EKFs' twist_densities:
    Bar-Shalom's a_max sqrt(T)), else the default density squared -- the EKFs' order."""
    if stated is not None:
        return stated * stated
    return a_max * a_max * period if a_max is not None else default * default


def robust(cfg: Config, sensor: SensorConfig, sigmas: tuple[float, ...]) -> gtsam.noiseModel.Base:
    """Diagonal ``sigmas`` wrapped in the configured M-estimator (``robustify``)."""
    return robustify(cfg, sensor, gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, float)),
                     len(sigmas))


@lru_cache(maxsize=64)
def gate_radius(gate: float, dim: int) -> float:
    """The chi-square gate's radius (whitened norm) at probability ``gate`` for ``dim`` dof."""
    return math.sqrt(chi2.ppf(gate, dim))


def robustify(cfg: Config, sensor: SensorConfig, base: gtsam.noiseModel.Base,
              dim: int, inflated: float = 1.0) -> gtsam.noiseModel.Base:
    """``base`` wrapped in the configured M-estimator. gtsam applies it to the norm of the
    whole whitened residual, so the default threshold is that norm at the sensor's chi-square
    gate for ``dim`` components: full weight wherever the EKF's gate would accept the same
    residual, linear (Huber) or log (Cauchy) growth beyond.

    ``inflated``: the factor f by which ``base``'s covariance is the measurement's own times f
    (a time-correlated GPS fix, ``ddfuse.estimation.gps_correlation``). The same residual in metres
    then whitens to 1/sqrt(f) of its norm against the own covariance, so the threshold (the
    gate radius, or a given ``robust_k`` alike) is scaled by 1/sqrt(f): the kernel still gives
    full weight to exactly the residuals the gate accepts (which judges the fix with its own
    covariance) and acts on the same residuals in metres. Unscaled, at f = 150 it would give
    full weight to residuals 12 times the gate's radius: no robustness left."""
    kind, k = cfg.smoother.robust, cfg.smoother.robust_k
    if k is None:
        k = gate_radius(sensor.gate if sensor.gate is not None else DEFAULT_GATE, dim)
    if inflated != 1.0:
        k /= math.sqrt(inflated)
    if kind == "huber":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), base)
    if kind == "cauchy":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(k), base)
    return base

