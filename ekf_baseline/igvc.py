"""Seed 000's 11-state IGVC EKF, built as the document means it (its errors: docs/errata.md).

State (STATE_NAMES, index: meaning, unit)::

    0 lat      geodetic latitude, rad            6 v        forward speed, m/s
    1 lon      longitude, rad                    7 psi_dot  yaw rate, rad/s, CCW +
    2 theta    bearing, rad, CLOCKWISE from N    8 v_l      left wheel rim speed, m/s
    3 x        local ENU east, m                 9 v_r      right wheel rim speed, m/s
    4 y        local ENU north, m               10 a        forward acceleration, m/s^2
    5 psi      yaw, rad, CCW from local east

Frames: the seed's x north / y east with a "left positive" heading is not a consistent frame for
its own eqs. 6-7; this filter keeps x, y, psi in the project's right-handed local ENU frame
(x east, y north, psi CCW from east) internally, so ``Estimate.pose`` is (x, y, psi) without a
conversion. theta stays a compass bearing, as the great-circle formulas (seed eqs. 4-5) need;
in the ENU frame at the datum theta = pi/2 - psi (the meridian convergence, about
dlon sin(lat) -- 2e-6 rad at 10 m east at 45 deg -- is ignored).

Motion models (``motion='euler'`` or ``'icc'``): generated once from sympy in
``ekf_baseline/igvc_jacobians.py`` (derivation: ``ekf_baseline/igvc_codegen.py``). The seed's
11-vector is redundant -- (lat, lon) and (x, y) are one position, theta and psi one heading,
(v, psi_dot) and (v_l, v_r) one twist. The models keep the redundant pairs consistent: the
wheel speeds are recomputed from (v, psi_dot) every step, and the process noise enters each pair
through one shared noise source (``IgvcNoise``), so a GPS update of lat/lon moves x/y with it
through their correlation and a compass update of theta moves psi.

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

Every update goes through ``ddfuse.ekf_baseline.kalman.KalmanCore`` (Joseph form, wrapped angle
innovations, per-sensor chi-square gate with lock-out recovery).

Time-correlated GPS errors: a GPS sensor with ``correlation_time`` tau > 0 has each fix fused
with R_f = f R, f = ``estimation.gps_correlation.inflation(t - t_last, tau)``, t_last the stamp
of the last fix of that sensor the filter fused (accepted by the gate or by a lock-out
recovery, or the fix the filter started at; none: f = 1); the gate, the logged innovation and
NIS, and a recovery's widening keep R (``KalmanCore``'s ``fuse``), as in the unicycle EKF.
tau = 0 leaves the arithmetic as without the key, bit for bit.

Poles: the (lat, lon) state is singular at a pole (the longitude is undefined there, and every
lon term carries 1/cos(lat)), so the filter refuses to run within ``POLE_LIMIT_KM`` (about 10
km) of one, |lat| > ``POLE_LIMIT_DEG`` = 89.91 deg: ``process`` raises ``PolarRegionError``
(a ValueError) when the datum, the first fix or the state is there, and the runner reports it
in the estimator's row (errata 000 #37). Use the unicycle EKF or the smoother, whose state is
the local ENU plane. The limit is where the ignored meridian convergence stops being small
against the model's own allowance for it: at a distance r from the pole, driving at v turns the
true bearing against the filter's theta = pi/2 - psi by about v sin(theta) / r rad/s; at r =
10 km and 1 m/s that is 1e-4 rad/s, already the frame-heading noise the model allows per
sqrt(s) (``IgvcNoise.frame_heading_psd`` = 1e-8 rad^2/s), and over a 1 km drive it adds up to
0.1 rad, more than a compass's error. Closer in it grows as 1/r: the sample drive (40 m across)
re-projected to 100 m from the pole gave ATE 0.40 m and NEES 30 (0.12 m and 3.1 at 10 km and
at 300 km), at 50 m 2.2 m and NEES 355, and at 11 m the great-circle step's sin(lat) rounded
to 1 and its Jacobian's 1/sqrt(1 - sin^2 lat) divided by zero. The double-precision
resolution of that step, R^2 1.1e-16 / r per step (0.5 um at 10 km, 0.4 mm at 11 m), is not
the binding limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from ddfuse.ekf_baseline import GIVEN_POSE_STD
from ddfuse.ekf_baseline import compiled as jit
from ddfuse.ekf_baseline import igvc_jacobians as gen
from ddfuse.ekf_baseline.calibration import ScaleStates
from ddfuse.ekf_baseline.kalman import KalmanCore
from ddfuse.estimation import geodesy
from ddfuse.estimation.config import DEFAULT_GATE, Config, SensorConfig
from ddfuse.estimation.estimator import Estimate, Estimator
from ddfuse.estimation.gps_correlation import inflation as gps_inflation
from ddfuse.estimation.measurements import (
    ForwardAccel,
    GpsFix,
    GroundTruthPose,
    GyroYawRate,
    Heading,
    WheelOdometry,
    WheelSpeeds,
)

__all__ = ["IgvcEkf", "IgvcNoise", "PolarRegionError", "POLE_LIMIT_DEG", "STATE_NAMES",
           "sphere_radius", "gps_model", "heading_model"]

STATE_NAMES = gen.STATE_NAMES
# the measurement types the filter uses (the others are ignored, before its start too)
_USED = (GpsFix, WheelOdometry, WheelSpeeds, GyroYawRate, Heading, ForwardAccel)
LAT, LON, THETA, X, Y, PSI, V, W, VL, VR, A = range(11)
N = 11
HALF_PI = 0.5 * math.pi
# flat indices (row-major, 11 x 11) of the entries of Q that IgvcEkf._q_values gives, in order
_Q_INDEX = np.ravel_multi_index((
    [X, Y, LON, LAT, LON, X, LAT, Y, PSI, THETA, PSI, THETA, A, W, VL, VR],
    [X, Y, LON, LAT, X, LON, Y, LAT, PSI, THETA, THETA, PSI, A, W, VL, VR]), (N, N))
DEFAULT_TRACK = 0.5  # m, used only for the wheel-speed states when robot.track_width is unset
FEED_GAP_S = 5.0  # s without any message: a gap in the feed (``IgvcEkf._bridge_gap``)
GAP_RESTART_STD = 10e3  # m: a gap that leaves the position this uncertain restarts the filter
# s: a longer gap restarts it without predicting over it (its 0.05 s steps: 6000 per 300 s;
# the sample bag's limits give a 450 km position sigma after 300 s)
GAP_CARRY_MAX_S = 300.0
# deg: |lat| beyond which the filter refuses to run, about POLE_LIMIT_KM from a pole (module
# docstring: the meridian convergence the model ignores grows as 1/distance to the pole)
POLE_LIMIT_DEG = 89.91
POLE_LIMIT_KM = 10.0
_POLE_LIMIT_RAD = math.radians(POLE_LIMIT_DEG)


class PolarRegionError(ValueError):
    """The filter's position (datum, first fix or state) is within ``POLE_LIMIT_KM`` of a pole,
    where seed 000's (lat, lon) state cannot represent it (module docstring)."""


