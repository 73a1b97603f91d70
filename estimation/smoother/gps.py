"""GPS fusion: a fix as a factor on the window's keyframe nearest its stamp.

A fix (east/north in m, local ENU; covariance m^2) becomes a GPS factor with the antenna's lever
arm (body frame, m), carried from the keyframe along its twist when it does not fall on it
(``ddfuse.factors.gps``), with what the motion does off that twist added to its covariance, and
the configured robust kernel. It is gated first (``Gating``): against the newest keyframe's
marginal, or for a late fix against its own keyframe's. With the sensor's ``correlation_time``
(``ddfuse.estimation.gps_correlation``) the factor's covariance is the fix's own inflated by f
for the time since the sensor's previous fused fix, while the gate and the logged innovation
keep the fix's own. With a robust ``gps.model`` (``gps_models``) the model judges the fix
instead of the gate. Design notes: docs/design/smoother.md (GPS fusion), urban_gps.md.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np
from ddfuse.estimation import gps_correlation
from ddfuse.estimation.config import DEFAULT_GATE, Config, SensorConfig
from ddfuse.estimation.estimator import EstimatorLog, Innovation
from ddfuse.estimation.measurements import GpsFix
from ddfuse.estimation.smoother.gating import RECOVER, REJECT, Gating
from ddfuse.estimation.smoother.gps_models import RobustGps
from ddfuse.estimation.smoother.held_twist import HeldTwist
from ddfuse.estimation.smoother.noise import SmootherNoise, gate_radius, robustify, twist_walk
from ddfuse.estimation.smoother.window import Window
from ddfuse.estimation.twist_tails import held_speed_walk
from ddfuse.factors.gps import gps_factor, gps_predict_jacobian
from ddfuse.factors.state import DIM, PSI

# A run of fixes a robust model takes for outliers this long (s) and this many is a
# disagreement of GPS and odometry, said once (GpsFusion._outlier_run)
DISAGREE_S = 10.0
DISAGREE_FIXES = 10
# s: a run of outliers whose fixes the GPS watch finds moving as the odometry does, none
# otherwise, this long is the estimate's fault (urban multipath holds an offset 2-10 s)
ESTIMATE_WRONG_S = 30.0
START_WRONG = "start wrong"  # _outlier_run: no fix has agreed since the start


@dataclass(slots=True)
class _OutlierRun:
    """A sensor's current run of fixes the robust model takes for outliers: the first one's
    stamp (s), how many, whether the disagreement was said, and how many of them the GPS watch
    found moving as the odometry does / not (``GpsFix.odometry_agrees``)."""

    t0: float
    fixes: int = 0
    said: bool = False
    moving: int = 0
    jumping: int = 0


class GpsFusion:
    """Builds the GPS factors; keeps, per sensor with a correlation time, the stamps of the
    fixes fused (from the last one before the window's lag on)."""

    def __init__(self, cfg: Config, sensors: dict[str, SensorConfig], noise: SmootherNoise,
                 twist: HeldTwist, window: Window, gating: Gating, log: EstimatorLog,
                 flush: Callable[[], None]) -> None:
        """``flush``: sends the window's pending factors to gtsam (re-initialising on
        failure), before a lock-out's widening."""
        self.cfg, self.sensors, self.noise, self.flush = cfg, sensors, noise, flush
        self.twist, self.window, self.gating, self.log = twist, window, gating, log
        # GPS sensors with time-correlated errors: name -> correlation time (s)
        self.tau = {s.name: s.correlation_time for s in cfg.of_kind("gps")
                    if s.correlation_time > 0.0}
        self.fused_t: dict[str, list[float]] = {}  # per sensor: stamps (sorted) of fused fixes
        # the config's robust GPS model (gps.model), None for 'default' and 'gaussian'
        self.robust = RobustGps(cfg.gps) if cfg.gps.robust else None
        # per sensor: its current run of outliers
        self.outlier_run: dict[str, _OutlierRun] = {}

    def fuse(self, m: GpsFix, k: int, dt: float) -> None:
        """Fix ``m`` on keyframe ``k``, ``dt`` s after it (the sensor's delay taken off)."""
        s = self.sensors[m.sensor]
        e, n = m.enu[0], m.enu[1]
        window = self.window
        n_inn = len(self.log.innovations)
        if k == window.k and window.kf_state is not None:
            cov = self.carried_cov(m, window.kf_state, dt)
            nis = self.innovation(m, s.lever_arm, dt, cov)
            if self.robust is not None:  # the model, not the gate, judges the fix
                self._fuse_robust(m, s, k, dt, cov, n_inn)
                return
            verdict = self.gating.verdict(m, s, nis)
            if verdict == REJECT:
                return
            if verdict == RECOVER:
                k = self.widen(m, s, dt, cov)  # a keyframe at the newest's stamp: same dt
        else:
            cov = self._delayed(m, s, k, dt)
            if cov is None:
                return
            if self.robust is not None:
                self._fuse_robust(m, s, k, dt, cov, n_inn)
                return
        # Time-correlated errors (the sensor's correlation_time): the factor takes the fix's
        # own covariance times f for the time since the previous fused fix (what the motion
        # carry of carried_cov adds stays as it is); the gate, the logged innovation and a
        # lock-out's widening above used the fix's own. f = 1 without a correlation time.
        f = 1.0
        if m.sensor in self.tau:
            f = self.inflation(m)
            self.record_fused(m)
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
            # the kernel's threshold scaled by 1/sqrt(f) (robustify): the same residuals in
            # metres as without the inflation, those the gate accepts given full weight
            model = robustify(self.cfg, s, gtsam.noiseModel.Diagonal.Precisions(prec), 2, f)
            self.window.add(gtsam.PriorFactorVector(self.window.key(k), target, model))
        else:
            # the fix's east/north correlation kept (a receiver's ellipse is rarely a circle)
            model = (gtsam.noiseModel.Diagonal.Variances(np.array((cov[0, 0], cov[1, 1])))
                     if cov[0, 1] == 0.0 else gtsam.noiseModel.Gaussian.Covariance(cov))
            self.window.add(gps_factor(self.window.key(k), e, n,
                                       robustify(self.cfg, s, model, 2, f), s.lever_arm, dt))

    def _fuse_robust(self, m: GpsFix, s: SensorConfig, k: int, dt: float, cov: np.ndarray,
                     n_inn: int) -> None:
        """Fix ``m`` on keyframe ``k`` under the config's robust model (``gps_models``): no gate;
        the stated covariance scaled by the learned factor; an outlier verdict logged (the
        innovation marked not accepted, counted as 'outlier') and a long run of them said
        (``_outlier_run``)."""
        f = 1.0
        if m.sensor in self.tau:
            f = self.inflation(m)
            self.record_fused(m)
        r = np.asarray(m.cov[:2, :2], dtype=float)
        cov = cov + (f - 1.0) * r
        logged = len(self.log.innovations) > n_inn
        if logged:
            inn = self.log.innovations[-1]
            y, s_inn = np.asarray(inn.residual, float), np.asarray(inn.cov, float)
        else:  # a late fix older than the smoother's solution: nothing to judge it against
            y, s_inn = np.zeros(2), cov
        gate = gate_radius(s.gate if s.gate is not None else DEFAULT_GATE, 2) ** 2
        factor, outlier = self.robust.factor(self.window.key(k), m.enu[0], m.enu[1], cov, r, f,
                                             s.lever_arm, dt, y, s_inn, gate)
        if logged:
            if outlier:
                inn.accepted = False
                self.log.rejected[(m.sensor, "outlier")] += 1
            else:  # learnt from the fixes taken for inliers: outliers cannot inflate it
                self.robust.scale.add(m.t, inn.nis)
        run = self._outlier_run(m, outlier)
        if run == START_WRONG and k == self.window.k:
            # the start, not the GPS: widened to this fix, fused without the kernel (which
            # would weigh it by its distance from the wrong estimate), the GPS followed
            k = self.widen(m, s, dt, cov, lockout=False)
            self.window.add(self.robust.inlier_factor(self.window.key(k), m.enu[0], m.enu[1],
                                                      cov, r, f, s.lever_arm, dt))
            return
        if run:
            return  # a disagreement said: the odometry is followed, the outlier not fused
        if outlier:  # the run of inliers that vouches for the start (Lockout.agreed)
            self.gating.lockout.disagreed(m.sensor)
        else:
            self.gating.lockout.accepted(m.sensor)
        self.window.add(factor)

    def _outlier_run(self, m: GpsFix, outlier: bool) -> bool | str:
        """A run of fixes the model takes for outliers over DISAGREE_S s or more (a wrong datum, a
        spoofed receiver, a long canyon) is said once, with what the estimate follows; its end,
        when a fix agrees again, too. Returns True while such a run goes on: its outliers are
        no longer fused, so that their sum cannot drag the estimate (the outlier component or
        the kernel's tail still pulls) -- until a fix agrees again, judged against the
        odometry's growing uncertainty. ``START_WRONG`` is returned instead, for the estimate
        to be widened and follow the GPS, where the sensor's fixes have not agreed since the
        start (never AGREED_RUN inliers in a row: the start is the one value against the
        GPS's many, a wrong ``initial_pose``), or where the run's fixes have all moved as the
        odometry does (the GPS watch's ``odometry_agrees``) for ESTIMATE_WRONG_S (the estimate
        left them: a wrong start heading whose first fixes agreed)."""
        run = self.outlier_run.get(m.sensor)
        if not outlier:
            if run is not None:
                if run.said:
                    self.log.note(m.t, f"{m.sensor}: GPS agrees with the odometry again after "
                                  f"{run.fixes} outliers over {m.t - run.t0:.1f} s; following "
                                  "the GPS")
                del self.outlier_run[m.sensor]
            return False
        if run is None:
            run = self.outlier_run[m.sensor] = _OutlierRun(m.t)
        run.fixes += 1
        if m.odometry_agrees is not None:
            if m.odometry_agrees:
                run.moving += 1
            else:
                run.jumping += 1
        span = m.t - run.t0
        what = f"{run.fixes} over {span:.1f} s taken for outliers by the {self.cfg.gps.model} model"
        if not run.said and span >= DISAGREE_S and run.fixes >= DISAGREE_FIXES:
            if not self.gating.lockout.agreed(m.sensor):
                self.log.note(m.t, f"{m.sensor}: no fix has agreed with the estimate since the "
                              f"start ({what}): the start is taken for wrong (the config's "
                              "initial_pose?), not the GPS; the estimate is widened to the "
                              "fixes and follows the GPS")
                del self.outlier_run[m.sensor]
                return START_WRONG
            run.said = True
            self.log.note(m.t, f"{m.sensor}: GPS and odometry disagree: {run.fixes} fixes over "
                          f"{span:.1f} s taken for outliers by the {self.cfg.gps.model} model; "
                          "following the odometry")
        elif (run.said and span >= ESTIMATE_WRONG_S and run.jumping == 0
              and run.moving >= DISAGREE_FIXES):
            # the watch compares distances, which need no heading; a run longer than a burst
            # lasts whose fixes all move as the odometry does is the estimate's fault
            self.log.note(m.t, f"{m.sensor}: the fixes taken for outliers ({what}) move as the "
                          "odometry does: the estimate is taken for wrong (its heading?), not "
                          "the GPS; widened to the fixes, the GPS followed")
            del self.outlier_run[m.sensor]
            return START_WRONG
        return run.said

    def inflation(self, m: GpsFix) -> float:
        """The factor f (>= 1) by which fix ``m``'s covariance is inflated for fusion
        (``estimation.gps_correlation.inflation``): its sensor's correlation time, and the time
        to the nearest earlier fix of that sensor fused; for a fix that comes late (older than
        one fused), the nearest fused fix on either side. 1 without a correlation time or
        before the sensor's first fused fix."""
        tau = self.tau.get(m.sensor)
        fused = self.fused_t.get(m.sensor)
        if tau is None or not fused:
            return 1.0
        if m.t >= fused[-1]:
            dt = m.t - fused[-1]
        else:
            i = bisect.bisect_left(fused, m.t)
            dt = min(abs(m.t - fused[j]) for j in (i - 1, i) if 0 <= j < len(fused))
        return gps_correlation.inflation(dt, tau)

    def record_fused(self, m: GpsFix) -> None:
        """Record fix ``m`` (of a sensor with a correlation time) as fused: its GPS factor is
        built. Stamps older than the window's lag are dropped but the last of them: a late fix
        is at most the lag older than the newest keyframe (``FixedLagSmoother._absolute``), so
        its nearest fused fix on either side is still there, and memory stays bounded."""
        fused = self.fused_t.setdefault(m.sensor, [])
        if not fused or m.t >= fused[-1]:
            fused.append(m.t)
        else:
            bisect.insort(fused, m.t)
        window = self.window
        cut = window.kf_t[window.k] - window.lag
        if len(fused) > 1 and fused[1] < cut:
            drop = bisect.bisect_left(fused, cut) - 1  # keep the last stamp before the cut
            del fused[:drop]

    def carried_cov(self, m: GpsFix, x: np.ndarray, dt: float) -> np.ndarray:
        """The fix's east/north covariance (2, 2), m^2, as a measurement of keyframe state
        ``x`` carried ``dt`` s along its constant twist: the fix's own plus what the body's
        motion does off that twist over |dt| -- slip (pose_noise) and the twist's random walk
        (the held-sample densities): along the heading  l^2 |dt| + q_v |dt|^3 / 3, across it
        t^2 |dt| + v^2 (h^2 |dt|^3 / 3 + q_w |dt|^5 / 20)."""
        cov = np.array(m.cov[:2, :2], dtype=float)
        a = abs(dt)
        if a < 1e-9:
            return cov
        nz, robot = self.noise, self.cfg.robot
        pl, pt, ph = nz.pose_noise
        tw = self.twist
        qv = twist_walk(robot.max_accel, nz.acc, tw.v_T, held_speed_walk(robot))
        qw = twist_walk(robot.max_yaw_accel, nz.yaw_acc,
                         tw.wg_T if tw.wg is not None else tw.wo_T,
                         robot.twist_walk.get("yaw_rate"))
        v = float(x[3])
        along = pl * pl * a + qv * a ** 3 / 3.0
        across = pt * pt * a + v * v * (ph * ph * a ** 3 / 3.0 + qw * a ** 5 / 20.0)
        c, sn = math.cos(float(x[PSI])), math.sin(float(x[PSI]))
        cov[0, 0] += along * c * c + across * sn * sn
        cov[1, 1] += along * sn * sn + across * c * c
        cov[0, 1] += (along - across) * c * sn
        cov[1, 0] = cov[0, 1]
        return cov

    def _delayed(self, m: GpsFix, s: SensorConfig, k: int, dt: float) -> np.ndarray | None:
        """A fix for an older keyframe ``k`` of the window: gated against that keyframe's
        marginal, as a fix on time is against the newest's, and logged for the NIS. The lock-out is
        left alone: it is about the current estimate. Returns the fix's covariance for the factor,
        or None when the gate rejects it."""
        try:
            x, full = self.window.estimate_of(k)
        except (RuntimeError, IndexError, ValueError):
            # not in the smoother yet: ungated
            return self.carried_cov(m, self.window.kf_state, dt)
        cov = self.carried_cov(m, x, dt)
        nis = self.innovation(m, s.lever_arm, dt, cov, x, full)
        if (self.robust is None and s.gate is not None
                and nis > gate_radius(s.gate, 2) ** 2):
            self.log.rejected[(m.sensor, "gate")] += 1
            self.log.innovations[-1].accepted = False
            return None
        return cov

    def widen(self, m: GpsFix, s: SensorConfig, dt: float, r: np.ndarray,
              lockout: bool = True) -> int:
        """Recover from a gate lock-out on fix ``m`` (``dt`` s from the newest keyframe) as the
        EKFs do, by widening the belief by the smallest factor alpha that makes the fix's
        innovation ordinary (``estimation.lockout.inflation``), here inside the graph: the fix
        goes on a new keyframe at the same stamp, tied to the newest one by a zero-mean link with
        covariance (alpha - 1) times the newest keyframe's marginal (the odometry scales
        excepted), so its marginal is the widened one while the window stays whole (the lagged
        output keeps smoothing across the jump). The batch ties the two keyframes tightly
        instead (the robot did not jump, the filter was lost) unless the GPS never agreed with
        the estimate since the start (``Lockout.agreed``): the start is then what was wrong.
        Returns the new keyframe."""
        self.flush()  # the newest keyframe's motion and heading factors, without the fix
        pred, H = gps_predict_jacobian(self.window.kf_state, s.lever_arm, dt)
        y = np.array((m.enu[0] - pred[0], m.enu[1] - pred[1]))
        return self.gating.widen_link(m.sensor, m.t, H, y, r, "fix", lockout=lockout)

    def innovation(self, m, lever, dt, r: np.ndarray, st: np.ndarray | None = None,
                   full: np.ndarray | None = None) -> float:
        """Innovation of the fix against the prediction before it is fused (logged for NIS),
        with the GPS factor's own model (``gps_predict_jacobian``) and measurement covariance
        ``r``; at keyframe state ``st`` with marginal ``full``, by default the newest's.
        Returns its NIS."""
        if st is None:
            st, full = self.window.kf_state, self.window.newest_marginal()
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
        nis = (d * r0 * r0 - 2 * b * r0 * r1 + a * r1 * r1) / det if det > 0.0 else math.inf
        self.log.innovations.append(Innovation(m.t, m.sensor, "gps", res, cov, float(nis), True))
        return float(nis)

