"""Seed 003's unicycle EKF (x, y, psi, v, psi_dot) with GPS, wheel speed and gyro, corrected and
extended for real data. Design notes, derivations and measured figures:
docs/design/unicycle_ekf.md.

State (world = local ENU frame; the same names and conventions as ``ddfuse.factors.state``)::

    index  name  unit   meaning
    0      x     m      position east
    1      y     m      position north
    2      psi   rad    heading of body x, CCW from east, kept wrapped to [-pi, pi)
    3      v     m/s    forward speed along body x (with scale states: the odometry's, v_odo)
    4      w     rad/s  yaw rate, CCW positive (with scale states and no gyro: the odometry's)
    5..    bg    rad/s  gyro bias (gyro reading = w + bg), one per IMU with gyro_bias: estimate
    ..     hoff  rad    heading offset (reading = wrap(psi + hoff)), per IMU with
                        heading_offset: estimate
    ..     k_v   1      odometry scales (the odometry reports v / k_v, w / k_w) when the config
    ..     k_w   1      states the geometry's uncertainty (robot.*_std)
    ..     acc   m/s^2  the twist's rates, when ``robot.twist_walk`` holds ``speed_rate`` /
    ..     yacc  rad/s^2  ``yaw_rate_rate`` (the first stage of ``ddfuse tune`` only; no config
                        states them): v' = acc, w' = yacc, each rate a random walk of that
                        density (m/s^2/sqrt(s), rad/s^2/sqrt(s)): a twist that ramps

Motion: the exact SE(2) constant-twist step (``motion='exact'``, the smoother's motion model)
or the seed's Euler step; the twist and calibration states are random walks
(:class:`ProcessNoise`; ``ddfuse.ekf_baseline.unicycle_motion``). Pose error
(``pose_error``): 'se2', the body-frame error in SE(2) exponential coordinates (default), or
'world'. Measurements (each gated on its own with its sensor's chi-square gate;
``ddfuse.ekf_baseline.unicycle_measurements``)::

    GpsFix          z = enu[:2]        h = antenna at t - delay: (x, y) + R(psi) lever_arm
    WheelOdometry   z = (v, yaw_rate)  h = v, w (w / k_w with a gyro)
    WheelSpeeds     z = (w_l, w_r)     h = ((v - w L/2) / r, (v + w L/2) / r)
    GyroYawRate     z = yaw_rate       h = w + bg (k_w w_odo without a fused gyro)
    Heading         z = yaw            h = wrap(psi + hoff), innovation wrapped

A GPS sensor with ``correlation_time`` > 0 has each fix fused with an inflated R
(``estimation.gps_correlation``), and so has each sample of a heading sensor with one
(``estimation.heading_correlation``); gate, log and recovery keep R. Under the heavy-tailed
speed walk (``estimation.twist_tails``) an odometry speed sample the burst explains better
widens the speed's prior by the burst's variance first. ``cfg.ekf.rate``: 'event'
(predict to and update with each message) or a rate in Hz (one stacked update per step).
Initialisation: a known pose, the first ground truth, a measured heading, or dead reckoning
aligned onto the GPS track once the fixes spread over ``init_distance`` m.
"""

from __future__ import annotations

import math