_TWO_PI = 2.0 * math.pi
_POSE_IX = np.ix_((X, Y, PSI), (X, Y, PSI))  # the (x, y, psi) block of P
# sparse H rows (KalmanCore.update_sparse) of the measurements of single states
_ROWS_W = (((W, 1.0),),)
_ROWS_A = (((A, 1.0),),)
_ROWS_PSI = (((PSI, 1.0),),)
_ROWS_THETA = (((THETA, -1.0),),)  # compass yaw = pi/2 - theta + offset
# the compiled kernels' message types and return bits (ddfuse.ekf_baseline.compiled)
_T_GYRO, _T_HEAD, _T_HEAD_POSE, _T_ACCEL, _T_ODOM, _T_WHEELS, _T_GPS = (
    jit.T_GYRO, jit.T_HEAD, jit.T_HEAD_POSE, jit.T_ACCEL, jit.T_ODOM, jit.T_WHEELS, jit.T_GPS)
_DEFER = jit.DEFER
_REJECTED = jit.REJECTED


def sphere_radius(lat_rad: float) -> float:
    """Radius (m) of the sphere that best fits WGS-84 around latitude ``lat_rad``: the Gaussian
    mean radius sqrt(M N) of the meridian (M) and prime-vertical (N) radii of curvature.

    The seed's great-circle formulas assume a sphere; with this radius the north and east scale
    errors against the ellipsoid are equal and opposite, (N - M) / (2 sqrt(M N)), about 0.17 %
    at 45 deg, instead of up to 0.35 % with the seed's "either value works" polar or equatorial
    radius."""
    s2 = math.sin(lat_rad) ** 2
    w = 1.0 - geodesy.WGS84_E2 * s2
    m = geodesy.WGS84_A * (1.0 - geodesy.WGS84_E2) / w**1.5
    n = geodesy.WGS84_A / math.sqrt(w)
    return math.sqrt(m * n)


@dataclass
class IgvcNoise:
    """Process noise and initial uncertainty of the 11-state filter (SI units, std devs or PSDs).

    Continuous white-noise spectral densities (variance per second of the random walk they
    drive): ``jerk_psd`` on a, (m/s^3)^2 s; ``yaw_accel_psd`` on psi_dot, (rad/s^2)^2 s;
    ``position_psd`` on the position, m^2/s, applied to (x, y) and (lat, lon) alike (Euler and
    slip errors); ``heading_psd`` on the heading, rad^2/s, applied to psi and theta alike;
    ``frame_psd``, m^2/s, independent between (lat, lon) and (x, y): the sphere-vs-ellipsoid and
    meridian-convergence mismatch between the two position representations (it also keeps P
    positive definite); ``frame_heading_psd``, rad^2/s, likewise between theta and psi (the
    meridian convergence, d(lon) sin(lat), makes the compass bearing and the local yaw drift
    apart by ~v tan(lat) / R rad/s). ``slip_var``, (m/s)^2 per step, is the wheel speed's
    deviation from the body twist (slip); it does not accumulate because the wheel states are
    recomputed each step.
    """

    jerk_psd: float = 0.5
    yaw_accel_psd: float = 0.1
    position_psd: float = 4e-4
    heading_psd: float = 2.5e-5
    frame_psd: float = 1e-6
    frame_heading_psd: float = 1e-8
    slip_var: float = 1e-4
    init_position_std: float = GIVEN_POSE_STD[0]  # m, with an initial pose given
    init_heading_std: float = GIVEN_POSE_STD[1]  # rad, with an initial pose given
    init_speed_std: float = 0.5  # m/s
    init_yaw_rate_std: float = 0.2  # rad/s
    init_accel_std: float = 0.5  # m/s^2
    # calibration states (IgvcEkf docstring); walks used when the IMU's config states none
    gyro_bias_walk: float = 1e-4  # rad/s/sqrt(s)
    heading_offset_walk: float = 0.02  # rad/sqrt(s)
    init_bias_std: float = 0.02  # rad/s


