"""Chi-square gates of the absolute measurements and the recovery from a gate lock-out.

A fix, sighting or heading sample is gated against the newest keyframe's marginal as in the
EKFs. A run of rejections (``ddfuse.estimation.lockout``) that nothing of another kind
corroborates (landmark sightings for the GPS, GPS fixes for the landmarks, either for a
compass) means the estimate, not the sensor, is lost: the belief is widened inside the graph by
a link to a new keyframe at the same stamp (``Gating.widen_link``), by the smallest factor that
makes the measurement ordinary (``ddfuse.estimation.lockout.inflation``). Design notes:
docs/design/smoother.md (Gates and lock-outs).
"""

from __future__ import annotations

import math

import numpy as np
from ddfuse.estimation.config import SensorConfig
from ddfuse.estimation.estimator import EstimatorLog
from ddfuse.estimation.lockout import Lockout, inflation
from ddfuse.estimation.measurements import GpsFix, LandmarkObservation
from ddfuse.estimation.smoother.noise import SmootherNoise, gate_radius
from ddfuse.estimation.smoother.window import Window
from ddfuse.factors.state import BG, DIM, HOFF, PSI

ACCEPT, REJECT, RECOVER = 0, 1, 2  # verdicts of the gate (Gating.verdict)
# rad^2 added to the heading's variance by the widening of a start taken for wrong (1 rad
# sigma; (pi/2)^2 made the sample bag's batch indeterminate)
START_HEADING_VAR = 1.0


class Gating:
    """The lock-out streaks per gated sensor (or (sensor, kind)), the stamps of the newest fix
    and sighting the gates accepted, and the widening of ``window``'s newest keyframe."""

    def __init__(self, window: Window, noise: SmootherNoise, log: EstimatorLog, *,
                 est_bias: bool, est_hoff: bool) -> None:
        self.window, self.noise, self.log = window, noise, log
        self.est_bias, self.est_hoff = est_bias, est_hoff
        self.lockout = Lockout()  # gate streaks per sensor (ddfuse.estimation.lockout)
        self.landmark_t = -math.inf  # stamp of the newest landmark sighting fused
        self.gps_ok_t = -math.inf  # stamp of the newest fix the gate accepted

    def verdict(self, m: GpsFix | LandmarkObservation, s: SensorConfig, nis: float) -> int:
        """The gate's verdict on a fix or a landmark sighting with innovation ``nis`` (2 dof; a
        range-only sighting 1), as in the EKFs: ACCEPT, REJECT (logged, counted) or RECOVER,
        a lock-out (``ddfuse.estimation.lockout``) that nothing of the other kind accepted since the
        rejections began contradicts (landmark sightings for the GPS, GPS fixes for the
        landmarks): the estimate, not the sensor, is wrong; the caller widens the belief."""
        gps = isinstance(m, GpsFix)
        dim = 2 if gps or m.has_bearing else 1
        if s.gate is None or nis <= gate_radius(s.gate, dim) ** 2:
            self.lockout.accepted(m.sensor)
            if gps:
                self.gps_ok_t = m.t
            return ACCEPT
        if self.lockout.rejected(m.sensor, m.t):
            count, first = self.lockout.streak(m.sensor)
            if (self.landmark_t if gps else self.gps_ok_t) < first:
                return RECOVER
            wait = self.lockout.corroborated(m.sensor, m.t)
            what, other, mine = (("fixes", "landmark sightings", "the GPS disagrees") if gps
                                 else ("sightings", "GPS fixes", "the landmarks disagree"))
            self.log.note(m.t, f"{m.sensor}: {count} {what} in a row failed the gate over "
                          f"{m.t - first:.1f} s while {other} were fused: {mine} with them, "
                          f"not recovering (checked again in {wait:.0f} s)")
        self.log.rejected[(m.sensor, "gate")] += 1
        self.log.innovations[-1].accepted = False
        return REJECT

    def widen_link(self, key, t_m: float, H: np.ndarray, y: np.ndarray, R: np.ndarray,
                   what: str, calibration: bool = True, lockout: bool = True) -> int:
        """Widen the newest keyframe's belief by the smallest alpha that makes innovation ``y``
        of a measurement (H (m, DIM), R (m, m)) at ``t_m`` ordinary (``GpsFusion.widen``), the
        lock-out of ``key`` (a sensor, or (sensor, kind)) recovered: P + (alpha - 1) P_ww, so
        S(alpha) = alpha A + (H P H^T - A + R) with A = H_w P_ww H_w^T. Widened: the pose and
        twist, and with ``calibration`` the gyro bias and heading offset where they are
        estimated; a state held at its value never is (gtsam's Cholesky would refuse its prior
        against its 1e-6 walk). Returns the new keyframe (docs/design/smoother.md, Gates and
        lock-outs). Without ``lockout`` (a widening no gate's lock-out asked for) the lock-out's
        bookkeeping and note are left out."""
        window = self.window
        full = window.full
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
            # link of only fixed_sigma would tie the keyframes whatever their sigma
            self.lockout.recovered(key, t_m)
            return window.k
        # Every estimated state but the odometry scales, as in the EKFs: H observes none of
        # them, so alpha is the EKF's; widened too, the scales would explain the jump
        q = np.zeros((DIM, DIM))
        ww = np.ix_(w, w)
        q[ww] = (alpha - 1.0) * full[ww]
        if rest is not None:
            d = np.linalg.pinv(H[:, w]) @ rest
            q[ww] += np.outer(d, d)
        q = 0.5 * (q + q.T) + np.eye(DIM) * self.noise.fixed_sigma ** 2
        # a widening no lock-out asked for, or a lock-out of a sensor that never agreed with
        # the estimate, is a start taken for wrong: the batch keeps q too
        start = not lockout or not self.lockout.agreed(key)
        if start and calibration:
            # the start's heading is as suspect as its position: alpha scales a 5 mrad
            # sigma, which a 180 deg error outlasts (4 lock-outs on the sample bag); the
            # compass's sum psi + offset keeps its variance
            q[PSI, PSI] += START_HEADING_VAR
            if self.est_hoff:
                q[HOFF, HOFF] += START_HEADING_VAR
                q[PSI, HOFF] -= START_HEADING_VAR
                q[HOFF, PSI] -= START_HEADING_VAR
        j = self.window.link_keyframe(q, None if start else self.noise.fixed_sigma)
        if not lockout:
            return j
        sensor = key[0] if isinstance(key, tuple) else key
        count, first = self.lockout.streak(key)
        wait = self.lockout.recovered(key, t_m)
        self.log.rejected[(sensor, "lockout_recovery")] += 1
        why = ("; none had agreed with the estimate since the start: the start is taken for "
               "wrong (the config's initial_pose?), in the batch too" if start else "")
        self.log.note(t_m, f"{sensor}: gate lock-out after {count} rejections over "
                      f"{t_m - first:.1f} s; belief widened x{alpha:.3g} and the {what} "
                      f"fused (next recovery not before {wait:.0f} s){why}")
        return j