import numpy as np
from ddfuse.ekf_baseline import GIVEN_POSE_STD
from ddfuse.ekf_baseline import compiled as jit
from ddfuse.ekf_baseline import unicycle_measurements as um
from ddfuse.ekf_baseline.gps_robust import robust_spec
from ddfuse.ekf_baseline.kalman import DEFAULT_LOCKOUT_COUNT, DEFAULT_LOCKOUT_TIME, KalmanCore
from ddfuse.ekf_baseline.unicycle_compiled import UnicycleKernels
from ddfuse.ekf_baseline.unicycle_layout import (
    SensorSlot,
    StateLayout,
    process_noise,
    start_mode,
)
from ddfuse.ekf_baseline.unicycle_measurements import delayed_gps_terms
from ddfuse.ekf_baseline.unicycle_motion import (
    ProcessNoise,
    euler_step_jac,
    pose_correct,
    scaled_step_terms,
    se2_error_terms,
    se2_log_error,
    se2_retract,
    twist_densities,
    unicycle_process_noise,
)
from ddfuse.ekf_baseline.unicycle_start import UnicycleStart
from ddfuse.estimation.config import Config
from ddfuse.estimation.estimator import Estimate, Estimator
from ddfuse.estimation.gaps import gap_note, grown_pose_cov, is_gap
from ddfuse.estimation.heading_correlation import HeadingClock
from ddfuse.estimation.measurements import (
    GpsFix,
    GroundTruthPose,
    GyroYawRate,
    Heading,
    WheelOdometry,
    WheelSpeeds,
)
from ddfuse.estimation.twist_tails import SpeedBursts, SpeedTails
from ddfuse.factors.kinematics import se2_step_jac

__all__ = ["ProcessNoise", "UnicycleEkf", "unicycle_process_noise", "euler_step_jac",
           "twist_densities", "scaled_step_terms", "delayed_gps_terms", "se2_error_terms",
           "se2_retract", "se2_log_error", "pose_correct", "POSE_ERRORS"]

_cos = math.cos
_sin = math.sin
_USED = (GpsFix, WheelOdometry, WheelSpeeds, GyroYawRate, Heading)
POSE_ERRORS = ("se2", "world")  # UnicycleEkf(pose_error=...): module docstring, "Pose error"
# Longest prediction step (s): a gap between messages (a driver restart, a dropped link) is
# predicted in steps of at most this. One linearised step over a turn misplaces the noise the
# twist's walk puts in along the way: after a 2 s gap at 0.5 rad/s the position covariance was
# off by 0.3-2.7x in some direction, after 10 s by 0.035-80x (overconfident across the turn);
# 0.1 s steps are within 0.25 % of 1 ms ones. The messages' own 10-50 Hz steps are never split.
MAX_PREDICT_DT = 0.1