def gps_model(s: np.ndarray, lever_arm: tuple[float, float], radius: float):
    """Antenna (lat, lon) predicted from state ``s`` and its Jacobian, both in radians.

    ``lever_arm`` (m) is the antenna's (x forward, y left) position in the body frame; its ENU
    offset is rotated by psi. Returns (h (2,) = (lat, lon), H (2, 11))."""
    lat, psi = s[LAT], s[PSI]
    lx, ly = lever_arm
    c, sn = math.cos(psi), math.sin(psi)
    e_off = c * lx - sn * ly  # m, east
    n_off = sn * lx + c * ly  # m, north
    cl = math.cos(lat)
    h = np.array([lat + n_off / radius, s[LON] + e_off / (radius * cl)])
    H = np.zeros((2, N))
    H[0, LAT] = 1.0
    H[0, PSI] = e_off / radius
    H[1, LON] = 1.0
    H[1, LAT] = e_off * math.sin(lat) / (radius * cl * cl)
    H[1, PSI] = -n_off / (radius * cl)
    return h, H


def heading_model(s: np.ndarray, offset: float, local: bool):
    """Heading sensor reading predicted from ``s`` (rad, wrapped) and its (1, 11) Jacobian.

    Global (compass, seed Theta_g): yaw = pi/2 - theta + offset. Local (``local``, seed
    Theta_l): yaw = psi + offset."""
    H = np.zeros((1, N))
    if local:
        h = s[PSI] + offset
        H[0, PSI] = 1.0
    else:
        h = HALF_PI - s[THETA] + offset
        H[0, THETA] = -1.0
    return np.array([(h + math.pi) % (2.0 * math.pi) - math.pi]), H


def igvc_q_values(lat: float, dt: float, radius: float, position_psd: float, frame_psd: float,
                  heading_psd: float, frame_heading_psd: float, jerk_psd: float,
                  yaw_accel_psd: float, slip_var: float) -> tuple[float, ...]:
    """``IgvcEkf.process_noise`` (same model) as the values of Q at the flat indices _Q_INDEX, from
    the :class:`IgvcNoise` densities as floats (its units; ``lat`` rad, ``dt`` s, ``radius`` m).
    Plain floats so that the compiled filter (ekf_baseline.kalman_jit) runs this same code."""
    rc = radius * math.cos(lat)
    r = radius
    pos = position_psd * dt
    frame = frame_psd * dt
    head = heading_psd * dt
    fh = frame_heading_psd * dt
    lon_x = pos / rc
    lat_y = pos / r
    return (
        pos + frame, pos + frame,  # x x, y y
        pos / rc / rc + frame / rc / rc,  # lon lon
        pos / r / r + frame / r / r,  # lat lat
        lon_x, lon_x, lat_y, lat_y,  # lon x, x lon, lat y, y lat
        head + fh, head + fh, -head, -head,  # psi psi, theta theta, psi theta, theta psi
        jerk_psd * dt, yaw_accel_psd * dt, slip_var, slip_var,  # a, w, vl, vr
    )


