"""When and from what the smoother's window starts: the first start (a given pose; without GPS at
the origin; else from the GPS course, ``ddfuse.estimation.gps_course``), the restart after a gap
in the feed that leaves the heading unknown, and the re-initialisation after a gtsam error.

Each start puts one keyframe with a prior (``Initialisation.first_keyframe``): the pose with its
sigmas (m, rad; local ENU), the twist with the default sigmas, the calibration states (gyro
bias, heading offset, odometry scales) from their priors or as learnt before a restart. Design
notes: docs/design/smoother.md (Starts and restarts).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from ddfuse.estimation.errors import error_line
from ddfuse.estimation.estimator import wrap_angle
from ddfuse.estimation.gaps import gap_note, grown_pose_cov, is_gap
from ddfuse.estimation.gps_course import GpsCourseStart
from ddfuse.estimation.measurements import Heading
from ddfuse.estimation.smoother.held_twist import ODOMETRY_WAIT
from ddfuse.estimation.smoother.noise import twist_walk
from ddfuse.estimation.twist_tails import held_speed_walk
from ddfuse.factors.kinematics import se2_step
from ddfuse.factors.state import BG, DIM, HOFF, KV, KW

if TYPE_CHECKING:
    from ddfuse.estimation.smoother.fixed_lag import FixedLagSmoother

# rad: a gap in the feed over which the yaw rate held across it leaves the heading this
# uncertain ends the window there (Initialisation.after_gap)
GAP_HEADING_SIGMA = 0.5
RESTART_HEADING_WAIT = 1.0  # s: how long the new window waits for a heading sample
MAX_RECOVERIES = 3  # re-initialisations within RECOVERY_WINDOW the smoother survives
RECOVERY_WINDOW = 10.0  # s of data


class Initialisation:
    """The starts of ``sm``'s window: the GPS-course buffer (``course``), a restart waiting for
    its first message (``restart``: pose, position sigma, heading sigma, calibration (value,
    4x4 covariance)) and the messages held for it, the calibration kept while the GPS course
    re-aligns after a gap, and the stamps of the recent re-initialisations."""

    def __init__(self, sm: FixedLagSmoother) -> None:
        self.sm = sm
        robot = sm.cfg.robot
        self.course = GpsCourseStart(
            gyro_names=sm.gyro_names, fixed_bias=sm.fixed_bias, wheel_radius=robot.wheel_radius,
            track_width=robot.track_width, min_psi_sigma=sm.noise.init_psi_sigma,
            odometry_wait=ODOMETRY_WAIT)
        self.restart: tuple | None = None  # after a gap (after_gap): the new window's start
        self.restart_buf: list = []  # and the messages held for it
        self.realign: tuple | None = None  # calibration kept while the GPS course re-aligns
        self.recovery_t: list[float] = []  # stamps of the recent re-initialisations

    # --- first start ----------------------------------------------------------------------
    def uninitialised(self, m) -> None:
        """Message ``m`` before the window has started: start it, or buffer ``m`` for the GPS
        course."""
        sm = self.sm
        if isinstance(m, Heading):
            sm.headings.latest = m
        if sm.given_pose is not None and self.realign is None:
            self.start(m.t, tuple(sm.given_pose), sm.noise.init_pos_sigma,
                       sm.noise.init_given_psi_sigma)
            sm.take(m)
            return
        if not sm.has_gps:
            psi = 0.0
            if isinstance(m, Heading) and not sm.est_hoff:
                s = sm.sensors[m.sensor]
                psi = wrap_angle(m.yaw - float(s.heading_offset))
            self.start(m.t, (0.0, 0.0, psi), sm.noise.init_pos_sigma, 0.05 if psi else 1e-3)
            sm.take(m)
            return
        got = self.course.add(m)
        if got is None:
            return
        for b in got.dropped:  # the fixes before odometry began, as ``_absolute``
            sm.log.rejected[(b.sensor, "before odometry began")] += 1
        self.start(got.t, (got.position[0], got.position[1], got.heading), got.pos_sigma,
                   got.psi_sigma)
        for b in got.replay:
            sm.take(b)

    def start(self, t: float, pose, pos_sigma: float, psi_sigma: float) -> None:
        self.sm.twist.last_t = t
        calib, self.realign = self.realign, None
        self.first_keyframe(t, pose, pos_sigma, psi_sigma, calib=calib)

    def first_keyframe(self, t: float, pose: tuple[float, float, float], pos_sigma: float,
                       psi_sigma: float, scale: tuple[np.ndarray, np.ndarray] | None = None,
                       calib: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """A new first keyframe at ``t``: ``pose`` with the given sigmas; the odometry scales
        from ``scale`` (value, 2x2 covariance) or their prior; with ``calib`` (value, 4x4
        covariance of bg, hoff, k_v, k_w) all four calibration states as they were learnt."""
        sm = self.sm
        n, twist = sm.noise, sm.twist
        x0 = np.array([pose[0], pose[1], pose[2], twist.v or 0.0, 0.0, sm.fixed_bias, 0.0,
                       1.0, 1.0])
        heading = sm.headings.latest
        if sm.est_hoff and heading is not None:
            x0[HOFF] = wrap_angle(heading.yaw - pose[2])
        sig = [pos_sigma, pos_sigma, psi_sigma, n.init_v_sigma, n.init_w_sigma,
               n.init_bg_sigma if sm.est_bias else n.fixed_sigma,
               n.init_hoff_sigma if sm.est_hoff else n.fixed_sigma,
               n.fixed_sigma, n.fixed_sigma]
        cov0 = np.diag(np.square(sig))
        if calib is not None:
            x0[BG:], cov0[BG:, BG:] = calib
        elif scale is not None:  # a re-initialisation keeps the scales it had learnt
            x0[KV:], cov0[KV:, KV:] = scale
        elif sm.scale_prior is not None:
            sd_v, sd_w, c_vw = sm.scale_prior
            cov0[KV:, KV:] = ((max(sd_v, n.fixed_sigma) ** 2, c_vw),
                              (c_vw, max(sd_w, n.fixed_sigma) ** 2))
        sm.window.first_keyframe(t, x0, cov0)
        twist.pim.reset(x0[BG], x0[KV], x0[KW])
        sm.headings.n = 0
        sm.initialised = True
        twist.last_t = t
        sm.flush()

    # --- restart after a gap ----------------------------------------------------------------
    def after_gap(self, t: float) -> None:
        """No message from ``sm.now`` to ``t``. A gap in the feed (``estimation.gaps``: over
        GAP_S) ends the window at the last message and starts a new one at ``t`` from the last
        pose, its covariance grown by what the robot could have done in the gap
        (``grown_pose_cov``). A shorter silence does so only if the yaw rate held over it leaves
        the heading more uncertain than GAP_HEADING_SIGMA; the new window then starts from the
        last estimate carried over it by its twist, with the sigmas it leaves. Either way the
        calibration states go on as learnt (their walks grown over the gap). Why (one
        preintegrated factor across such a gap is linearised at a heading that is unknown):
        docs/design/smoother.md; the gap rule: docs/design/gaps.md."""
        sm = self.sm
        tw, window = sm.twist, sm.window
        gap = t - sm.now
        n, robot = sm.noise, sm.cfg.robot
        long_gap = is_gap(gap)
        yaw = []
        for var, period, w in ((tw.wg_var, tw.wg_T, tw.wg), (tw.wo_var, tw.wo_T, tw.wo)):
            if w is not None:
                q = twist_walk(robot.max_yaw_accel, n.yaw_acc, period,
                               robot.twist_walk.get("yaw_rate"))
                yaw.append(var * gap * gap + q * gap ** 3 / 3.0)
        if not long_gap and (not yaw or min(yaw) < GAP_HEADING_SIGMA ** 2 or tw.v is None):
            return
        sm.release_held()
        if tw.pim.n > 0:
            sm.new_keyframe(tw.last_t)
        sm.flush()
        x, full = window.kf_state, window.full
        if full is None or full.shape != (DIM, DIM):
            return
        if long_gap:
            grown = grown_pose_cov(full[:3, :3], gap, robot)
            px, py, ppsi = float(x[0]), float(x[1]), float(x[2])
            pos_var, psi_var = max(float(grown[0, 0]), float(grown[1, 1])), float(grown[2, 2])
            sm.log.note(t, gap_note("smoother", gap, grown) + "; the window ends there")
        else:
            qv = twist_walk(robot.max_accel, n.acc, tw.v_T, held_speed_walk(robot))
            v = float(x[3])
            grow_pos = tw.v_var * gap * gap + qv * gap ** 3 / 3.0
            psi_var = float(full[2, 2]) + min(yaw)
            # a heading this unknown spreads the carried position along the arc of |v| gap
            pos_var = (max(float(full[0, 0]), float(full[1, 1])) + grow_pos
                       + (v * gap) ** 2 * min(psi_var, 1.0))
            px, py, ppsi = se2_step(float(x[0]), float(x[1]), float(x[2]), v, float(x[4]), gap)
            sm.log.note(t, f"no message for {gap:.1f} s: the heading after it is unknown (sigma "
                        f"{math.sqrt(psi_var):.2f} rad); the window ends there and a new one "
                        f"starts from the estimate carried over the gap (position sigma "
                        f"{math.sqrt(pos_var):.1f} m)")
        calib_cov = full[BG:, BG:].copy()
        calib_cov[0, 0] += (n.gyro_bias_rw if sm.est_bias else n.fixed_rw) ** 2 * gap
        calib_cov[1, 1] += (n.heading_offset_rw if sm.est_hoff else n.fixed_rw) ** 2 * gap
        window.capture_leaving(math.inf, newest=True)  # the window as it stood: all smoothed
        window.restart()
        prior_var = pos_var
        if not self.position_observed:
            # Nothing measures the position: its grown variance is a pure offset of the new
            # window, added to every output (``Window.gauge``). In gtsam's prior it stood
            # beside walks of 1e-4 (a condition of 1e11): indeterminate at the first keyframe,
            # four re-initialisations and the smoother stopped (rl_jackal.bag, a 15 s gap).
            prior_var = min(pos_var, max(float(full[0, 0]), float(full[1, 1])))
            window.add_gauge(window.k + 1, pos_var - prior_var)
        # the held samples described the time before the gap; the next ones start afresh
        tw.forget()
        sm.held = []
        self.restart = ((px, py, wrap_angle(ppsi)), math.sqrt(prior_var),
                        min(math.sqrt(psi_var), math.pi), (x[BG:].copy(), calib_cov))
        self.restart_buf = []
        sm.initialised = False  # until restart_now: the new window's first keyframe

    @property
    def position_observed(self) -> bool:
        """True if a configured sensor measures the position (a GPS, landmarks)."""
        cfg = self.sm.cfg
        return bool(cfg.of_kind("gps") or cfg.of_kind("landmarks"))

    def restart_now(self, m) -> None:
        """Open the window a gap ended (``after_gap``) at the first message after it, once a
        heading sample fixes the heading (the motion factors are then linearised at it), or
        after RESTART_HEADING_WAIT s without one (the carried heading, its wide sigma); then
        replay the messages held meanwhile."""
        sm = self.sm
        buf = self.restart_buf
        buf.append(m)
        head = m if isinstance(m, Heading) else None
        if head is None and m.t - buf[0].t < RESTART_HEADING_WAIT and sm.heading_sensors:
            return
        pose, pos_sigma, psi_sigma, (xc, cc) = self.restart
        if head is None and not sm.heading_sensors and sm.has_gps:
            # no absolute heading at all: the GPS course gives it, as at the start (the
            # calibration states kept); no estimate until then
            self.restart, self.restart_buf, self.realign = None, [], (xc, cc)
            sm.headings.latest = None
            sm.now = -math.inf  # as at the start: no gap to check against until then
            for b in buf:
                self.uninitialised(b)
            return
        if head is not None:
            s = sm.sensors[head.sensor]
            if s.heading_offset == "estimate":
                psi, var = head.yaw - xc[HOFF - BG], head.var + cc[HOFF - BG, HOFF - BG]
            else:
                psi, var = head.yaw - float(s.heading_offset), head.var
            pose, psi_sigma = (pose[0], pose[1], wrap_angle(psi)), math.sqrt(var)
        self.restart, self.restart_buf = None, []
        sm.headings.latest = None  # the pre-gap sample must not set the new keyframe's offset
        self.first_keyframe(buf[0].t, pose, pos_sigma, psi_sigma, calib=(xc, cc))
        sm.now = buf[0].t
        for b in buf:
            sm.take(b)

    # --- re-initialisation after a gtsam error ----------------------------------------------
    def recover(self, reason: str) -> None:
        """gtsam failed (indeterminate system, ...): restart from the last good estimate."""
        sm = self.sm
        window = sm.window
        t = window.kf_t[window.k]
        first = error_line(reason)
        self.recovery_t = [r for r in self.recovery_t if r > t - RECOVERY_WINDOW] + [t]
        if len(self.recovery_t) > MAX_RECOVERIES:
            window.capture_leaving(math.inf, newest=True)  # what the window holds is kept
            # Failing again and again (each re-initialisation's own update succeeds, the next
            # keyframes' do not): the model is ill-conditioned here, and going on would output
            # a track re-started from ever staler estimates (metres off). Stop this estimator:
            # the runner keeps what it estimated and the other estimators go on.
            sm.stopped = (f"{len(self.recovery_t)} re-initialisations within "
                          f"{RECOVERY_WINDOW:g} s at t={t:.3f} ({first}): its system is "
                          "ill-conditioned here; check the config's noise values, priors and "
                          "delays")
            raise RuntimeError(f"smoother: {sm.stopped}")
        sm.log.note(t, f"smoother re-initialised after gtsam error: {first}")
        sm.log.rejected[("smoother", "gtsam error, re-initialised")] += 1
        state, cov, full = window.kf_state, window.kf_cov, window.full
        window.capture_leaving(math.inf)  # the window's keyframes as they stood: no gap in lag
        window.restart()
        sig = np.sqrt(np.maximum(np.diag(cov), 1e-6)) * 2.0
        calib = None
        if full is not None and full.shape == (DIM, DIM):
            # the gyro bias and heading offset as learnt, their sigmas doubled as the pose's
            # (their priors instead cost yaw and fed the next failures)
            cc = 4.0 * full[BG:, BG:]
            calib = (np.array(state[BG:], dtype=float), 0.5 * (cc + cc.T))
        self.first_keyframe(t, (state[0], state[1], state[2]), float(max(sig[0], sig[1])),
                            float(sig[2]), window.scale_belief, calib=calib)
