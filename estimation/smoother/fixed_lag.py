"""The ISAM2 fixed-lag smoother over keyframes (``gtsam.IncrementalFixedLagSmoother``): the
estimator that routes each message to the collaborator whose job it is.

State: one 9-vector key per keyframe, ``[x, y, psi, v, w, bg, hoff, k_v, k_w]`` (m, m, rad, m/s,
rad/s, rad/s, rad, 1, 1; position and heading in the local ENU frame, twist in the body frame;
``ddfuse.factors.state``). Per keyframe interval: one preintegrated wheel/gyro factor
(``held_twist``), one averaged heading factor (``heading``), a gyro-bias factor from the gyro
minus the odometry yaw rate; per absolute measurement a GPS factor (``gps``) or a landmark
factor (``landmarks``), gated (``gating``). Keyframes: ``smoother.keyframe: gps`` puts one at
each GPS fix or landmark sighting (at most one per ``MIN_KEYFRAME_DT``) and one after
``1/keyframe_rate`` s without any; ``rate`` puts them at ``keyframe_rate`` Hz and carries the
absolute measurements to the newest keyframe along its twist.

Collaborators (each with its own state): ``window`` (gtsam, keyframes, pending factors, lagged
output), ``twist`` (held samples, preintegration), ``headings``, ``gating``, ``gps``,
``landmark_fusion``, ``init`` (start, restart after a gap, re-initialisation).

Outputs: ``estimate()``, the filtered estimate at the newest message's stamp (the newest
keyframe, updated with the heading samples since it, composed with the partial
preintegration); ``lagged_estimates()``, each keyframe as it leaves the window; both with the
pose's marginal covariance (m^2, rad^2). The design, its history and the measured figures:
docs/design/smoother.md.
"""

from __future__ import annotations

import bisect
import math

import numpy as np
from ddfuse.estimation.config import Config, SensorConfig, landmark_maps
from ddfuse.estimation.estimator import IN_ORDER_TOLERANCE, Estimate, Estimator, wrap_angle
from ddfuse.estimation.heading_correlation import HeadingClock
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
from ddfuse.estimation.smoother.gating import Gating
from ddfuse.estimation.smoother.gps import GpsFusion
from ddfuse.estimation.smoother.heading import HeadingAccumulator
from ddfuse.estimation.smoother.held_twist import ODOMETRY_WAIT, HeldTwist, compiled_preintegration
from ddfuse.estimation.smoother.initialisation import Initialisation
from ddfuse.estimation.smoother.isam2 import relinearize_skip
from ddfuse.estimation.smoother.landmarks import LandmarkFusion
from ddfuse.estimation.smoother.noise import MIN_KEYFRAME_DT, SmootherNoise, walk_floor
from ddfuse.estimation.smoother.outputs import compose, estimated_only
from ddfuse.estimation.smoother.window import Window
from ddfuse.factors.gyro import bias_difference_factor
from ddfuse.factors.kinematics import se2_step
from ddfuse.factors.linear import linear_state_factor
from ddfuse.factors.preintegration import WheelGyroPreintegration, preintegrated_factor
from ddfuse.factors.state import BG, KV, KW, NAMES