class IgvcEkf(Estimator):
    """Seed 000's 11-state EKF (module docstring) as an :class:`Estimator`.

    Calibration states follow the seed's 11, as in the unicycle EKF: a gyro bias (gyro =
    psi_dot + bg) per IMU whose ``gyro_bias`` is 'estimate', a heading offset (reading =
    wrap(heading + hoff), initialised from the first reading) per IMU whose ``heading_offset``
    is 'estimate' -- random walks of the IMU's stated densities (noise.gyro_bias_walk,
    heading_offset_walk) or IgvcNoise's -- and the odometry scales k_v, k_w (odometry and wheel
    speeds report v / k_v, psi_dot / k_w) when the config states the geometry's uncertainty.
    A GPS sensor's ``delay`` is compensated: the antenna is predicted at t - delay (first
    order: moved back by v delay along the bearing). The config's robot.slip replaces the
    position and heading noise densities (isotropic here: the mean of the along- and
    across-track variances).

    ``initial_pose`` (x, y, yaw) in the local ENU frame (m, m, rad) overrides the config's
    ``initial_pose``; with 'ground_truth' in the config and no ``initial_pose`` the filter starts
    at the first GroundTruthPose it is given (pass ``stream.ground_truth[0]`` as initial_pose when
    the ground truth is not in the measurement stream). Without any initial pose and with a GPS
    configured, it starts at the first fix, with the heading from the first usable Heading or,
    failing that, from the GPS course once the fixes are ``course_distance`` m apart; without GPS
    it starts at the origin with yaw 0. ``datum`` (lat deg, lon deg, alt m) is the local ENU
    origin (``stream.datum``); default the config's, else the first fix. ``motion`` is 'euler'
    (seed eq. 14) or 'icc' (seed appendix A). Prediction steps are at most ``max_step`` s.
    ``reference``: run the dense numpy implementation (``process_noise``, ``gps_model``,
    ``heading_model``, ``KalmanCore.update``) instead of the fast path (generated sparse F,
    float Q, ``KalmanCore.update_sparse``); the tests compare the two. ``compiled``: each step
    in the numba kernels of ``ekf_baseline.kalman_jit`` (the generated Jacobian compiled as it
    is); default when numba is installed and ``reference`` is not set (as UnicycleEkf).
    """

    name = "igvc_ekf"

    def __init__(
        self,
        cfg: Config,
        *,
        initial_pose: tuple[float, float, float] | None = None,
        datum: tuple[float, float, float] | None = None,
        motion: str = "euler",
        noise: IgvcNoise | None = None,
        max_step: float = 0.05,
        course_distance: float = 3.0,
        reference: bool = False,
        compiled: bool | None = None,
    ) -> None:
        super().__init__()
        if motion not in ("euler", "icc"):
            raise ValueError(f"motion must be 'euler' or 'icc', got {motion!r}")
        self.cfg = cfg
        self.motion = motion
        self.reference = bool(reference)
        if compiled is None:
            compiled = not self.reference and jit.available()
        elif compiled and (self.reference or not jit.available()):
            raise ValueError("compiled=True needs numba and reference=False")
        self.compiled = bool(compiled)
        if self.compiled:
            jit.warm_up("igvc")  # compile / load the kernels now, not in the first step
            self.log = jit.BufferedLog()
        self._jrows: dict[str, int] = {}  # sensor -> row in the compiled core's sensor table
        self._step = gen.euler_step if motion == "euler" else gen.icc_step
        self._step_sparse = gen.euler_step_sparse if motion == "euler" else gen.icc_step_sparse
        self._sensor_info: dict[str, tuple] = {}
        # GPS sensors with time-correlated errors: name -> correlation time (s), and the stamp
        # of each one's last fused fix (module docstring)
        self._gps_tau = {s.name: float(s.correlation_time) for s in cfg.of_kind("gps")
                         if s.correlation_time > 0.0}
        self._gps_fused: dict[str, float] = {}
        self.noise = noise or IgvcNoise()
        slip = cfg.robot.slip
        if slip and noise is None:
            # the robot's stated slip replaces the defaults; the position noise here is
            # isotropic: the mean of the along- and across-track variances (same trace)
            ns = self.noise
            long_, lat_ = slip.get("longitudinal"), slip.get("lateral")
            if long_ is not None or lat_ is not None:
                d = math.sqrt(ns.position_psd)
                long_ = d if long_ is None else long_
                lat_ = d if lat_ is None else lat_
                ns = replace(ns, position_psd=0.5 * (long_ * long_ + lat_ * lat_))
            if "heading" in slip:
                ns = replace(ns, heading_psd=slip["heading"] ** 2)
            self.noise = ns
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
        self._first_fix: GpsFix | None = None
        self._heading_init: tuple[float, float] | None = None  # (yaw, var)
        if initial_pose is not None and (self.datum is not None or not self._has_gps):
            self._init(None, initial_pose, self.noise.init_position_std ** 2,
                       self.noise.init_heading_std ** 2)
        self._pose_given = initial_pose

    # ------------------------------------------------------------------ initialisation
    def _calibration_states(self, cfg: Config) -> None:
        """The states after the seed's 11 (class docstring) and their random-walk densities."""
        names = list(STATE_NAMES)
        walks: dict[int, float] = {}  # state index -> variance per second
        self._bias_idx: dict[str, int] = {}
        self._hoff_idx: dict[str, int] = {}
        ns = self.noise
        # (the reading it corrects, config field, state prefix, its index map, walk key, default)
        for use, field, prefix, idx, walk, default in (
                ("yaw_rate", "gyro_bias", "bg", self._bias_idx, "gyro_bias_walk",
                 ns.gyro_bias_walk),
                ("yaw", "heading_offset", "hoff", self._hoff_idx, "heading_offset_walk",
                 ns.heading_offset_walk)):
            for s in cfg.of_kind("imu"):
                if use in s.use and getattr(s, field) == "estimate":
                    idx[s.name] = len(names)
                    walks[len(names)] = s.noise.get(walk, default) ** 2
                    names.append(f"{prefix}:{s.name}")
        self._scale = ScaleStates.append_to(cfg, names)
        self._ks = self._scale.index if self._scale else None
        self.state_names = tuple(names)
        self.n = len(names)
        self._walks = walks
        self._hoff_ready: set[int] = set()

    def _init(self, t: float | None, pose, pos_var: float, yaw_var: float) -> None:
        x, y, yaw = (float(v) for v in pose)
        if self.datum is not None:
            lat, lon, _ = geodesy.enu_to_geodetic(x, y, 0.0, *self.datum)
            lat, lon = math.radians(lat), math.radians(lon)
        else:
            # no datum and no GPS: lat/lon are relative to (0, 0) and unobserved
            lat, lon = y / self.radius, x / self.radius
        ns = self.noise
        s0 = np.zeros(N)
        s0[[LAT, LON, THETA, X, Y, PSI]] = lat, lon, HALF_PI - yaw, x, y, yaw
        gp = self._position_noise_map(lat)
        P0 = pos_var * (gp @ gp.T)
        gh = np.zeros((N, 1))
        gh[PSI, 0], gh[THETA, 0] = 1.0, -1.0
        P0 += yaw_var * (gh @ gh.T)
        P0 += np.diag(self._frame_var(lat, 1.0))
        P0[V, V] = ns.init_speed_std ** 2
        P0[W, W] = ns.init_yaw_rate_std ** 2
        P0[A, A] = ns.init_accel_std ** 2
        # the wheel speeds are functions of (v, psi_dot), plus slip: s0 -> T s0 maps them
        T = np.eye(N)
        T[VL, VL] = T[VR, VR] = 0.0
        T[VL, V], T[VL, W], T[VR, V], T[VR, W] = 1.0, -0.5 * self.track, 1.0, 0.5 * self.track
        P0 = T @ P0 @ T.T
        P0[VL, VL] += ns.slip_var
        P0[VR, VR] += ns.slip_var
        # the calibration states: biases about 0, offsets uniform on the circle until the first
        # reading initialises them, scales about 1
        n = self.n
        x0 = np.zeros(n)
        x0[:N] = s0
        Pn = np.zeros((n, n))
        Pn[:N, :N] = P0
        for i in self._bias_idx.values():
            Pn[i, i] = ns.init_bias_std ** 2
        for i in self._hoff_idx.values():
            Pn[i, i] = math.pi * math.pi / 3.0
        if self._scale:
            self._scale.set_prior(x0, Pn)
        # lon is an angle too: wrapped so that crossing the antimeridian does not leave it
        # outside [-pi, pi) (the GPS innovation is wrapped as well)
        angles = (LON, THETA, PSI, *self._hoff_idx.values())
        if self.compiled:
            self.kf = self._compiled_core(x0, Pn, angles)
        else:
            self.kf = KalmanCore(x0, Pn, self.log, state_angles=angles)
        self.kf.after_inflation = self._retie_pairs
        if self._ks is not None:
            self.kf.held_in_recovery = (self._ks, self._ks + 1)
        self.t = t

    def _position_noise_map(self, lat: float) -> np.ndarray:
        """(11, 2) map of an (east, north) position perturbation in metres to the state."""
        g = np.zeros((N, 2))
        g[X, 0] = 1.0
        g[LON, 0] = 1.0 / (self.radius * math.cos(lat))
        g[Y, 1] = 1.0
        g[LAT, 1] = 1.0 / self.radius
        return g

    def _retie_pairs(self, kf: KalmanCore) -> None:
        """Re-tie the redundant pairs (lat, lon) ~ (x, y) and theta ~ pi/2 - psi after a gate
        recovery inflated P (``KalmanCore._recover``).

        Their independent part (the frame noise, ``frame_psd``) is tiny and observed by no
        measurement: the GPS measures lat/lon and reaches x, y only through their correlation.
        The inflation scales it by alpha (x639 on rl_husky_gps.bag at 54 s) along with the
        rest, and what is left of it after the next fixes is then never reduced: x, y
        decorrelated from lat/lon (0.99 -> 0.18 in 20 s) and their sigma grew to 3.5 m for
        200 s while lat/lon held 0.2 m. So the pair differences are pinned back to the frame
        noise of one second, a constraint update c(s) = (x - E, y - N, psi + theta - pi/2)
        with that variance (Joseph form) and no innovation: the means agree to the frame
        mismatch already, only their errors drifted apart."""
        P = kf.P
        lat = float(kf.x[LAT])
        D = np.zeros((3, self.n))
        D[0, X], D[0, LON] = 1.0, -self.radius * math.cos(lat)
        D[1, Y], D[1, LAT] = 1.0, -self.radius
        D[2, PSI] = D[2, THETA] = 1.0
        Rc = np.diag((self.noise.frame_psd, self.noise.frame_psd, self.noise.frame_heading_psd))
        PD = P @ D.T
        K = np.linalg.solve(D @ PD + Rc, PD.T).T
        A = np.eye(self.n) - K @ D
        P_new = A @ P @ A.T + K @ Rc @ K.T
        kf.P = 0.5 * (P_new + P_new.T)

    def _frame_var(self, lat: float, scale: float) -> np.ndarray:
        d = np.zeros(N)
        v = self.noise.frame_psd * scale
        d[LAT] = v / self.radius**2
        d[LON] = v / (self.radius * math.cos(lat)) ** 2
        d[X] = d[Y] = v
        d[THETA] = d[PSI] = self.noise.frame_heading_psd * scale
        return d

    def _try_init_without_pose(self, m) -> None:
        """Start from GPS (position) plus a heading, or at the origin without GPS."""
        if not self._has_gps:
            self._init(m.t, self._pose_given or (0.0, 0.0, 0.0),
                       self.noise.init_position_std ** 2, self.noise.init_heading_std ** 2)
            return
        if isinstance(m, Heading) and m.sensor not in self._hoff_idx and m.source != "pose":
            # a compass with a known offset gives the heading; an estimated offset does not
            self._heading_init = (m.yaw - self._heading_offset(m.sensor), m.var)
        if not isinstance(m, GpsFix) or m.status < 0:
            return
        if self.datum is None:
            # the frame the fix's enu is in: a live converter's first fix may have been dropped
            # before it reached this filter, and the next one is then not the datum
            self.datum = m.datum if m.datum is not None else (m.lat, m.lon, m.alt)
            self.radius = sphere_radius(math.radians(self.datum[0]))
        e, n = self._fix_enu(m)
        pos_var = 0.5 * float(m.cov[0, 0] + m.cov[1, 1])
        if self._pose_given is not None:
            self._init(m.t, self._pose_given, self.noise.init_position_std ** 2,
                       self.noise.init_heading_std ** 2)
            return
        if self._heading_init is not None:
            self._init(m.t, (e, n, self._heading_init[0]), pos_var, self._heading_init[1])
            self._fused_fix(m.sensor, m.t)  # the position is this fix's
            return
        if self._first_fix is None:
            self._first_fix = m
            return
        e0, n0 = self._fix_enu(self._first_fix)
        d = math.hypot(e - e0, n - n0)
        if d >= self.course_distance:
            # the course over ground from the first fix; assumes the robot drove forward
            yaw_var = (2.0 * pos_var) / (d * d)
            self._init(m.t, (e, n, math.atan2(n - n0, e - e0)), pos_var, yaw_var)
            self._fused_fix(m.sensor, m.t)
            self.log.note(m.t, f"heading initialised from the GPS course over {d:.1f} m")

    def _fix_enu(self, m: GpsFix) -> tuple[float, float]:
        if m.enu is not None:
            return m.enu[0], m.enu[1]
        e, n, _ = geodesy.geodetic_to_enu(m.lat, m.lon, m.alt, *self.datum)
        return e, n

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

    def process_noise(self, s: np.ndarray, dt: float) -> np.ndarray:
        """Discrete process noise Q (11, 11) of one step of ``dt`` s at state ``s`` (see
        IgvcNoise): shared position noise for (x, y) and (lat, lon), shared heading noise for
        psi and -theta, jerk on a, angular acceleration on psi_dot, slip on the wheel speeds."""
        ns = self.noise
        g = self._position_noise_map(s[LAT])
        Q = ns.position_psd * dt * (g @ g.T)
        Q[PSI, PSI] += ns.heading_psd * dt
        Q[THETA, THETA] += ns.heading_psd * dt
        Q[PSI, THETA] -= ns.heading_psd * dt
        Q[THETA, PSI] -= ns.heading_psd * dt
        Q += np.diag(self._frame_var(s[LAT], dt))
        Q[A, A] += ns.jerk_psd * dt
        Q[W, W] += ns.yaw_accel_psd * dt
        Q[VL, VL] += ns.slip_var
        Q[VR, VR] += ns.slip_var
        return Q

    def predict_to(self, t: float) -> None:
        """Propagate the state to time ``t`` (s) in steps of at most ``max_step``."""
        kf = self.kf
        dt_total = t - self.t
        if dt_total <= 0.0:
            return
        n = max(1, math.ceil(dt_total / self.max_step - 1e-9))
        dt = dt_total / n
        if self.reference:
            for _ in range(n):
                xs = kf.x.tolist()
                f, F11 = self._step(xs[:N], dt, self.track, self.radius)
                F = np.eye(self.n)
                F[:N, :N] = F11
                Q = np.zeros((self.n, self.n))
                Q[:N, :N] = self.process_noise(kf.x, dt)
                for i, q in self._walks.items():
                    Q[i, i] = q * dt
                kf.predict(F, Q, list(f) + xs[N:])
        else:
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
        """``process_noise`` (same model) as the values of Q at the flat indices _Q_INDEX."""
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
        if self.kf is not None and self.t is not None and m.t - self.t > FEED_GAP_S:
            self._bridge_gap(m.t)
        if self.kf is None:
            if self._wait_truth:
                self._count_before_init(m)
                return
            self._try_init_without_pose(m)
            # a datum or start taken from this fix: refused at it, not a message later
            self._check_pole()
            if self.kf is None:
                self._count_before_init(m)
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
        """Carry the filter over a gap in the feed (no message for more than FEED_GAP_S), or
        restart it when the gap leaves its position unknown (sigma over GAP_RESTART_STD).

        The jerk-driven model grows the position's variance as dt^5: 50 m of sigma after a 10
        s gap on the sample bag, 3.5 km after 60 s, 450 km after 300 s. Past a few tens of km
        the two position representations (lat, lon on the sphere, x, y on the plane) move
        apart under it, the covariance between them is lost, and the GPS, which measures
        lat/lon, no longer reaches x, y: their sigma stayed at 2 m after a 300 s gap, 125 m
        after 900 s, and a day broke the filter; re-tying the pairs (``_retie_pairs``) at
        such variances loses positive definiteness. A restart starts as the run did (GPS and a
        heading, or the GPS course), as the smoother starts a new window after a gap that
        leaves its heading unknown."""
        gap = t - self.t
        if gap <= GAP_CARRY_MAX_S:  # beyond it, not worth its predict steps: restarted anyway
            self.predict_to(t)
            sd = math.sqrt(max(float(self.kf.P[X, X]), float(self.kf.P[Y, Y])))
            if sd <= GAP_RESTART_STD:
                return
            why = f"position sigma {sd / 1000.0:.0f} km over it"
        else:
            why = f"over {GAP_CARRY_MAX_S:.0f} s"
        self.log.note(t, f"{self.name}: restarted after a {gap:.1f} s gap in the feed ({why}): "
                         "it starts again as at the beginning")
        self.kf = None
        self.t = None
        self._first_fix = None
        self._heading_init = None
        self._pose_given = None  # the configured start pose was the run's, not this one's
        self._wait_truth = False
        self._hoff_ready = set()

    def _update(self, m) -> None:
        """The measurement update of ``m`` in Python (after the prediction to m.t)."""
        block = self._measurement(m)
        if block is None:
            return
        kind, y, rows, R = block
        blocks = ((m.sensor, kind, y, rows, R, self._info(m.sensor)[0]),)
        # the compiled filter's Python updates (what its kernels defer) are the reference's
        update = (self.kf.update_dense if self.reference or self.compiled
                  else self.kf.update_sparse)
        if kind != "gps" or m.sensor not in self._gps_tau:
            update(m.t, blocks)
        else:  # a GPS with correlated errors: fused with the fix's inflated covariance
            update(m.t, blocks, (self._gps_factor(m),))
            if self.kf.last_verdicts[0]:
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

    # ------------------------------------------------------------------ compiled path
    def _compiled_core(self, x0, P0, angles):
        """The JitKalmanCore of this filter (ddfuse.ekf_baseline.compiled): F's pattern from the
        generated model (its ones, its variable entries, the calibration states' identity),
        Q's entries (_Q_INDEX), the random walks."""
        kj = jit.kernels()
        self._igvc_event = kj.igvc_event
        n = self.n
        ones, variable = ((gen.EULER_F_ONES, gen.EULER_F_VARIABLE) if self.motion == "euler"
                          else (gen.ICC_F_ONES, gen.ICC_F_VARIABLE))
        f_pairs = [divmod(k, N) for k in ones] + [divmod(k, N) for k in variable]
        f_pairs += [(i, i) for i in range(N, n)]
        ns = self.noise
        self._jrows = {}
        return jit.JitKalmanCore(
            x0, P0, self.log, state_angles=angles, kinds=jit.IGVC_KINDS, f_pairs=f_pairs,
            f_variable=range(len(ones), len(ones) + len(variable)),
            q_pairs=[divmod(int(k), N) for k in _Q_INDEX], walks=list(self._walks.items()),
            motion=0 if self.motion == "euler" else 1, ks=self._ks,
            noise=(ns.position_psd, ns.frame_psd, ns.heading_psd, ns.frame_heading_psd,
                   ns.jerk_psd, ns.yaw_accel_psd, ns.slip_var),
            params={kj.FP_WHEEL_R: self.wheel_radius, kj.FP_TRACK: self.track,
                    kj.FP_RADIUS: self.radius, kj.FP_MAXSTEP: self.max_step})

    def _pack(self, m):
        """The kernels' arguments (typ, sensor row, z0, z1, r0, r1, r01, r10, flags, rf) for
        message ``m``, or None when it needs the Python path: a heading whose offset is not
        initialised yet, a fix without a fix, wheel speeds without a wheel radius, another
        message type. ``rf``: the factor on R in the fusion (``_gps_factor``)."""
        name = m.sensor
        row = self._jrows.get(name)
        if row is None:
            gate, bias, offset, lever, delay = self._info(name)
            row = self._jrows[name] = self.kf.sensor_row(
                name, gate=gate, bias=bias, hoff=offset, lever=lever, delay=delay,
                bias_idx=self._bias_idx.get(name), hoff_idx=self._hoff_idx.get(name))
        cls = m.__class__
        if cls is GyroYawRate:
            return (_T_GYRO, row, m.yaw_rate, 0.0, m.var, 0.0, 0.0, 0.0, 0, 1.0)
        if cls is Heading:
            hi = self._hoff_idx.get(name)
            if hi is not None and hi not in self._hoff_ready:
                return None
            return (_T_HEAD_POSE if m.source == "pose" else _T_HEAD, row, m.yaw, 0.0, m.var,
                    0.0, 0.0, 0.0, 0, 1.0)
        if cls is ForwardAccel:
            return (_T_ACCEL, row, m.accel, 0.0, m.var, 0.0, 0.0, 0.0, 0, 1.0)
        if cls is WheelOdometry:
            v, w = m.v, m.yaw_rate
            return (_T_ODOM, row, 0.0 if v is None else v, 0.0 if w is None else w, m.v_var,
                    m.yaw_rate_var, 0.0, 0.0, (v is not None) | (w is not None) << 1, 1.0)
        if cls is WheelSpeeds and self.wheel_radius is not None:
            return (_T_WHEELS, row, m.left, m.right, m.left_var, m.right_var, 0.0, 0.0, 0, 1.0)
        if cls is GpsFix and m.status >= 0:
            (c00, c01, _), (c10, c11, _), _ = m.cov.tolist()
            return (_T_GPS, row, m.lat, m.lon, c00, c11, c01, c10, 0, self._gps_factor(m))
        return None

    def _run_event(self, m, p) -> None:
        """Predict to ``m.t`` and update with ``m`` (packed as ``p``) in one kernel call."""
        kf = self.kf
        t = m.t
        dt = t - self.t
        code = self._igvc_event(kf.fp, kf.ip, kf.W, kf.sf, kf.si, kf.lg, dt, t, *p)
        if code:
            code = kf.settle(code, self._igvc_event, dt, t, *p)
        if dt > 0.0:
            self.t = t
        if code & _DEFER:  # predicted; the update needs Python (lock-out, singular S)
            self._update(m)
        elif self._gps_tau and p[0] == _T_GPS and not code & _REJECTED:
            self._fused_fix(m.sensor, t)  # fused: the next fix's inflation counts from it

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

    def _measurement(self, m):
        """The model of measurement ``m`` as (kind, innovation y, sparse H rows, R) for
        ``KalmanCore.update_sparse`` / ``update_dense``, or None (not used, or used to
        initialise a heading offset). Models: module docstring; calibration states: class
        docstring."""
        _gate, bias, offset, lever, delay = self._info(m.sensor)
        x = self.kf.x.tolist()
        ks = self._ks
        if isinstance(m, GyroYawRate):
            bi = self._bias_idx.get(m.sensor)
            if bi is None:
                return "gyro", (m.yaw_rate - (x[W] + bias),), _ROWS_W, ((m.var,),)
            return ("gyro", (m.yaw_rate - (x[W] + x[bi]),), (((W, 1.0), (bi, 1.0)),),
                    ((m.var,),))
        if isinstance(m, Heading):
            if m.source == "pose":
                g, row = x[PSI], [(PSI, 1.0)]
            else:
                g, row = HALF_PI - x[THETA], [(THETA, -1.0)]
            hi = self._hoff_idx.get(m.sensor)
            if hi is not None:
                if hi not in self._hoff_ready:
                    self._init_offset(m, hi, g, row)
                    return None
                offset = x[hi]
                row.append((hi, 1.0))
            h = (g + offset + math.pi) % _TWO_PI - math.pi
            return ("heading", ((m.yaw - h + math.pi) % _TWO_PI - math.pi,), (tuple(row),),
                    ((m.var,),))
        if isinstance(m, ForwardAccel):
            return "accel", (m.accel - x[A],), _ROWS_A, ((m.var,),)
        if isinstance(m, WheelOdometry):
            return self._odometry_model(m, x, ks)
        if isinstance(m, WheelSpeeds):
            r = self.wheel_radius
            if r is None:
                self.log.rejected[(m.sensor, "no_wheel_radius")] += 1
                return None
            vl, vr = x[VL], x[VR]
            if ks is None:
                return ("wheels", (m.left - vl / r, m.right - vr / r),
                        (((VL, 1.0 / r),), ((VR, 1.0 / r),)),
                        ((m.left_var, 0.0), (0.0, m.right_var)))
            # rim speeds -> (v / k_v, w / k_w) -> wheel speeds through the nominal geometry
            kv, kw = x[ks], x[ks + 1]
            a, b = 0.5 / (kv * r), 0.5 / (kw * r)
            s_, d_ = vl + vr, vr - vl
            dkv, dkw = -a * s_ / kv, b * d_ / kw
            return ("wheels", (m.left - (a * s_ - b * d_), m.right - (a * s_ + b * d_)),
                    (((VL, a + b), (VR, a - b), (ks, dkv), (ks + 1, dkw)),
                     ((VL, a - b), (VR, a + b), (ks, dkv), (ks + 1, -dkw))),
                    ((m.left_var, 0.0), (0.0, m.right_var)))
        if isinstance(m, GpsFix):
            if m.status < 0:
                self.log.rejected[(m.sensor, "no_fix")] += 1
                return None
            # ~1000 fixes per 400 s: the numpy model costs nothing here
            z, hx, H = self._gps_metres(m, lever, delay)
            rows = tuple(tuple((j, float(v)) for j, v in enumerate(row) if v != 0.0)
                         for row in H.tolist())
            cv = m.cov
            return ("gps", (z[0] - hx[0], z[1] - hx[1]), rows,
                    ((float(cv[0, 0]), float(cv[0, 1])), (float(cv[1, 0]), float(cv[1, 1]))))
        return None

    def _odometry_model(self, m: WheelOdometry, x: list, ks: int | None):
        """v = (v_l + v_r) / 2 and yaw rate (v_r - v_l) / L (seed eqs. 18-19), divided by the
        odometry scales k_v, k_w when they are estimated."""
        L = self.track
        kv, kw = (x[ks], x[ks + 1]) if ks is not None else (1.0, 1.0)
        y, rows, var = [], [], []
        if m.v is not None:
            v = 0.5 * (x[VL] + x[VR])
            y.append(m.v - v / kv)
            row = [(VL, 0.5 / kv), (VR, 0.5 / kv)]
            if ks is not None:
                row.append((ks, -v / (kv * kv)))
            rows.append(tuple(row))
            var.append(m.v_var)
        if m.yaw_rate is not None:
            w = (x[VR] - x[VL]) / L
            y.append(m.yaw_rate - w / kw)
            row = [(VR, 1.0 / (L * kw)), (VL, -1.0 / (L * kw))]
            if ks is not None:
                row.append((ks + 1, -w / (kw * kw)))
            rows.append(tuple(row))
            var.append(m.yaw_rate_var)
        if not y:
            return None
        R = ((var[0],),) if len(var) == 1 else ((var[0], 0.0), (0.0, var[1]))
        return "odometry", tuple(y), tuple(rows), R

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

    def _gps_metres(self, m: GpsFix, lever, delay: float = 0.0
                    ) -> tuple[list, list, np.ndarray]:
        """The fix (z), its prediction (hx) and Jacobian (H, (2, n)) in metres (east, north)
        about the current estimate: scaling z, h and H by the same constant leaves gain and NIS
        unchanged and makes the logged residuals readable. With a ``delay`` (s) the antenna
        is predicted where it was that long before the state's time: moved back by v delay
        along the bearing (first order, as the seed's motion model), heading psi - w delay."""
        x = self.kf.x
        s = x[:N].copy()
        J = None
        if delay:
            # s_d = s moved back; J = d s_d / d s for the states that move it
            lat, theta, v, w = s[LAT], s[THETA], s[V], s[W]
            ct, st_ = math.cos(theta), math.sin(theta)
            cl = math.cos(lat)
            R = self.radius
            s[LAT] = lat - delay * v * ct / R
            s[LON] = s[LON] - delay * v * st_ / (R * cl)
            s[PSI] = s[PSI] - delay * w
            J = np.eye(N)
            J[LAT, THETA], J[LAT, V] = delay * v * st_ / R, -delay * ct / R
            J[LON, LAT] = -delay * v * st_ * math.sin(lat) / (R * cl * cl)
            J[LON, THETA], J[LON, V] = -delay * v * ct / (R * cl), -delay * st_ / (R * cl)
            J[PSI, W] = -delay
        h, H = gps_model(s, lever, self.radius)
        if J is not None:
            H = H @ J
        if self.n > N:
            H = np.hstack([H, np.zeros((2, self.n - N))])
        lat0, lon0 = x[LAT], x[LON]
        te, tn = self.radius * math.cos(lat0), self.radius
        zlat, zlon = math.radians(m.lat), math.radians(m.lon)
        dlon_z = (zlon - lon0 + math.pi) % (2.0 * math.pi) - math.pi
        z = [te * dlon_z, tn * (zlat - lat0)]
        hx = [te * (h[1] - lon0), tn * (h[0] - lat0)]
        return z, hx, np.vstack([te * H[1], tn * H[0]])
