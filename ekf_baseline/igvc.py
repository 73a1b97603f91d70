"""Seed 000's 11-state IGVC EKF, built as the document means it (its errors: docs/errata.md).

State (STATE_NAMES, index: meaning, unit)::

    0 lat      geodetic latitude, rad            6 v        forward speed, m/s
    1 lon      longitude, rad                    7 psi_dot  yaw rate, rad/s, CCW +
    2 theta    bearing, rad, CLOCKWISE from N    8 v_l      left wheel rim speed, m/s
    3 x        local ENU east, m                 9 v_r      right wheel rim speed, m/s
    4 y        local ENU north, m               10 a        forward acceleration, m/s^2
    5 psi      yaw, rad, CCW from local east

Frames: x, y, psi in the local ENU frame (x east, y north, psi CCW from east), so
``Estimate.pose`` is (x, y, psi); theta a compass bearing, theta = pi/2 - psi at the datum.

Motion models (``motion='euler'`` or ``'icc'``): generated once from sympy in
``ekf_baseline/igvc_jacobians.py`` (``ekf_baseline/igvc_codegen.py``); they keep the redundant
pairs ((lat, lon) ~ (x, y), theta ~ psi, (v, psi_dot) ~ (v_l, v_r)) consistent.

Measurements (seed eq. 17/19, corrected):

* GpsFix -> (lat, lon) of the antenna (``lever_arm`` of the GPS sensor, body frame). Updated in
  metres (east, north) about the current estimate so the logged residuals are in metres; the
  NIS is the same as in radians.
* Heading -> the global heading Theta_g = theta: yaw = pi/2 - theta + heading_offset. A Heading
  with ``source='pose'`` is the seed's local heading Theta_l = psi + heading_offset. An offset
  'estimate' is a calibration state (IgvcEkf).
* GyroYawRate -> psi_dot + the configured numeric gyro_bias or the estimated bias state.
* ForwardAccel -> a.
* WheelSpeeds (rad/s) -> (v_l / r, v_r / r).
* WheelOdometry -> v = (v_l + v_r)/2 and yaw rate (v_r - v_l)/L (seed eqs. 18-19).

Models: ``ddfuse.ekf_baseline.igvc_measurements``. Every update goes through
``ddfuse.ekf_baseline.kalman.KalmanCore`` (Joseph form, per-sensor chi-square gate with
lock-out recovery) or the compiled kernels.

A GPS sensor with ``correlation_time`` > 0 has each fix fused with an inflated R
(``estimation.gps_correlation``), as in the unicycle EKF, and so has each sample of a heading
sensor with one (``estimation.heading_correlation``). Poles: within ``POLE_LIMIT_KM`` of
a pole (|lat| > ``POLE_LIMIT_DEG``) ``process`` raises ``PolarRegionError``; why the limit is
there, and the rest of the design notes: docs/design/igvc_ekf.md.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from ddfuse.ekf_baseline import compiled as jit
from ddfuse.ekf_baseline import igvc_jacobians as gen
from ddfuse.ekf_baseline import igvc_measurements as im
from ddfuse.ekf_baseline.gps_robust import robust_spec
from ddfuse.ekf_baseline.igvc_compiled import IgvcKernels
from ddfuse.ekf_baseline.igvc_model import (
    _Q_INDEX,
    HALF_PI,
    LAT,
    LON,
    PSI,
    THETA,
    IgvcNoise,
    N,
    X,
    Y,
    igvc_q_values,
    sphere_radius,
)
from ddfuse.ekf_baseline.igvc_start import _USED, IgvcStart
from ddfuse.ekf_baseline.kalman import KalmanCore
from ddfuse.estimation.config import DEFAULT_GATE, Config, SensorConfig
from ddfuse.estimation.estimator import Estimate, Estimator
from ddfuse.estimation.gaps import gap_note, grown_pose_cov, is_gap
from ddfuse.estimation.gps_correlation import inflation as gps_inflation
from ddfuse.estimation.heading_correlation import HeadingClock
from ddfuse.estimation.measurements import (
    ForwardAccel,
    GpsFix,
    GroundTruthPose,
    GyroYawRate,
    Heading,
    WheelOdometry,
    WheelSpeeds,
)
from ddfuse.estimation.twist_tails import SpeedBursts, SpeedTails

__all__ = ["IgvcEkf", "IgvcNoise", "PolarRegionError", "POLE_LIMIT_DEG", "STATE_NAMES", "LAT",
           "LON", "sphere_radius"]

STATE_NAMES = gen.STATE_NAMES
# the measurement types the filter uses (the others are ignored, before its start too)
DEFAULT_TRACK = 0.5  # m, used only for the wheel-speed states when robot.track_width is unset
FEED_GAP_S = 5.0  # s without any message: a gap in the feed (``IgvcEkf._bridge_gap``)
GAP_RESTART_STD = 10e3  # m: a gap that leaves the position this uncertain restarts the filter
# deg: |lat| beyond which the filter refuses to run, about POLE_LIMIT_KM from a pole (module
# docstring: the meridian convergence the model ignores grows as 1/distance to the pole)
POLE_LIMIT_DEG = 89.91
POLE_LIMIT_KM = 10.0
_POLE_LIMIT_RAD = math.radians(POLE_LIMIT_DEG)
# the states a change of the forward speed moves alike, by as much: v and the rim speeds v_l,
# v_r (STATE_NAMES)
_SPEEDS = [STATE_NAMES.index(k) for k in ("v", "v_l", "v_r")]


class PolarRegionError(ValueError):
    """The filter's position (datum, first fix or state) is within ``POLE_LIMIT_KM`` of a pole,
    where seed 000's (lat, lon) state cannot represent it (module docstring)."""