class FixedLagSmoother(Estimator):
    """The ISAM2 fixed-lag smoother (see the module docstring)."""

    name = "smoother"
    keep_all = False  # BatchSmoother keeps every factor for a final whole-run solve

    def __init__(self, cfg: Config, *, initial_pose=None, landmarks=None, lag: float | None = None,
                 noise: SmootherNoise | None = None, reference: bool = False,
                 lagged: bool = True, keep_all: bool | None = None) -> None:
        """``initial_pose``: (x m, y m, psi rad) in local ENU, else the config's, else from the
        GPS course; ``landmarks``: id -> (east, north) m, else the config's maps; ``lag`` (s):
        else the config's. ``reference``: preintegrate with the Python
        ``WheelGyroPreintegration`` instead of its compiled twin (the same numbers, for tests).
        ``lagged``: whether to output the lagged track (``lagged_estimates``); its covariances
        are a quarter to a third of the smoother's cost, so a caller that does not use it turns
        it off. The filtered output is the same either way, and ``final_state`` is still
        given. ``keep_all``: keep every factor of the run too (the class's default: the
        batch's), for a batch that shares this run (``batch.SharedBatch``)."""
        super().__init__()
        self.cfg = cfg
        if keep_all is not None:
            self.keep_all = keep_all
        pim_class = WheelGyroPreintegration if reference else compiled_preintegration()
        self.stopped: str | None = None  # why it gave up (then every process call says so)
        self.finished = False
        self.lag = float(lag if lag is not None else cfg.smoother.lag)
        if not (self.lag > 0.0 and math.isfinite(self.lag)):
            # gtsam would take it and fail later, deep inside an update (IndexError on 'x0')
            raise ValueError(f"smoother lag: expected seconds > 0, got {self.lag:g}")
        self.noise = noise or SmootherNoise.from_config(cfg)
        # as the EKFs: the config's map and its given start pose unless the caller passes them
        landmarks = dict(landmark_maps(cfg) if landmarks is None else landmarks)
        self.given_pose = initial_pose if initial_pose is not None else (
            tuple(cfg.initial_pose) if isinstance(cfg.initial_pose, (tuple, list)) else None)
        self.sensors: dict[str, SensorConfig] = {s.name: s for s in cfg.sensors}
        imus = [s for s in cfg.of_kind("imu") if "yaw_rate" in s.use]
        self.gyro_names = {s.name for s in imus}
        self.est_bias = any(s.gyro_bias == "estimate" for s in imus)
        self.fixed_bias = next((float(s.gyro_bias) for s in imus if s.gyro_bias != "estimate"),
                               0.0)
        heads = cfg.heading_sensors()
        self.heading_sensors = bool(heads)
        self.est_hoff = any(s.heading_offset == "estimate" for s in heads)
        # odometry scale states, as in the EKFs (ekf_baseline.calibration): estimated when the
        # config states how well the geometry is known and a sensor gives odometry
        self.scale_prior = cfg.robot.scale_std if (
            cfg.of_kind("odometry") or cfg.of_kind("wheels")) else None
        self._scale_rw = (max(self.noise.scale_rw, walk_floor(max(self.scale_prior[:2])))
                          if self.scale_prior is not None else self.noise.fixed_rw)
        self.has_gps = bool(cfg.of_kind("gps"))
        self.odometry_held_back = bool(cfg.of_kind("odometry") or cfg.of_kind("wheels"))
        # keyframes closer than MIN_KEYFRAME_DT would break walk_floor's margin: at 75 Hz and
        # more (13 ms apart) gtsam declared the window indeterminate within 0.4 s
        self.keyframe_rate = min(cfg.smoother.keyframe_rate, 1.0 / MIN_KEYFRAME_DT)
        self.kf_policy = cfg.smoother.keyframe
        self.initialised = False
        self.held: list = []  # messages since the last odometry sample, waiting for the next
        self.now = -math.inf  # stamp of the newest message seen
        log, noise = self.log, self.noise
        self.window = Window(self.lag, keep_all=self.keep_all, lagged=lagged,
                             relinearize_skip=relinearize_skip(cfg.gps.model))
        # the batch's record of its preintegrated and bias-difference factors (batch_factors)
        self.factor_record: list | None = [] if self.keep_all else None
        self.twist = HeldTwist(cfg.robot, noise, pim_class, self.fixed_bias)
        self.gating = Gating(self.window, noise, log, est_bias=self.est_bias,
                             est_hoff=self.est_hoff)
        self.headings = HeadingAccumulator(
            self.sensors, noise, self.twist, self.window, self.gating, log,
            est_bias=self.est_bias, est_hoff=self.est_hoff,
            est_scales=self.scale_prior is not None, clock=HeadingClock(cfg))
        self.gps = GpsFusion(cfg, self.sensors, noise, self.twist, self.window, self.gating, log,
                             self.flush)
        self.landmark_fusion = LandmarkFusion(cfg, self.sensors, landmarks, self.window,
                                              self.gating, log, self.flush)
        self.init = Initialisation(self)

    @property
    def lagged(self) -> bool:
        return self.window.lagged

    # --- measurement handling ---------------------------------------------------------------
    def process(self, m) -> None:
        """Consume one measurement: in stamp order, but for a GPS fix or a landmark sighting up
        to the lag late (``late_horizon``, ``_late``); an older one of another kind raises
        ``LateMeasurement``."""
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
        if m.t < self.newest_t - IN_ORDER_TOLERANCE:
            self._late(m)
            return
        if m.t > self.newest_t:
            self.newest_t = m.t
        self.take(m)

    def take(self, m) -> None:
        """``process`` past its checks: also what ``Initialisation`` replays of the messages it
        held (older than the newest processed, and in order among themselves)."""
        if not self.initialised:
            if self.init.restart is not None:
                self.init.restart_now(m)
            else:
                self.init.uninitialised(m)
            return
        if m.t - self.now > ODOMETRY_WAIT and math.isfinite(self.now):
            self.init.after_gap(m.t)
            if self.init.restart is not None:
                self.init.restart_now(m)
                return
        self.now = max(self.now, m.t)
        if isinstance(m, (WheelOdometry, WheelSpeeds)):
            # Odometry is held BACKWARD over its period (``held_twist``): the messages that
            # arrived inside it are integrated now.
            self.twist.set_odometry(m)
            self.release_held()
            self._step(m)
            return
        if self.odometry_held_back:
            self.held.append(m)
            if m.t - self.held[0].t > ODOMETRY_WAIT:  # odometry stopped: hold the last forward
                self.release_held()
            return
        self._step(m)

    def late_horizon(self, m) -> float:
        """How late (s behind the newest stamp processed) ``m`` may come: the lag for a GPS fix
        or a landmark sighting (it goes to the window's keyframe nearest its stamp; older than
        the lag it is dropped and counted), 0 for the rest. Wheel odometry and gyro samples
        are preintegrated in stamp order and heading samples averaged into the open keyframe
        interval, carried by its preintegrated yaw: one older than the newest stamp belongs to
        an interval already integrated or closed, and putting it there would mean
        re-integrating the window."""
        return self.lag if isinstance(m, (GpsFix, LandmarkObservation)) else 0.0

    def _late(self, m) -> None:
        """A measurement older than the newest processed (``late_horizon``): a GPS fix or a
        landmark sighting waits with the held messages when its stamp is past the integrated
        odometry (as it would have on time), else goes to the window's keyframe nearest its
        stamp (``_absolute``); anything else raises ``LateMeasurement``."""
        if not isinstance(m, (GpsFix, LandmarkObservation)):
            self.in_order(m)  # raises: it cannot be used that late
        if not self.initialised:
            init = self.init
            if (isinstance(m, GpsFix) and self.has_gps and init.restart is None
                    and (self.given_pose is None or init.realign is not None)):
                # the GPS course waiting for its baseline (``Initialisation.uninitialised``):
                # the fix goes to its place in the buffer, read and replayed in stamp order
                init.uninitialised(m)
                return
            # a restart after a gap starts from the messages in order
            self.log.rejected[(m.sensor, "late, before the window started")] += 1
            return
        if self.odometry_held_back and m.t >= self.twist.last_t:
            bisect.insort(self.held, m, key=lambda b: b.t)
            return
        self._absolute(m, late=True)

    def release_held(self) -> None:
        """Use the messages that were waiting for an odometry sample, in order."""
        held, self.held = self.held, []
        for b in held:
            self._step(b)

    def _step(self, m) -> None:
        """Integrate up to ``m.t`` and use ``m`` (odometry already set by ``process``)."""
        twist = self.twist
        twist.advance(m.t)
        if isinstance(m, GyroYawRate):
            if m.sensor in self.gyro_names:
                twist.set_gyro(m)
        elif isinstance(m, Heading):
            if not self.headings.add(m):
                return
        elif isinstance(m, (GpsFix, LandmarkObservation)):
            self._absolute(m)
            return
        window = self.window
        if m.t - window.kf_t[window.k] >= 1.0 / self.keyframe_rate and twist.pim.n > 0:
            self.new_keyframe(m.t)
            self.flush()

    def _absolute(self, m, late: bool = False) -> None:
        """A GPS fix or landmark sighting: to the keyframe at its stamp (a new one unless the
        newest is within MIN_KEYFRAME_DT, or with ``keyframe: rate`` the newest), or, when it
        comes late, the window's keyframe nearest its stamp; dropped when older than the lag.
        ``late``: it came after later messages were processed (``_late``): the odometry is
        integrated past its stamp, so no keyframe is made at it."""
        window = self.window
        kf_t = window.kf_t
        t_kf = kf_t[window.k]
        if self.twist.v is None and abs(m.t - t_kf) >= MIN_KEYFRAME_DT:
            # No odometry yet in this window: nothing relates a measurement away from the first
            # keyframe to it (attached with a guessed twist, gtsam declared the system
            # indeterminate)
            self.log.rejected[(m.sensor, "before odometry began")] += 1
            return
        if (not late and m.t - t_kf >= (MIN_KEYFRAME_DT if self.kf_policy == "gps" else 1e9)
                and self.twist.pim.n > 0):
            self.new_keyframe(m.t)
        k = window.k
        # A delayed measurement goes to the keyframe nearest in time inside the window; one
        # older than the lag (gtsam's own cut) is dropped, however near a keyframe it is.
        if m.t < kf_t[k] - MIN_KEYFRAME_DT:
            cut = kf_t[k] - self.lag
            near = [j for j, tj in kf_t.items() if tj >= cut]
            if m.t < cut or not near:
                self.log.rejected[(m.sensor, "older than the smoother lag")] += 1
                self.log.note(m.t, f"{m.sensor}: measurement {kf_t[window.k] - m.t:.2f} s "
                              f"older than the newest keyframe, beyond the {self.lag:g} s lag, "
                              "dropped")
                return
            k = min(near, key=lambda j: abs(kf_t[j] - m.t))
        dt = m.t - kf_t[k]
        if isinstance(m, GpsFix):
            # A fix with a configured delay is the antenna position that long before its stamp:
            # the GPS factor's motion compensation carries it from the keyframe (dt < 0).
            self.gps.fuse(m, k, dt - self.sensors[m.sensor].delay)
        else:
            self.landmark_fusion.fuse(m, k, dt)
        self.flush()

    def new_keyframe(self, t: float) -> None:
        """Close the open keyframe interval at ``t`` with a new keyframe: its preintegrated
        factor, initial value (the newest estimate carried by the preintegration), averaged
        heading and gyro-bias factors."""
        headings, twist, window = self.headings, self.twist, self.window
        if headings.n:
            headings.log_innovation(t)
        ki, kj = window.key(window.k), window.key(window.k + 1)
        n = self.noise
        pim = twist.frozen()
        window.add(preintegrated_factor(
            ki, kj, pim,
            gyro_bias_rw=n.gyro_bias_rw if self.est_bias else n.fixed_rw,
            heading_offset_rw=headings.offset_walk(),
            pose_noise=n.pose_noise,
            scale_rw=self._scale_rw, record=self.factor_record))
        kf_state = window.kf_state
        guess = pim.predict(kf_state)
        pose, cov = compose(kf_state, twist.delta(kf_state, pim), pim.covariance, window.kf_cov)
        window.new_keyframe(t, guess)
        window.kf_state, window.kf_cov = guess, cov
        rows = []
        if headings.n:
            # the interval's heading samples, each carried to this keyframe by the
            # preintegrated yaw since it, averaged: one factor
            h, z, var = headings.pending(pim)
            rows.append((h, z, math.sqrt(var), True))
            headings.n = 0
        diff = twist.bias_difference() if self.est_bias else None
        if diff is not None:
            # mean gyro - k_w x mean odometry yaw rate over the interval: a measurement of the
            # gyro bias (not a linear row: its sigma depends on k_w, errors in both rates)
            window.add(bias_difference_factor(kj, *diff, record=self.factor_record))
        if rows:
            # linear in the state: one C++ factor, no Python callback per relinearisation
            window.add(linear_state_factor(kj, rows, guess))
        twist.reset_difference()
        twist.pim.reset(guess[BG], guess[KV], guess[KW])

    def flush(self) -> None:
        """Send the pending factors to gtsam; re-initialise when it fails."""
        error = self.window.flush()
        if error is not None:
            self.init.recover(error)

    # --- outputs ----------------------------------------------------------------------------
    def estimate(self) -> Estimate | None:
        """The filtered estimate at the newest message's stamp: the newest keyframe composed
        with the partial preintegration up to the last odometry sample, then the held twist
        carried forward over the messages still waiting for the next odometry sample."""
        init = self.init
        if init.restart is not None:  # a gap ended the window; the new one waits to start
            pose, pos_sigma, psi_sigma, _ = init.restart
            gauge = self.window.gauge_var(self.window.k + 1)
            cov = np.diag((pos_sigma ** 2 + gauge, pos_sigma ** 2 + gauge, psi_sigma ** 2))
            return Estimate(init.restart_buf[-1].t if init.restart_buf else self.now, pose,
                            cov, None, None, NAMES)
        if not self.initialised or self.window.kf_state is None:
            return None
        twist = self.twist
        st, kf_cov = self.headings.with_pending()
        delta, q = twist.partial(st)
        t = twist.last_t
        ahead = self.now - t
        yr = (twist.yaw_rate(twist.wg_q, twist.wo_q, twist.wg_var, twist.wo_var)
              if ahead > 0.0 and twist.v is not None else None)
        t_open = twist.pim.dt_total + (ahead if yr is not None else 0.0)
        if t_open > 0.0:
            # the slip since the keyframe (to the held twist's end where it is carried on),
            # which the preintegrated factor will state (in the keyframe's frame, as the
            # interval's covariance): the output grows into the next keyframe's marginal
            # instead of jumping at it
            a, b, c = self.noise.pose_noise
            q[0][0] += a * a * t_open
            q[1][1] += b * b * t_open
            q[2][2] += c * c * t_open
        pose, cov = compose(st, delta, q, kf_cov)
        cov = self.window.with_gauge(self.window.k, cov)
        if yr is not None:
            wg, wo, _, _, gain = yr
            sl = st.tolist()  # Python floats: numpy scalars cost 4 us in se2_step
            bg, kv, kw = sl[BG], sl[KV], sl[KW]
            pose, t = se2_step(pose[0], pose[1], pose[2], kv * twist.v,
                               wg - gain * bg + kw * wo, ahead), self.now
        return Estimate(t, (pose[0], pose[1], wrap_angle(pose[2])), cov, st.copy(), None, NAMES)

    def finish(self) -> None:
        """Close the run, once: a batch that shares this run may have closed it already (a
        ``finish`` that raised is tried again, and raises again)."""
        if not self.finished:
            self._finish()
            self.finished = True

    def _finish(self) -> None:
        if not self.initialised:
            course = self.init.course
            why = ("the GPS track never moved far enough" if course.last_fix is not None else
                   "no GPS fix came, and it takes its heading from the GPS course")
            self.log.note(course.buffer[-1].t if course.buffer else 0.0,
                          f"never initialised: {why}")
            return
        self.release_held()
        # The odometry since the newest keyframe closes the run as a last keyframe, unless it
        # spans less than MIN_KEYFRAME_DT: a preintegrated factor over a few milliseconds has
        # walk sigmas of ~1e-6, and gtsam declared such a system indeterminate.
        window, twist = self.window, self.twist
        if twist.pim.n > 0 and twist.last_t - window.kf_t[window.k] >= MIN_KEYFRAME_DT:
            self.new_keyframe(twist.last_t)
            self.flush()
        window.capture_leaving(math.inf, newest=True)

    def lagged_estimates(self) -> TrackBuilder | None:
        return self.window.track if self.lagged else None

    def final_state(self) -> Estimate | None:
        """The newest keyframe with its full marginal (the lagged track's last entry after
        ``finish``: at the end of the run the filtered and the lagged output meet there),
        restricted to the states this run estimates (a held bias, offset or scale is left out,
        as the EKFs carry no state for it)."""
        return self._estimated_only(self.window.track.last)

    def _estimated_only(self, e: Estimate | None) -> Estimate | None:
        return estimated_only(e, self.est_bias, self.est_hoff, self.scale_prior is not None)