class UnicycleEkf(UnicycleStart, UnicycleKernels, Estimator):
    """Unicycle EKF (module docstring). Convention for every filter in this package:
    ``UnicycleEkf(cfg, *, initial_pose=None)``, then ``process(m)`` per measurement in time order,
    ``estimate()`` at any time, ``finish()`` after the last one.

    Options: ``noise`` (:class:`ProcessNoise`), ``motion`` ('exact' SE(2) step or the seed's
    'euler'), ``init_distance`` (m of GPS spread before the GPS heading alignment),
    ``initial_std`` (position m, heading rad) for a known initial pose, ``v_std0`` (m/s),
    ``w_std0`` (rad/s), ``bias_std0`` (rad/s) prior sigmas, ``lockout_count`` /
    ``lockout_time`` for the gate lock-out recovery of :class:`ekf_baseline.kalman.KalmanCore`.
    ``reference``: run the Python reference (the dense numpy ``KalmanCore.update_blocks``)
    instead of the compiled kernels of ``ekf_baseline.kalman_jit`` (prediction, measurement
    models, gate, Joseph update, innovation log; what they defer -- a gate lock-out's
    recovery, the initialisations -- runs the reference's Python code on the same arrays; the
    acceleration-limit densities' bookkeeping stays in Python and is copied into the kernels'
    arrays when it changes them). The tests compare the two (tests/test_ekf_compiled.py).
    ``pose_error``: 'se2' (default) carries the pose error in SE(2) exponential coordinates,
    'world' as the world-frame difference (module docstring, "Pose error").
    """

    name = "ekf_unicycle"

    def __init__(
        self,
        cfg: Config,
        *,
        initial_pose: tuple[float, float, float] | None = None,
        noise: ProcessNoise | None = None,
        motion: str = "exact",
        init_distance: float = 5.0,
        initial_std: tuple[float, float] = GIVEN_POSE_STD,
        v_std0: float = 1.0,
        w_std0: float = 0.5,
        bias_std0: float = 0.02,
        lockout_count: int = DEFAULT_LOCKOUT_COUNT,
        lockout_time: float = DEFAULT_LOCKOUT_TIME,
        reference: bool = False,
        pose_error: str = "se2",
    ) -> None:
        super().__init__()
        if pose_error not in POSE_ERRORS:
            raise ValueError(f"pose_error must be one of {POSE_ERRORS}, got {pose_error!r}")
        self.pose_error = pose_error
        self._lie = pose_error == "se2"
        # the kernels compiled or loaded now, not in the first step; on a cold cache under the
        # "reference" policy (ddfuse run), the Python reference path instead (jit.usable)
        kernels = ("unicycle",) if cfg.ekf.rate == "event" else ("unicycle", "unicycle_stacked")
        self.compiled = not reference and jit.usable(*kernels)
        self.reference = not self.compiled
        if self.compiled:
            self.log = jit.BufferedLog()
        if motion not in ("exact", "euler"):
            raise ValueError(f"motion must be 'exact' or 'euler', got {motion!r}")
        self.cfg = cfg
        self.noise, self._amax = process_noise(cfg, noise)
        self._tw_last: dict[tuple[str, int], float] = {}  # (sensor, 3 v / 4 w): last stamp
        self._tw_period: dict[int, dict[str, float]] = {3: {}, 4: {}}  # per sensor, s
        self._tw_on = self._amax != (None, None)
        # the heavy-tailed speed walk (estimation.twist_tails; module docstring)
        tails = SpeedTails.from_robot(cfg.robot) if noise is None else None
        self.bursts = SpeedBursts(tails) if tails is not None else None
        self._step_jac = se2_step_jac if motion == "exact" else euler_step_jac
        self.motion = motion
        self.rate = None if cfg.ekf.rate == "event" else float(cfg.ekf.rate)
        self.init_distance = float(init_distance)
        self.initial_std = initial_std
        self.v_std0, self.w_std0, self.bias_std0 = v_std0, w_std0, bias_std0
        self._lockout = (lockout_count, lockout_time)

        lay = StateLayout.of(cfg, self.noise, self._lie)
        self._sensors = lay.sensors
        self._walks = lay.walks
        self._scale = lay.scale
        self._ks = lay.scale.index if lay.scale else None
        self._w_true = lay.w_true
        self._rates = lay.rates
        self.state_names = lay.names
        self.n = len(lay.names)
        self._hoff_states = lay.hoff_states
        self._bias_states = lay.bias_states
        self._hoff_ready: set[int] = set()
        self._if, self._iq = lay.f_index, lay.q_index
        # a GPS sensor with time-correlated errors (module docstring)
        self._gps_corr = any(s.correlation_time > 0.0 for s in cfg.of_kind("gps"))
        # heading sensors with time-correlated samples (estimation.heading_correlation)
        self._heading_clock = HeadingClock(cfg)
        # a robust GPS model (gps.model; ekf_baseline.gps_robust): its fixes take the Python path
        self._robust = robust_spec(cfg)

        self._mode, self._initial_pose = start_mode(cfg, initial_pose)
        has_gps = bool(cfg.of_kind("gps"))
        self._has_gps = has_gps
        self._pending_pos: tuple[float, float, np.ndarray] | None = None
        self._pending_fix: tuple[str, float] | None = None  # (sensor, stamp) of _pending_pos
        # GPS sensor -> stamp of its last fused fix (module docstring, "Time-correlated GPS
        # errors"); kept for the sensors with a correlation time only
        self._gps_fused: dict[str, float] = {}
        self._pair_fix: dict[str, float] = {}  # GPS sensor -> stamp of its last fix in _pairs
        self._pending_head: tuple[float, float] | None = None
        self._aligned = self._mode != "align"
        self._pairs: list[tuple[float, float, float, float, float]] = []  # dr x, y, gps e, n, var

        self.kf: KalmanCore | None = None
        self.t: float | None = None  # time of the state
        self._buf: list = []
        self._t0 = 0.0
        self._k = 0
        self._F = np.eye(self.n)
        self._T = np.eye(self.n)  # estimate(): the se2 error's covariance to the world frame
        self._Q = np.zeros((self.n, self.n))
        self._F_flat = self._F.reshape(-1)  # views: assigning into them fills F and Q
        self._Q_flat = self._Q.reshape(-1)
        self._wheel = (cfg.robot.wheel_radius, cfg.robot.track_width)

    # ------------------------------------------------------------------ public
    def process(self, m) -> None:
        """Consume one measurement (time order). Unused types are ignored."""
        if isinstance(m, GroundTruthPose):
            if self._mode == "ground_truth" and self.kf is None:
                self._start(m.t, m.x, m.y, m.yaw, np.diag(np.square(
                    (self.initial_std[0], self.initial_std[0]))), self.initial_std[1] ** 2)
            return
        if not isinstance(m, _USED):
            return
        self.in_order(m)  # no history: a stale measurement is refused, not fused as current
        if self.kf is None and not self._try_start(m):
            return
        if self._aligned and self.t is not None:
            last = self._buf[-1].t if self._buf else self.t
            if is_gap(m.t - last):
                self._after_gap(m.t, last)
        if self.rate is None:
            if self.compiled:
                p = self._pack(m)
                if p is not None:
                    self._run_event(m, p)
                    return
            self._predict_to(m.t)
            self._apply((m,))
            return
        # fixed rate: step at t0 + k / rate, applying what arrived since the previous step
        step = self._t0 + self._k / self.rate
        if m.t > step:
            if self._buf:
                self._step(step)
            # the next step is the first grid time at or after m.t
            self._k = max(self._k + 1, math.ceil((m.t - self._t0) * self.rate - 1e-9))
        self._buf.append(m)

    def finish(self) -> None:
        """Apply what is still buffered (rate mode) at the time of the last message."""
        if self._buf:
            self._step(max(self._buf[-1].t, self.t if self.t is not None else -math.inf))

    def estimate(self) -> Estimate | None:
        """Current estimate (at the time of the last predict/update), None before the heading is
        known (see the module docstring)."""
        if self.kf is None or not self._aligned:
            return None
        kf = self.kf
        x = kf.x
        if not self._lie:
            P = kf.P.copy()
        elif self.compiled:  # (the runner asks at 10 Hz: ~1 us here, ~9 us in numpy)
            P = kf.kj.world_cov(kf.W, self.n, float(x[2]))
        else:  # to the world frame, to first order: A P A^T, A = blockdiag(R(psi), I)
            c, s = _cos(x[2]), _sin(x[2])
            T = self._T
            T[0, 0], T[0, 1], T[1, 0], T[1, 1] = c, -s, s, c
            P = T @ kf.P @ T.T
            P += P.T
            P *= 0.5
        return Estimate(
            t=self.t,
            pose=(float(x[0]), float(x[1]), float(x[2])),
            pose_cov=P[:3, :3].copy(),
            state=x.copy(),
            state_cov=P,
            state_names=self.state_names,
            pose_error=self.pose_error,
        )

    def _after_gap(self, t: float, last: float) -> None:
        """No message from ``last`` to ``t`` (a gap, ``estimation.gaps``): apply what is
        buffered (rate mode), then restart at ``t`` from the last pose with its covariance
        grown by what the robot could have done in the gap; the twist unknown (zero, sigma the
        robot's limits), the calibration states as learnt with their walks over the gap, every
        cross term with the pose dropped. The held twist is not predicted over it (that put the
        track hundreds of metres off; docs/design/gaps.md)."""
        if self._buf:
            self._step(self._t0 + self._k / self.rate)
        kf, robot = self.kf, self.cfg.robot
        gap = t - self.t
        x, P = kf.x.copy(), kf.P.copy()
        pose = grown_pose_cov(P[:3, :3], gap, robot)
        P[:5, :] = 0.0
        P[:, :5] = 0.0
        P[:3, :3] = pose
        P[3, 3], P[4, 4] = robot.speed_limit ** 2, robot.yaw_rate_limit ** 2
        for i, w in zip(self._bias_states + self._hoff_states, self._walks, strict=True):
            P[i, i] += w * gap
        for _ti, ri, q2 in self._rates:
            P[ri, ri] += q2 * gap
        x[3] = x[4] = 0.0
        kf.x, kf.P = x, P
        self.t = t
        self.log.note(t, gap_note(self.name, gap, pose))

    def _sensor(self, name: str) -> SensorSlot:
        info = self._sensors.get(name)
        if info is None:  # a sensor not in the config (synthetic streams): defaults
            info = self._sensors[name] = SensorSlot()
        return info

    # ------------------------------------------------------------------ filter steps
    def _step(self, ts: float) -> None:
        buf = self._buf
        self._buf = []
        if self.compiled:
            prev: dict[str, float] = {}
            packs = [self._pack(m, prev) for m in buf]
            if None not in packs:
                self._run_stacked(ts, buf, packs)
                return
        self._predict_to(ts)
        self._apply(buf)

    def _gap_steps(self, t: float) -> None:
        """Over a gap to ``t`` (more than ``MAX_PREDICT_DT``), predict all but the last of the
        equal steps of at most that; the last is the caller's (the kernels predict it with
        their update), so that every path splits a gap alike."""
        n = math.ceil((t - self.t) / MAX_PREDICT_DT - 1e-9)
        for k in range(1, n):
            self._predict_step(self.t + (t - self.t) / (n - k + 1))

    def _predict_to(self, t: float) -> None:
        """Predict to ``t``, in equal steps of at most ``MAX_PREDICT_DT`` over a gap."""
        if t - self.t <= 0.0:
            return  # same stamp (or a tiny reorder): apply at the current state time
        self._gap_steps(t)
        self._predict_step(t)

    def _predict_step(self, t: float) -> None:
        """One prediction step to ``t`` (> the state's time)."""
        dt = t - self.t
        kf = self.kf
        xs = kf.x.tolist()
        ks = self._ks
        if self._lie:
            # the world-frame step's F and Q mapped to the pose error's coordinates
            nz = self.noise
            kv, kw = (1.0, 1.0) if ks is None else (xs[ks], xs[ks + 1])
            x1, y1, p1, F, q = scaled_step_terms(
                xs[0], xs[1], xs[2], xs[3], xs[4], kv, kw, dt,
                self.motion == "euler", nz.acc, nz.yaw_acc, nz.pos_long, nz.pos_lat, nz.heading,
                self._w_true)
            F, q = se2_error_terms(xs[2], p1, F, q)
            self._F_flat[self._if] = F if ks is not None else F[:7] + F[12:]
        elif ks is None:
            x1, y1, p1, J = self._step_jac(xs[0], xs[1], xs[2], xs[3], xs[4], dt)
            j0, j1 = J[0], J[1]
            # one flat fancy-index assignment each for F and Q: element assignments cost
            # ~100 ns apiece, the (row, col) fancy index twice the flat one
            self._F_flat[self._if] = (j0[2], j0[3], j0[4], j1[2], j1[3], j1[4], dt)
            q = unicycle_process_noise(xs[2], xs[3], dt, self.noise)
        else:
            nz = self.noise
            x1, y1, p1, F, q = scaled_step_terms(
                xs[0], xs[1], xs[2], xs[3], xs[4], xs[ks], xs[ks + 1], dt,
                self.motion == "euler", nz.acc, nz.yaw_acc, nz.pos_long, nz.pos_lat, nz.heading,
                self._w_true)
            self._F_flat[self._if] = F
        self._Q_flat[self._iq] = q + q + tuple([w * dt for w in self._walks])
        for ti, ri, q2 in self._rates:  # x_ti' = x_ri, x_ri a walk: kalman_jit_predict's
            self._F[ti, ri] = dt
            Q = self._Q
            Q[ti, ti] += q2 * dt * dt * dt / 3.0
            Q[ti, ri] = Q[ri, ti] = 0.5 * q2 * dt * dt
            Q[ri, ri] = q2 * dt
            xs[ti] += dt * xs[ri]
        xs[0], xs[1], xs[2] = x1, y1, p1
        kf.predict(self._F, self._Q, xs)
        self.t = t

    def _twist_msg(self, m, info: SensorSlot) -> None:
        """With stated acceleration limits: record the twist components message ``m`` measures
        (odometry and wheel speeds: v, w; a used gyro: w) for :meth:`_twist_seen`. Both paths
        call it once per message they apply, before the next prediction."""
        if isinstance(m, GyroYawRate):
            if info.use_w and self._amax[1] is not None:
                self._twist_seen(m.sensor, 4, m.t)
        elif isinstance(m, WheelOdometry):
            if m.v is not None:
                self._twist_seen(m.sensor, 3, m.t)
            if m.yaw_rate is not None:
                self._twist_seen(m.sensor, 4, m.t)
        elif isinstance(m, WheelSpeeds):
            self._twist_seen(m.sensor, 3, m.t)
            self._twist_seen(m.sensor, 4, m.t)

    def _twist_seen(self, sensor: str, comp: int, t: float) -> None:
        """Record a measurement of v (comp 3) or w (4) by ``sensor`` at ``t``; with stated
        acceleration limits, re-derive the twist densities when the shortest sample period of
        that component's sensors changes by more than 10 %."""
        key = (sensor, comp)
        last = self._tw_last.get(key)
        self._tw_last[key] = t
        if last is None or not t > last:
            return
        per = self._tw_period[comp]
        old = min(per.values()) if per else None
        per[sensor] = t - last
        new = min(per.values())
        if old is None or abs(new - old) > 0.1 * old:
            p3, p4 = self._tw_period[3], self._tw_period[4]
            self.noise = twist_densities(*self._amax, min(p3.values()) if p3 else None,
                                         min(p4.values()) if p4 else None, self.noise)
            if self.compiled and self.kf is not None:  # the kernels' copy of the densities
                self.kf.set_noise(self._noise_floats())

    def _apply(self, ms) -> None:
        """Assemble the piecewise measurement model of the messages ``ms`` -- per measurement its
        innovation, H rows and R (``unicycle_measurements``, the kernels' models) -- and update
        through ``KalmanCore.update_blocks`` (module docstring, "Measurements")."""
        kf = self.kf
        x = kf.x.tolist()  # python floats: the models' arithmetic is the kernels'
        t = self.t
        tw = self._tw_on
        ks = -1 if self._ks is None else self._ks
        wt = self._w_true
        mr = 2 * len(ms)
        H = np.zeros((mr, self.n))
        y = np.zeros(mr)
        R = np.zeros((mr, mr))
        blocks: list[tuple] = []  # (sensor, kind, first row, end row, angles, gate)
        nr = 0
        # correlated GPS fixes and heading samples: (block index, GPS sensor or None, stamp,
        # factor)
        corr: list[tuple] = []
        prev: dict[str, float] = {}

        def add(sensor, kind, m, gate):
            nonlocal nr
            blocks.append((sensor, kind, nr, nr + m, (), gate))
            nr += m

        for m in ms:
            info = self._sensors.get(m.sensor) or self._sensor(m.sensor)
            if tw:  # (the sample periods set the densities of the next prediction)
                self._twist_msg(m, info)
            if isinstance(m, GyroYawRate):
                if not info.use_w:
                    continue
                bi = -1 if info.bias_idx is None else info.bias_idx
                add(m.sensor, "gyro", um.gyro_rows(x, ks, wt, bi, info.bias, m.yaw_rate, m.var,
                                                   H, y, R, nr), info.gate)
            elif isinstance(m, Heading):
                if not info.use_yaw:
                    continue
                hf = self._heading_clock.factor(m)
                if not self._aligned:
                    self.log.rejected[(m.sensor, "before_init")] += 1
                    continue
                hi = info.hoff_idx
                if hi is not None and hi not in self._hoff_ready:
                    self._init_offset(t, m, hi)
                    x = kf.x.tolist()
                    continue
                if hf != 1.0:
                    corr.append((len(blocks), None, m.t, hf))
                add(m.sensor, "heading", um.heading_rows(x, -1 if hi is None else hi, info.hoff,
                                                         m.yaw, m.var, H, y, R, nr), info.gate)
            elif isinstance(m, WheelOdometry):
                if m.v is not None:
                    if self.bursts is not None:  # the heavy-tailed walk (module docstring)
                        h = np.zeros(self.n)
                        h[3] = 1.0  # with scale states the odometry's speed, k_v the true's
                        self.bursts.widen(kf.P, m.sensor, m.t, m.v - x[3], m.v_var, h,
                                          h / (1.0 if ks < 0 else x[ks]))
                    add(m.sensor, "v", um.speed_rows(x, m.v, m.v_var, H, y, R, nr), info.gate)
                if m.yaw_rate is not None:
                    add(m.sensor, "yaw_rate", um.yaw_rate_rows(x, ks, wt, m.yaw_rate,
                                                               m.yaw_rate_var, H, y, R, nr),
                        info.gate)
            elif isinstance(m, GpsFix):
                if m.enu is None or m.status < 0:
                    self.log.rejected[(m.sensor, "no_fix" if m.status < 0 else "no_enu")] += 1
                    continue
                if not self._aligned:
                    self._pairs.append((x[0], x[1], m.enu[0], m.enu[1],
                                        0.5 * float(m.cov[0][0] + m.cov[1][1])))
                    self._pair_fix[m.sensor] = m.t
                    e0, n0 = self._pairs[0][2], self._pairs[0][3]
                    if math.hypot(m.enu[0] - e0, m.enu[1] - n0) >= self.init_distance:
                        self._align(t)
                        x = kf.x.tolist()
                    continue
                (c00, c01, _), (c10, c11, _), _ = m.cov.tolist()
                if info.tau > 0.0:
                    corr.append((len(blocks), m.sensor, m.t,
                                 self._gps_factor(m, info.tau, prev)))
                lx, ly = info.lever
                add(m.sensor, "gps", um.gps_rows(x, ks, wt, self._lie, lx, ly, info.delay,
                                                 m.enu[0], m.enu[1], c00, c11, c01, c10, H, y,
                                                 R, nr), info.gate)
            elif isinstance(m, WheelSpeeds):
                r, L = self._wheel
                if r is None or L is None:
                    raise ValueError("WheelSpeeds need robot.wheel_radius and robot.track_width")
                add(m.sensor, "wheels", um.wheel_rows(x, ks, wt, r, L, m.left, m.right,
                                                      m.left_var, m.right_var, H, y, R, nr),
                    info.gate)
        if not blocks:
            return
        xb = kf.x[:3].tolist() if self._lie else None
        fuse = None
        if corr:  # correlated GPS fixes, heading samples: fused with their inflated covariance
            fuse = [1.0] * len(blocks)
            for i, _, _, f in corr:
                fuse[i] = f
        # the innovations are y already: h(x) = 0 in update_blocks' y = z - h(x)
        kf.update_blocks(t, y[:nr], 0.0, H[:nr], R[:nr, :nr], blocks, fuse)
        if corr:
            verdicts = kf.last_verdicts
            for i, sensor, stamp, _ in corr:
                if sensor is not None and verdicts[i]:
                    self._fused_fix(sensor, stamp)
        if xb is not None:
            # KalmanCore added the correction K y; its position part is the body-frame rho
            xa = kf.x.copy()
            x1, y1 = pose_correct(xb[0], xb[1], xb[2], float(xa[0]) - xb[0],
                                  float(xa[1]) - xb[1])
            xa[0], xa[1] = x1, y1
            kf.x = xa