_TWO_PI = 2.0 * math.pi
_POSE_IX = np.ix_((X, Y, PSI), (X, Y, PSI))  # the (x, y, psi) block of P


class IgvcEkf(IgvcStart, IgvcKernels, Estimator):
    """Seed 000's 11-state EKF (module docstring) as an :class:`Estimator`.

    Calibration states follow the seed's 11, as in the unicycle EKF: a gyro bias (gyro =
    psi_dot + bg) per IMU whose ``gyro_bias`` is 'estimate', a heading offset (reading =
    wrap(heading + hoff), initialised from the first reading) per IMU whose ``heading_offset``
    is 'estimate' -- random walks of the IMU's stated densities (noise.gyro_bias_walk,
    heading_offset_walk) or IgvcNoise's -- and the odometry scales k_v, k_w (odometry and wheel
    speeds report v / k_v, psi_dot / k_w) when the config states the geometry's uncertainty.
    A GPS sensor's ``delay`` is compensated: the antenna is predicted at t - delay (first
    order: moved back by v delay along the bearing). The config's robot.slip replaces the
    position and heading noise densities (isotropic here: the larger of the along- and
    across-track variances, ``IgvcNoise``).

    ``initial_pose`` (x, y, yaw) in the local ENU frame (m, m, rad) overrides the config's
    ``initial_pose``; with 'ground_truth' in the config and no ``initial_pose`` the filter starts
    at the first GroundTruthPose it is given (pass ``stream.ground_truth[0]`` as initial_pose when
    the ground truth is not in the measurement stream). Without any initial pose and with a GPS
    configured, it starts at the first fix, with the heading from the first usable Heading or,
    failing that, from the GPS course (``ddfuse.estimation.gps_course``, the smoother's start:
    the fixes' direction less the dead-reckoned turn) once the fixes span ``course_distance`` m,
    the measurements since its first fix replayed; without GPS
    it starts at the origin with yaw 0. ``datum`` (lat deg, lon deg, alt m) is the local ENU
    origin (``stream.datum``); default the config's, else the first fix. ``motion`` is 'euler'
    (seed eq. 14) or 'icc' (seed appendix A); default the config's ``ekf_igvc.motion``.
    Prediction steps are at most ``max_step`` s.
    ``reference``: run the Python reference (``KalmanCore.update_blocks``) instead of the
    compiled kernels of ``ekf_baseline.kalman_jit`` (the generated Jacobian compiled as it is;
    what they defer runs the reference's code on the same arrays), as UnicycleEkf.
    """

    name = "igvc_ekf"

    def __init__(
        self,
        cfg: Config,
        *,
        initial_pose: tuple[float, float, float] | None = None,
        datum: tuple[float, float, float] | None = None,
        motion: str | None = None,
        noise: IgvcNoise | None = None,
        max_step: float = 0.05,
        course_distance: float = 3.0,
        reference: bool = False,
    ) -> None:
        super().__init__()
        motion = cfg.ekf_igvc.motion if motion is None else motion
        if motion not in ("euler", "icc"):
            raise ValueError(f"motion must be 'euler' or 'icc', got {motion!r}")
        self.cfg = cfg
        self.motion = motion
        # compiled or loaded now, not in the first step; or the reference path (jit.usable)
        self.compiled = not reference and jit.usable("igvc")
        self.reference = not self.compiled
        if self.compiled:
            self.log = jit.BufferedLog()
        self._jrows: dict[str, int] = {}  # sensor -> row in the compiled core's sensor table
        self._step_sparse = gen.euler_step_sparse if motion == "euler" else gen.icc_step_sparse
        self._sensor_info: dict[str, tuple] = {}
        # a robust GPS model (gps.model; ekf_baseline.gps_robust): its fixes take the Python path
        self._robust = robust_spec(cfg)
        # GPS sensors with time-correlated errors: name -> correlation time (s), and the stamp
        # of each one's last fused fix (module docstring)
        self._gps_tau = {s.name: float(s.correlation_time) for s in cfg.of_kind("gps")
                         if s.correlation_time > 0.0}
        self._gps_fused: dict[str, float] = {}
        # heading sensors with time-correlated samples (estimation.heading_correlation)
        self._heading_clock = HeadingClock(cfg)
        self.noise = noise or IgvcNoise()
        slip = cfg.robot.slip
        if slip and noise is None:
            # the robot's stated slip replaces the defaults; the position noise here is
            # isotropic: the larger of the along- and across-track variances, which it covers
            # in every direction (IgvcNoise; errata 000 #42)
            ns = self.noise
            long_, lat_ = slip.get("longitudinal"), slip.get("lateral")
            if long_ is not None or lat_ is not None:
                d = math.sqrt(ns.position_psd)
                long_ = d if long_ is None else long_
                lat_ = d if lat_ is None else lat_
                ns = replace(ns, position_psd=max(long_ * long_, lat_ * lat_))
            if "heading" in slip:
                ns = replace(ns, heading_psd=slip["heading"] ** 2)
            self.noise = ns
        if "yaw_rate" in cfg.robot.twist_walk and noise is None:
            # the robot's stated yaw-rate walk; its speed is driven by jerk on an acceleration
            # state, which robot.twist_walk.speed (a walk of the speed itself) does not describe
            self.noise = replace(self.noise, yaw_accel_psd=cfg.robot.twist_walk["yaw_rate"] ** 2)
        # the heavy-tailed speed walk's bursts (estimation.twist_tails) on top of the jerk-driven
        # speed: at an odometry speed sample the burst explains better than the steady walk, v
        # and both rim speeds widened alike by the burst's extra variance
        tails = SpeedTails.from_robot(cfg.robot) if noise is None else None
        self.bursts = SpeedBursts(tails) if tails is not None else None
        self._calibration_states(cfg)
        n = self.n
        ones, variable = ((gen.EULER_F_ONES, gen.EULER_F_VARIABLE) if motion == "euler"
                          else (gen.ICC_F_ONES, gen.ICC_F_VARIABLE))
        # the generated Jacobian's flat indices (11 x 11) in the n x n F; the calibration
        # states are constants or random walks: F = 1 on their diagonal
        self._F = np.zeros((n, n))
        self._F.reshape(-1)[[k // N * n + k % N for k in ones]] = 1.0
        self._F[range(N, n), range(N, n)] = 1.0
        self._F_var = np.array([k // N * n + k % N for k in variable])
        self._Q = np.zeros((n, n))
        walked = list(self._walks)
        self._q_index = np.concatenate([
            [i // N * n + i % N for i in _Q_INDEX],
            [i * n + i for i in walked]]).astype(np.int64)
        self.max_step = float(max_step)
        self.course_distance = float(course_distance)
        self.track = cfg.robot.track_width or DEFAULT_TRACK
        self.wheel_radius = cfg.robot.wheel_radius
        if datum is None and isinstance(cfg.datum, tuple):
            datum = cfg.datum
        self.datum = tuple(datum) if datum is not None else None
        if initial_pose is None and isinstance(cfg.initial_pose, tuple):
            initial_pose = cfg.initial_pose
        self._wait_truth = initial_pose is None and cfg.initial_pose == "ground_truth"
        self._has_gps = bool(cfg.of_kind("gps"))
        self.kf: KalmanCore | None = None
        self.t: float | None = None
        self.radius = sphere_radius(math.radians(self.datum[0]) if self.datum else 0.0)
        self._course = self._course_start()
        self._heading_init: tuple[float, float] | None = None  # (yaw, var)
        if initial_pose is not None and (self.datum is not None or not self._has_gps):
            self._init(None, initial_pose, self.noise.init_position_std ** 2,
                       self.noise.init_heading_std ** 2)
        self._pose_given = initial_pose

    # ------------------------------------------------------------------ helpers
    def _sensor(self, name: str) -> SensorConfig | None:
        try:
            return self.cfg.sensor(name)
        except KeyError:
            return None

    def _gate(self, name: str) -> float | None:
        s = self._sensor(name)
        return s.gate if s is not None else DEFAULT_GATE

    def _heading_offset(self, name: str) -> float:
        s = self._sensor(name)
        off = s.heading_offset if s is not None else 0.0
        return float(off) if off != "estimate" else 0.0

    def predict_to(self, t: float) -> None:
        """Propagate the state to time ``t`` (s) in steps of at most ``max_step``."""
        kf = self.kf
        dt_total = t - self.t
        if dt_total <= 0.0:
            return
        n = max(1, math.ceil(dt_total / self.max_step - 1e-9))
        dt = dt_total / n
        F_flat, Q_flat = self._F.reshape(-1), self._Q.reshape(-1)
        walks = list(self._walks.values())
        for _ in range(n):
            xs = kf.x.tolist()
            f, fv = self._step_sparse(xs[:N], dt, self.track, self.radius)
            F_flat[self._F_var] = fv
            Q_flat[self._q_index] = self._q_values(xs[LAT], dt) + tuple(
                [q * dt for q in walks])
            kf.predict(self._F, self._Q, f + tuple(xs[N:]))
        self.t = t

    def _q_values(self, lat: float, dt: float) -> tuple[float, ...]:
        """:func:`igvc_q_values` of this filter's noise densities."""
        ns = self.noise
        return igvc_q_values(lat, dt, self.radius, ns.position_psd, ns.frame_psd, ns.heading_psd,
                             ns.frame_heading_psd, ns.jerk_psd, ns.yaw_accel_psd, ns.slip_var)

    # ------------------------------------------------------------------ Estimator
    def _check_pole(self) -> None:
        """PolarRegionError when the state's latitude (before the start: the datum's) is
        within POLE_LIMIT_KM of a pole (module docstring). Checked before each message: one
        step moves the state by centimetres, and the steps only divide by zero within about
        0.1 m of the pole, so the limit is met well before."""
        if self.kf is not None:
            lat, where = float(self.kf.x[LAT]), "the filter's position is"
        elif self.datum is not None:
            lat, where = math.radians(self.datum[0]), "the datum is"
        else:
            return
        if abs(lat) <= _POLE_LIMIT_RAD:
            return
        d = self.radius * (HALF_PI - abs(lat))
        far = f"{d / 1000.0:.3g} km" if d >= 1000.0 else f"{d:.3g} m"
        raise PolarRegionError(
            f"seed 000's lat/lon state is singular within {POLE_LIMIT_KM:g} km of a pole (|lat| "
            f"> {POLE_LIMIT_DEG:g} deg): {where} at latitude {math.degrees(lat):.5f} deg, "
            f"{far} from the {'north' if lat > 0 else 'south'} pole (the longitude and the "
            "bearing are undefined at the pole, the model's meridian convergence wrong near "
            "it); use ekf or the smoother")

    def process(self, m) -> None:
        self._check_pole()
        if isinstance(m, GroundTruthPose):
            if self.kf is None and self._wait_truth:
                self._pose_given = (m.x, m.y, m.yaw)
                self._wait_truth = False
                if self.datum is not None or not self._has_gps:
                    self._init(m.t, self._pose_given, self.noise.init_position_std ** 2,
                               self.noise.init_heading_std ** 2)
            return
        self.in_order(m)  # no history: a stale measurement is refused, not fused as current
        if self.kf is not None and self.t is not None and m.t - self.t > FEED_GAP_S:
            self._bridge_gap(m.t)
        if self.kf is None:
            if self._wait_truth:
                self._count_before_init(m)
                return
            replayed = self._try_init_without_pose(m)
            # a datum or start taken from this fix: refused at it, not a message later
            self._check_pole()
            if self.kf is None:
                self._count_before_init(m)
                return
            if replayed:
                return
            if self.t == m.t and isinstance(m, GpsFix | Heading):
                return  # the measurement that initialised the filter is not used twice
        if self.t is None:
            self.t = m.t
        if self.compiled:
            p = self._pack(m)
            if p is not None:
                self._run_event(m, p)
                return
        self.predict_to(m.t)
        self._update(m)

    def _count_before_init(self, m) -> None:
        """Count a measurement of a kind the filter uses that came before it could start
        (waiting for a fix and a heading, the GPS course or the truth pose; after a restart,
        again), as the unicycle EKF counts them: (sensor, "before_init") in ``log.rejected``.
        A fix that only set the datum or the course's first point is counted too; the message
        that starts the filter is not."""
        if isinstance(m, _USED):
            self.log.rejected[(m.sensor, "before_init")] += 1

    def _bridge_gap(self, t: float) -> None:
        """Carry the filter over a silence in the feed (no message for more than FEED_GAP_S),
        or restart it over a gap (``estimation.gaps``: more than GAP_S).

        A silence up to GAP_S is predicted over. Over a gap the held twist says nothing: the
        jerk-driven model grew the position's variance as dt^5 (3.5 km of sigma after 60 s on
        the sample bag, 450 km after 300 s) and its mean went 100 m off. So the filter starts
        again from the last pose with the covariance the gap rule grows it by
        (``grown_pose_cov``), the twist as at the start, the calibration states as learnt
        (their walks over the gap). When that leaves the position sigma over GAP_RESTART_STD
        and a GPS will give it again, it starts as the run did (GPS and a heading, or the GPS
        course): past a few tens of km of variance the two position representations (lat, lon
        on the sphere, x, y on the plane) move apart and the fixes no longer reach x, y."""
        gap = t - self.t
        if not is_gap(gap):
            self.predict_to(t)
            return
        kf = self.kf
        x_old, P_old = kf.x.copy(), kf.P.copy()
        pose = grown_pose_cov(P_old[_POSE_IX], gap, self.cfg.robot)
        pos_var = max(float(pose[0, 0]), float(pose[1, 1]))
        if math.sqrt(pos_var) <= GAP_RESTART_STD or not self._has_gps:
            self._init(t, (x_old[X], x_old[Y], x_old[PSI]), pos_var, float(pose[2, 2]))
            x, P = self.kf.x.copy(), self.kf.P.copy()
            x[N:], P[N:, N:] = x_old[N:], P_old[N:, N:]
            for i, w in self._walks.items():
                P[i, i] += w * gap
            self.kf.x, self.kf.P = x, P
            self.log.note(t, gap_note(self.name, gap, pose))
            return
        self.log.note(t, f"{self.name}: restarted after a {gap:.1f} s gap in the feed "
                         f"(position sigma {math.sqrt(pos_var) / 1000.0:.0f} km over it): it "
                         "starts again as at the beginning")
        self.kf = None
        self.t = None
        self._course = self._course_start()
        self._heading_init = None
        self._pose_given = None  # the configured start pose was the run's, not this one's
        self._wait_truth = False
        self._hoff_ready = set()

    def _update(self, m) -> None:
        """The measurement update of ``m`` in Python (after the prediction to m.t): its rows
        from ``igvc_measurements`` (the kernels' models) through ``KalmanCore.update_blocks``."""
        kf = self.kf
        H = np.zeros((2, self.n))
        y = np.zeros(2)
        R = np.zeros((2, 2))
        # a correlated heading sensor's factor, asked of every sample (estimation.
        # heading_correlation: a pure function of the stream), an offset's first one too
        hf = self._heading_clock.factor(m) if isinstance(m, Heading) else 1.0
        kind, nr = self._measurement(m, H, y, R)
        if not nr:
            return
        if kind == "odometry" and m.v is not None and self.bursts is not None:
            g = np.zeros(self.n)
            g[_SPEEDS] = 1.0
            self.bursts.widen(kf.P, m.sensor, m.t, float(y[0]), float(R[0, 0]), H[0], g)
        blocks = ((m.sensor, kind, 0, nr, (), self._info(m.sensor)[0]),)
        # the innovations are y already: h(x) = 0 in update_blocks' y = z - h(x)
        if hf != 1.0:  # correlated heading samples: fused with the sample's inflated R
            kf.update_blocks(m.t, y[:nr], 0.0, H[:nr], R[:nr, :nr], blocks, (hf,))
        elif kind != "gps" or m.sensor not in self._gps_tau:
            kf.update_blocks(m.t, y[:nr], 0.0, H[:nr], R[:nr, :nr], blocks)
        else:  # a GPS with correlated errors: fused with the fix's inflated covariance
            kf.update_blocks(m.t, y[:nr], 0.0, H[:nr], R[:nr, :nr], blocks, (self._gps_factor(m),))
            if kf.last_verdicts[0]:
                self._fused_fix(m.sensor, m.t)

    def _gps_factor(self, m: GpsFix) -> float:
        """The factor on fix ``m``'s covariance in the fusion (module docstring): 1.0 for a
        white sensor or its first fused fix."""
        tau = self._gps_tau.get(m.sensor)
        if tau is None:
            return 1.0
        return gps_inflation(m.t - self._gps_fused.get(m.sensor, -math.inf), tau)

    def _fused_fix(self, sensor: str, stamp: float) -> None:
        """Record that the fix of GPS ``sensor`` stamped ``stamp`` was fused (or gave the
        initial position): the next fix's inflation counts from it (correlated sensors only)."""
        if sensor in self._gps_tau:
            self._gps_fused[sensor] = stamp

    def estimate(self) -> Estimate | None:
        if self.kf is None:
            return None
        s, P = self.kf.x, self.kf.P
        return Estimate(
            t=self.t if self.t is not None else 0.0,
            pose=(float(s[X]), float(s[Y]), float(s[PSI])),
            pose_cov=P[_POSE_IX],  # advanced indexing: a copy
            state=s.copy(),
            state_cov=P.copy(),
            state_names=self.state_names,
        )

    # ------------------------------------------------------------------ measurements
    def _info(self, name: str) -> tuple:
        """(gate, gyro bias rad/s, heading offset rad, GPS lever arm m, GPS delay s) of a
        sensor, cached."""
        info = self._sensor_info.get(name)
        if info is None:
            s = self._sensor(name)
            bias = float(s.gyro_bias) if s is not None and s.gyro_bias != "estimate" else 0.0
            lever = tuple(s.lever_arm) if s is not None else (0.0, 0.0)
            info = self._sensor_info[name] = (self._gate(name), bias,
                                              self._heading_offset(name), lever,
                                              s.delay if s is not None else 0.0)
        return info

    def _measurement(self, m, H, y, R) -> tuple[str, int]:
        """The rows of measurement ``m`` (``igvc_measurements``) written into H (2, n), y, R
        (2, 2): (kind, number of rows), 0 rows when it is not used (or initialises a heading
        offset). Models: module docstring; calibration states: class docstring."""
        _gate, bias, offset, lever, delay = self._info(m.sensor)
        x = self.kf.x.tolist()
        ks = -1 if self._ks is None else self._ks
        if isinstance(m, GyroYawRate):
            bi = self._bias_idx.get(m.sensor, -1)
            return "gyro", im.gyro_rows(x, bi, bias, m.yaw_rate, m.var, H, y, R, 0)
        if isinstance(m, Heading):
            local = m.source == "pose"
            hi = self._hoff_idx.get(m.sensor)
            if hi is not None and hi not in self._hoff_ready:
                self._init_offset(m, hi, x[PSI] if local else HALF_PI - x[THETA],
                                  [(PSI, 1.0)] if local else [(THETA, -1.0)])
                return "heading", 0
            return "heading", im.heading_rows(x, local, -1 if hi is None else hi, offset, m.yaw,
                                              m.var, H, y, R, 0)
        if isinstance(m, ForwardAccel):
            return "accel", im.accel_rows(x, m.accel, m.var, H, y, R, 0)
        if isinstance(m, WheelOdometry):
            return "odometry", im.odometry_rows(
                x, ks, self.track, m.v is not None, m.yaw_rate is not None,
                0.0 if m.v is None else m.v, 0.0 if m.yaw_rate is None else m.yaw_rate,
                m.v_var, m.yaw_rate_var, H, y, R, 0)
        if isinstance(m, WheelSpeeds):
            if self.wheel_radius is None:
                self.log.rejected[(m.sensor, "no_wheel_radius")] += 1
                return "wheels", 0
            return "wheels", im.wheel_rows(x, ks, self.wheel_radius, m.left, m.right,
                                           m.left_var, m.right_var, H, y, R, 0)
        if isinstance(m, GpsFix):
            if m.status < 0:
                self.log.rejected[(m.sensor, "no_fix")] += 1
                return "gps", 0
            (c00, c01, _), (c10, c11, _), _ = m.cov.tolist()
            return "gps", im.gps_rows(x, self.radius, lever[0], lever[1], delay, m.lat, m.lon,
                                      c00, c11, c01, c10, H, y, R, 0)
        return "", 0

    def _init_offset(self, m: Heading, hi: int, g: float, row: list) -> None:
        """hoff = wrap(z - g(x)), g the reading without its offset (linear: ``row``): variance
        var(g) + R, covariance -cov(g, .) with the rest of the state."""
        kf = self.kf
        gP = sum(a * kf.P[c] for c, a in row)  # row of G P
        x = kf.x.copy()
        x[hi] = (m.yaw - g + math.pi) % _TWO_PI - math.pi
        P = kf.P.copy()
        P[hi, :] = -gP
        P[:, hi] = -gP
        P[hi, hi] = sum(a * gP[c] for c, a in row) + m.var
        kf.x, kf.P = x, P
        self._hoff_ready.add(hi)
        self.log.note(m.t, f"heading offset of {m.sensor} initialised to "
                           f"{math.degrees(x[hi]):.1f} deg")
