"""Seed 002's EKF: wheel odometry drives the pose, range/bearing sightings of landmarks correct it.

Two filters, both :class:`ddfuse.estimation.estimator.Estimator` s on the shared Kalman core
(``ekf_baseline.kalman``: Joseph update, wrapped bearing innovations, per-sensor chi-square gate
with lock-out recovery); the seed's errors are listed in docs/errata.md, "Seed 002".

* :class:`LandmarkEkf` -- localisation in a known map. State (x, y, psi): position in the
  map/local frame (m) and heading CCW from its x axis (rad).
* :class:`LandmarkSlamEkf` -- the seed's augmented state: (x, y, psi, l1x, l1y, l2x, l2y, ...),
  each landmark appended (m, map frame) the first time it is seen with a bearing, initialised
  from that range/bearing with the full covariance (pose uncertainty and measurement noise mapped
  through the inverse observation model, cross-covariances with everything already in the state).

Motion (the control input, as in the seed): WheelOdometry (v m/s, yaw rate rad/s) or WheelSpeeds
(converted with robot.wheel_radius and robot.track_width). An odometry sample is the mean twist
over its counting interval, the time since the previous sample (that is how wheel odometry is
computed: encoder counts over the interval, stamped at its end), so the filter moves the pose
over (t_prev, t] with the sample stamped t: sightings inside that interval wait (at most one
odometry period) until the sample that covers them arrives, then are applied in time order.
Holding the LAST sample instead (the seed's zero-order hold) applies every twist one period late.
Sightings before the first odometry sample are applied at once with the robot at rest; those
after the last one, in ``finish``, with the last twist held. ``motion='exact'`` moves the pose
along the constant-twist arc (``ddfuse.factors.kinematics.se2_step_jac``, smooth through zero yaw
rate); ``'euler'`` is the seed's first-order model x' = x + v cos(psi) dt,
y' = y + v sin(psi) dt, psi' = psi + w dt.

Odometry calibration: when the config gives the uncertainty of the nominal geometry
(robot.wheel_radius_std / track_width_std), two states follow the pose, k_v and k_w
(``ekf_baseline.calibration``): the true twist is (k_v v, k_w w) of the odometry's (v, w). The
sightings make them observable.

Process noise: the odometry's error is white from sample to sample and held for one sample
period tau, so it adds G diag(var_v, var_w) G^T tau / dt per step of length dt, G = df/d(v, w)
(seed: G Q G^T), with the variances scaled by k^2. Over a whole sample period this equals the
seed's per-step G Q G^T, but it does not shrink when a landmark sighting splits the period into
shorter prediction steps. The config's robot.slip, when stated, adds white body-frame velocity
noise (longitudinal, lateral) and yaw-rate noise over every step, rotated into the world frame.

Observation (LandmarkObservation): range r = |l - p| (m) and bearing b = atan2(l - p) - psi
(rad, body frame, CCW from forward x), or the range alone when ``has_bearing`` is False.

The motion and observation models are ``ekf_baseline.landmark_model``'s plain-float functions.
LandmarkEkf runs its prediction and sightings in compiled kernels on them by default
(``ekf_baseline.landmark_compiled``; docs/design/ekf_kernels.md); LandmarkSlamEkf, whose state
grows, in Python.
"""

from __future__ import annotations

import math

import numpy as np
from ddfuse.ekf_baseline import GIVEN_POSE_STD
from ddfuse.ekf_baseline import compiled as jit
from ddfuse.ekf_baseline.calibration import ScaleStates
from ddfuse.ekf_baseline.kalman import KalmanCore
from ddfuse.ekf_baseline.landmark_compiled import LandmarkKernels, warm_up
from ddfuse.ekf_baseline.landmark_model import (
    MIN_RANGE,
    odometry_step,
    range_bearing_terms,
)
from ddfuse.ekf_baseline.landmark_relocalise import MIN_SIGHTINGS, usable_fit
from ddfuse.estimation.config import DEFAULT_GATE, LANDMARK_NOT_IN_MAP, Config, landmark_maps
from ddfuse.estimation.estimator import Estimate, Estimator
from ddfuse.estimation.gaps import gap_note, grown_pose_cov, is_gap
from ddfuse.estimation.landmark_correlation import SightingClock
from ddfuse.estimation.landmark_frames import FrameBearings, FrameTerms
from ddfuse.estimation.measurements import (
    GroundTruthPose,
    LandmarkObservation,
    WheelOdometry,
    WheelSpeeds,
)

__all__ = [
    "LandmarkEkf",
    "LandmarkSlamEkf",
    "motion_step",
    "range_bearing",
    "landmark_from_range_bearing",
]

_PI = math.pi
_TWO_PI = 2.0 * math.pi
_GIVEN_STD = (GIVEN_POSE_STD[0], GIVEN_POSE_STD[0], GIVEN_POSE_STD[1])  # x, y, psi
TAU_BOUNDS = (1e-3, 0.5)  # s: the odometry sample period is clamped to this range
_TAU_LO, _TAU_HI = TAU_BOUNDS
# rad: the sigma of a heading uniform on the circle, pi / sqrt(3); LandmarkSlamEkf is lost beyond
LOST_HEADING_STD = _PI / math.sqrt(3.0)
# rad: after a gap, a heading known worse than this is restarted from a frame of sightings
# (landmark_relocalise) rather than updated about: a bearing's Jacobian at a heading this far
# off moves the pose the wrong way (docs/design/gaps.md)
RELOCALISE_HEADING_STD = 0.1


def _wrap(a: float) -> float:
    return (a + _PI) % _TWO_PI - _PI


def motion_step(pose, v: float, w: float, dt: float, motion: str = "exact"):
    """Pose after ``dt`` s of constant (v m/s, w rad/s) from ``pose`` (x m, y m, psi rad)
    (``landmark_model.odometry_step``).

    Returns (pose1 (3,), F (3, 3) = d pose1 / d pose, G (3, 2) = d pose1 / d (v, w)); psi1 is
    wrapped to [-pi, pi)."""
    if motion not in ("exact", "euler"):
        raise ValueError(f"motion must be 'exact' or 'euler', got {motion!r}")
    x1, y1, p1, J = odometry_step(pose[0], pose[1], pose[2], v, w, dt, motion == "euler")
    J = np.array(J)
    return np.array([x1, y1, _wrap(p1)]), J[:, :3], J[:, 3:]


def range_bearing(pose, landmark, with_bearing: bool = True):
    """Predicted (range m, bearing rad) of ``landmark`` (x, y) from ``pose`` (x, y, psi)
    (``landmark_model.range_bearing_terms``).

    Returns (h (m,), Hp (m, 3) = dh/d pose, Hl (m, 2) = dh/d landmark), m = 2, or 1 (range
    only) without ``with_bearing``; the bearing is wrapped to [-pi, pi). Raises ValueError when
    the landmark is at the body origin (range < MIN_RANGE), where the bearing is undefined."""
    r, b, ar, br, aq, bq = range_bearing_terms(float(pose[0]), float(pose[1]), float(pose[2]),
                                               float(landmark[0]), float(landmark[1]))
    if r < MIN_RANGE:
        raise ValueError("landmark at the body origin")
    Hl = np.array([[ar, br], [-aq, bq]])
    Hp = np.array([[-ar, -br, 0.0], [aq, -bq, -1.0]])
    h = np.array([r, b])
    if not with_bearing:
        return h[:1], Hp[:1], Hl[:1]
    return h, Hp, Hl


def landmark_from_range_bearing(pose, r: float, b: float):
    """Landmark position (x, y) from one range/bearing sighting taken at ``pose``.

    Returns (l (2,), Gp (2, 3) = dl/d pose, Gz (2, 2) = dl/d (r, b)), the inverse observation
    model and its Jacobians used to initialise the landmark's covariance."""
    x, y, psi = pose
    a = psi + b
    c, s = math.cos(a), math.sin(a)
    l = np.array([x + r * c, y + r * s])
    Gp = np.array([[1.0, 0.0, -r * s], [0.0, 1.0, r * c]])
    Gz = np.array([[c, -r * s], [s, r * c]])
    return l, Gp, Gz


class _OdometryDrivenEkf(Estimator):
    """What both filters share: initialisation, the odometry control input and prediction."""

    n_pose = 3

    def __init__(
        self,
        cfg: Config,
        *,
        initial_pose: tuple[float, float, float] | None,
        motion: str,
        init_std: tuple[float, float, float],
        compiled: bool = False,
    ) -> None:
        super().__init__()
        self.compiled = bool(compiled)
        if self.compiled:
            warm_up()  # compile / load the kernels now, not in the first step
            self.log = jit.BufferedLog()
        if motion not in ("exact", "euler"):
            raise ValueError(f"motion must be 'exact' or 'euler', got {motion!r}")
        self.cfg = cfg
        self._clock = SightingClock(cfg)  # a correlated sensor's factor on R (fusion only)
        self._frames = FrameBearings(cfg)  # bearings with an error common to their frame
        self.motion = motion
        self.init_std = tuple(float(s) for s in init_std)
        self.kf: KalmanCore | None = None
        self.t: float | None = None
        # control input (the twist of the current odometry interval) and its variances
        self.v = 0.0
        self.w = 0.0
        self.v_var = 0.0
        self.w_var = 0.0
        self._t_odo: float | None = None
        self.tau: float | None = None  # s, odometry sample period
        self._pending: list[LandmarkObservation] = []  # sightings waiting for their odometry
        self._relocalise = False  # after a gap: restart from the first frame that fixes the pose
        # odometry scale states (k_v, k_w) follow the pose when the geometry is uncertain
        self._scale = ScaleStates.of(cfg, 3)
        self.n_base = 5 if self._scale else 3
        self._gates = {s.name: s.gate for s in cfg.sensors}
        # the robot's stated slip (robot.slip: white body-frame velocity and yaw-rate noise,
        # densities), on top of the odometry's own noise; none stated: none added
        slip = cfg.robot.slip
        self._slip = tuple(float(slip.get(k, 0.0)) ** 2 for k in (
            "longitudinal", "lateral", "heading")) if slip else None
        if initial_pose is None and isinstance(cfg.initial_pose, tuple):
            initial_pose = cfg.initial_pose
        self._wait_truth = initial_pose is None and cfg.initial_pose == "ground_truth"
        if initial_pose is not None:
            self._start(initial_pose)
        elif not self._wait_truth:
            self._start((0.0, 0.0, 0.0))  # the config's documented default: the origin

    def _start(self, pose) -> None:
        x0 = np.array([float(pose[0]), float(pose[1]), float(pose[2])])
        self._pose_prior = x0.copy()  # the pose before the updates at the current time
        P0 = np.diag(np.square(self.init_std))
        if self._scale:
            x0 = np.concatenate([x0, [1.0, 1.0]])
            P0 = np.pad(P0, ((0, 2), (0, 2)))
            self._scale.set_prior(x0, P0)
        if self.compiled:
            self.kf = self._compiled_core(x0, P0)
        else:
            self.kf = KalmanCore(x0, P0, self.log, state_angles=(2,))

    def _gate(self, sensor: str) -> float | None:
        return self._gates.get(sensor, DEFAULT_GATE)

    # ------------------------------------------------------------------ prediction
    def predict_to(self, t: float) -> None:
        """Move the pose to time ``t`` (s) with the held control input."""
        if self.t is None:
            self.t = t
            return
        dt = t - self.t
        if dt <= 0.0:
            return
        if self.compiled:  # (inline: ~0.3 us a call of 3 us per odometry sample)
            kf, tau = self.kf, self.tau
            self._lm_predict(kf.fp, kf.ip, kf.W, dt, self.v, self.w, self.v_var, self.w_var,
                             dt if tau is None else tau)
            self.t = t
            return
        kf = self.kf
        x = kf.x.tolist()
        kv, kw = (x[3], x[4]) if self.n_base == 5 else (1.0, 1.0)
        x1, y1, p1, J = odometry_step(x[0], x[1], x[2], kv * self.v, kw * self.w, dt,
                                      self.motion == "euler")
        J = np.array(J)
        Fp, G = J[:, :3], J[:, 3:]
        self._first_estimates_motion(Fp)
        tau = self.tau if self.tau is not None else dt
        # numpy's products, not landmark_model.odometry_noise_terms (the kernels' Q): summed in
        # another order, they move ekf_slam's track on mrclam1_robot1.bag by 1e-8
        # (docs/design/ekf_kernels.md)
        Qp = (G * np.array([kv * kv * self.v_var, kw * kw * self.w_var])) @ G.T * (tau / dt)
        if self._slip is not None:
            ql, qt, qh = self._slip
            c, sn = math.cos(x[2]), math.sin(x[2])
            Qp = Qp + dt * np.array(((c * c * ql + sn * sn * qt, c * sn * (ql - qt), 0.0),
                                     (c * sn * (ql - qt), sn * sn * ql + c * c * qt, 0.0),
                                     (0.0, 0.0, qh)))
        pose1 = (x1, y1, _wrap(p1))
        n = kf.n
        if n == 3:
            F, Q = Fp, Qp
        else:
            F = np.eye(n)
            F[:3, :3] = Fp
            if self.n_base == 5:
                F[:3, 3:5] = G * np.array([self.v, self.w])  # d pose1 / d (k_v, k_w)
            Q = np.zeros((n, n))
            Q[:3, :3] = Qp
        xn = kf.x.copy()
        xn[:3] = pose1
        kf.predict(F, Q, xn)
        self.t = t
        self._pose_prior = kf.x[:3].copy()

    def _first_estimates_motion(self, Fp: np.ndarray) -> None:
        """Hook for LandmarkSlamEkf's first-estimates Jacobian; the known-map filter has none."""

    def _set_control(self, t: float, v, w, v_var: float, w_var: float, sensor: str) -> None:
        if v is None or w is None:
            # an odometry sensor configured without 'v' or 'yaw_rate': that component is unknown
            key = (sensor, "missing_component")
            if self.log.rejected[key] == 0:
                self.log.note(t, f"{sensor}: odometry lacks v or yaw_rate; using 0 +- 1 for it")
            self.log.rejected[key] += 1
        self.v, self.v_var = (v, v_var) if v is not None else (0.0, 1.0)
        self.w, self.w_var = (w, w_var) if w is not None else (0.0, 1.0)
        t_odo = self._t_odo
        if t_odo is not None and t > t_odo:  # clamped to TAU_BOUNDS (no min/max: ~0.1 us)
            d = t - t_odo
            self.tau = _TAU_LO if d < _TAU_LO else _TAU_HI if d > _TAU_HI else d
        self._t_odo = t

    # ------------------------------------------------------------------ Estimator
    def process(self, m) -> None:
        if isinstance(m, GroundTruthPose):
            if self.kf is None and self._wait_truth:
                self._start((m.x, m.y, m.yaw))
                self._wait_truth = False
                self.t = m.t
            return
        self.in_order(m)  # no history: a stale measurement is refused, not fused as current
        if self.kf is None:
            return
        last = self._pending[-1].t if self._pending else self.t
        if last is not None and is_gap(m.t - last):
            self._after_gap(m.t)
        if isinstance(m, WheelOdometry):
            self._odometry(m.t, m.v, m.yaw_rate, m.v_var, m.yaw_rate_var, m.sensor)
        elif isinstance(m, WheelSpeeds):
            r, L = self.cfg.robot.wheel_radius, self.cfg.robot.track_width
            if r is None or L is None:
                self.log.rejected[(m.sensor, "no_wheel_geometry")] += 1
                return
            self._odometry(m.t, *m.twist(r, L), m.sensor)
        elif isinstance(m, LandmarkObservation):
            if self._t_odo is None and not self._relocalise:  # no odometry yet: at rest
                self.predict_to(m.t)
                self._sighting(m)
            else:
                self._pending.append(m)

    def _after_gap(self, t: float) -> None:
        """No message for a gap (``estimation.gaps``) until ``t``: apply the sightings before
        it, then restart at ``t`` from the last pose with its covariance grown by what the robot
        could have done in the gap, every cross term with the pose dropped (scales and mapped
        landmarks keep theirs). The next odometry sample only starts the clock again: held
        backward over the gap, its twist with the noise of one sample period made the pose
        over-confident after it (docs/design/gaps.md)."""
        self._flush()
        kf = self.kf
        gap = t - self.t
        P = kf.P.copy()
        pose = grown_pose_cov(P[:3, :3], gap, self.cfg.robot)
        P[:3, :] = 0.0
        P[:, :3] = 0.0
        P[:3, :3] = pose
        kf.P = P
        self.t = t
        self._t_odo = None
        self._pose_prior = kf.x[:3].copy()
        self._relocalise = True
        self.log.note(t, gap_note(self.name, gap, pose))

    def _odometry(self, t: float, v, w, v_var: float, w_var: float, sensor: str) -> None:
        """A sample covering (previous sample, t]: the twist of that interval; apply the
        sightings inside it, then move to t. The first sample only starts the clock."""
        if self._t_odo is None:
            if self._pending:  # the sightings after a gap, held for relocalising
                self._flush()
            self.predict_to(t)
            self._set_control(t, v, w, v_var, w_var, sensor)
            return
        self._set_control(t, v, w, v_var, w_var, sensor)
        if self._pending:
            self._flush()
        self.predict_to(t)

    def _flush(self) -> None:
        pending, self._pending = self._pending, []
        i = 0
        while i < len(pending):
            j = i + 1
            while j < len(pending) and pending[j].t == pending[i].t:
                j += 1
            frame = pending[i:j]
            i = j
            if self._relocalise:
                self.predict_to(frame[0].t)
                frame = self._relocalised(frame)
            for s in frame:
                self.predict_to(s.t)
                self._sighting(s)

    def _relocalised(self, frame: list[LandmarkObservation]) -> list[LandmarkObservation]:
        """After a gap, while the heading is known worse than ``RELOCALISE_HEADING_STD``:
        restart the pose from ``frame`` (sightings of one stamp) alone when it fixes the pose
        (``landmark_relocalise.usable_fit``), every cross term with the pose dropped. Returns
        the sightings it did not use (the caller updates with those as usual)."""
        kf = self.kf
        if kf.P[2, 2] <= RELOCALISE_HEADING_STD ** 2:
            self._relocalise = False
            return frame
        rows, used = self._frame_rows(frame)
        # the frame's common bearing error: exact for one sensor's frame; with several sensors
        # the largest one's, which overstates the others' (each has its own common error)
        common = max((self._frames.common.get(m.sensor, 0.0) for m in used), default=0.0)
        fit = (usable_fit(kf.x[:3], kf.P[:3, :3], rows, common)
               if len(rows) >= MIN_SIGHTINGS else None)
        if fit is None:
            return frame
        P = kf.P.copy()
        P[:3, :] = 0.0
        P[:, :3] = 0.0
        P[:3, :3] = fit.cov
        kf.P = P
        kf.x[:3] = fit.pose
        self._pose_prior = fit.pose.copy()
        self._relocalise = False
        x, y, psi = fit.pose
        self.log.note(frame[0].t, f"{self.name}: relocalised from {len(rows)} sightings of one "
                                  f"frame at ({x:.2f}, {y:.2f} m, {math.degrees(psi):.1f} deg), "
                                  f"sigma {math.sqrt(fit.cov[0, 0] + fit.cov[1, 1]):.2f} m, "
                                  f"{math.degrees(math.sqrt(fit.cov[2, 2])):.1f} deg")
        taken = {id(u) for u in used}
        return [s for s in frame if id(s) not in taken]

    def _frame_rows(self, frame: list[LandmarkObservation]):
        """The rows of ``landmark_relocalise.fit_pose`` for the sightings of ``frame`` whose
        landmark position is known, and those sightings."""
        raise NotImplementedError  # pragma: no cover - abstract

    def finish(self) -> None:
        """Apply the sightings after the last odometry sample, with its twist held."""
        if self.kf is not None:
            self._flush()

    def _sighting(self, m: LandmarkObservation) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _measure(self, m: LandmarkObservation, landmark, lcols: list[int] | None,
                 jac_at=None, fuse: float = 1.0, ref=None) -> None:
        """Update with one sighting of ``landmark`` (x, y); ``lcols`` its state columns (SLAM).
        ``jac_at`` = (pose, landmark): where the Jacobians are evaluated, if not at the
        current estimate (first-estimates Jacobians). ``fuse``: the factor on R in the gain and
        Joseph update (``estimation.landmark_correlation``; the gate and the log keep R).
        ``ref``: how :meth:`_frame_landmark` finds the landmark again when a later sighting of
        the same frame is conditioned on this one (``estimation.landmark_frames``; default:
        ``landmark`` itself)."""
        kf = self.kf
        frame = self._frames.terms(m) if self._frames else None
        try:
            h, Hp, Hl = range_bearing(kf.x[:3], landmark, m.has_bearing)
            if jac_at is not None:
                _, Hp, Hl = range_bearing(jac_at[0], jac_at[1], m.has_bearing)
            k = h.shape[0]
            H = np.zeros((k, kf.n))
            H[:, :3] = Hp
            if lcols is not None:
                H[:, lcols] = Hl
            if m.has_bearing:
                z, R, angles = [m.range, m.bearing], np.diag([m.range_var, m.bearing_var]), (1,)
            else:
                z, R, angles = [m.range], np.array([[m.range_var]]), ()
            if frame is not None:
                self._condition(frame, h, H, R, jac_at is not None)
        except ValueError:
            self.log.rejected[(m.sensor, "degenerate")] += 1
            return
        if fuse == 1.0:
            ok = kf.update(m.t, m.sensor, "landmark", z, h, H, R, angles=angles,
                           gate=self._gate(m.sensor))
        else:
            ok = kf.update_blocks(m.t, np.asarray(z, float), h, H, R,
                                  ((m.sensor, "landmark", 0, k, angles, self._gate(m.sensor)),),
                                  fuse=(fuse,)) == 1
        if frame is not None and ok:
            self._frames.accepted(m, tuple(landmark) if ref is None else ref)

    def _frame_landmark(self, ref):
        """An earlier sighting's landmark from its ``ref``: (position (x, y) m, its state
        columns or None, the position its Jacobians are taken at)."""
        return ref, None, ref

    def _condition(self, frame: FrameTerms, h: np.ndarray, H: np.ndarray, R: np.ndarray,
                   fej: bool) -> None:
        """Turn a sighting's bearing row (``h``, ``H``, ``R``: row 1, in place) into the
        conditional one given its frame's earlier sightings (``estimation.landmark_frames``):
        h + sum_j w_j (z_j - h_j), H - sum_j w_j H_j, the conditional variance. ``fej``: the
        Jacobians at the pose before this time's updates and the landmarks' first estimates."""
        x = self.kf.x[:3]
        for (ref, zb), w in zip(frame.earlier, frame.weights, strict=True):
            lm, cols, lm_jac = self._frame_landmark(ref)
            hj, Hp, Hl = range_bearing(x, lm, True)
            if fej:
                _, Hp, Hl = range_bearing(self._pose_prior, lm_jac, True)
            h[1] += w * _wrap(zb - hj[1])
            H[1, :3] -= w * Hp[1]
            if cols is not None:
                H[1, cols] -= w * Hl[1]
        R[1, 1] = frame.bearing_var

    def _pose_estimate(self, names: tuple[str, ...]) -> Estimate | None:
        if self.kf is None:
            return None
        if self.n_base == 5:
            names = (*names[:3], "k_v", "k_w", *names[3:])
        x, P = self.kf.x, self.kf.P
        return Estimate(
            t=self.t if self.t is not None else 0.0,
            pose=(float(x[0]), float(x[1]), float(x[2])),
            pose_cov=P[:3, :3].copy(),
            state=x.copy(),
            state_cov=P.copy(),
            state_names=names,
        )


class LandmarkEkf(LandmarkKernels, _OdometryDrivenEkf):
    """Seed 002's EKF localising in a known landmark map.

    ``landmarks`` maps id -> (x, y) (m, map/local frame); default: the maps of the config's
    landmark sensors. ``initial_pose`` (x, y, psi) overrides the config's; with 'ground_truth'
    in the config the filter starts at the first GroundTruthPose it is given (or pass
    ``stream.ground_truth[0]``'s pose). ``init_std`` are the initial standard deviations of
    (x m, y m, psi rad). ``motion`` is 'exact' (constant-twist arc) or 'euler' (the seed's).
    ``compiled`` (default): the prediction and the sightings run in the numba kernels of
    ``ekf_baseline.kalman_jit`` (``landmark_compiled``; what they defer -- a gate lock-out's
    recovery, a singular S, a landmark at the body origin -- in the Python update on the same
    arrays; so are the sightings of a sensor with ``noise.bearing_common``,
    ``estimation.landmark_frames``); False: all in Python (numpy). The tests compare the two
    (tests/test_landmark_compiled.py; docs/design/ekf_kernels.md)."""

    name = "landmark_ekf"

    def __init__(
        self,
        cfg: Config,
        *,
        initial_pose: tuple[float, float, float] | None = None,
        landmarks: dict[str, tuple[float, float]] | None = None,
        motion: str = "exact",
        init_std: tuple[float, float, float] = _GIVEN_STD,
        compiled: bool = True,
    ) -> None:
        super().__init__(cfg, initial_pose=initial_pose, motion=motion, init_std=init_std,
                         compiled=compiled)
        if landmarks is None:
            landmarks = landmark_maps(cfg)
        self.landmarks = {str(k): (float(v[0]), float(v[1])) for k, v in landmarks.items()}

    def _sighting(self, m: LandmarkObservation) -> None:
        lm = self.landmarks.get(m.landmark_id)
        if lm is None:
            # the bag reader drops these already; fed directly, counted under its reason
            self.log.rejected[(m.sensor, LANDMARK_NOT_IN_MAP)] += 1
            return
        f = self._clock.factor(m)
        if self.compiled and m.sensor not in self._frames.common:
            self._sighting_compiled(m, lm, f)
        else:
            self._measure(m, lm, None, fuse=f)

    def _frame_rows(self, frame: list[LandmarkObservation]):
        used = [m for m in frame if m.has_bearing and m.landmark_id in self.landmarks]
        rows = [(*self.landmarks[m.landmark_id], m.range, m.bearing, m.range_var,
                 m.bearing_var) for m in used]
        return rows, used

    def estimate(self) -> Estimate | None:
        return self._pose_estimate(("x", "y", "yaw"))


class LandmarkSlamEkf(_OdometryDrivenEkf):
    """Seed 002's augmented-state EKF (EKF-SLAM with known data association by landmark id).

    Landmarks are unknown at the start and appended to the state the first time each is seen
    with a bearing (a range-only first sighting cannot place it and is counted in
    ``log.rejected[(sensor, 'range_only_unmapped')]``). ``landmark_positions()`` returns the
    current map. Other arguments as for :class:`LandmarkEkf`."""

    name = "landmark_slam_ekf"

    def __init__(
        self,
        cfg: Config,
        *,
        initial_pose: tuple[float, float, float] | None = None,
        motion: str = "exact",
        init_std: tuple[float, float, float] = _GIVEN_STD,
    ) -> None:
        super().__init__(cfg, initial_pose=initial_pose, motion=motion, init_std=init_std)
        self.slots: dict[str, int] = {}  # landmark id -> index of its x in the state
        self.first_estimate: dict[str, np.ndarray] = {}  # landmark id -> its position when added

    def _first_estimates_motion(self, Fp: np.ndarray) -> None:
        """FEJ: d pose1 / d psi at the pose before this time's updates, not after them. For
        both motion models that column is (-(y1 - y0), x1 - x0, 1) with (x0, y0) the pose the
        step starts from; replacing the updated (x0, y0) by the prior one keeps the linearised
        model's unobservable directions (global translation and rotation) unobservable."""
        d = self.kf.x[:2] - self._pose_prior[:2]
        Fp[0, 2] -= d[1]
        Fp[1, 2] += d[0]

    def _sighting(self, m: LandmarkObservation) -> None:
        """Use sighting ``m`` (update or augment); if that leaves the filter lost
        (:meth:`_lost_after`), restart it from its pose before the sighting (:meth:`_restart`)."""
        kf = self.kf
        pose, pose_cov = kf.x[:3].copy(), kf.P[:3, :3].copy()
        singular = self.log.rejected.get((m.sensor, "singular"), 0)
        try:
            self._use_sighting(m)
        except (np.linalg.LinAlgError, FloatingPointError, ZeroDivisionError,
                OverflowError) as exc:
            self._restart(m, pose, pose_cov, f"{type(exc).__name__}: {exc}")
            return
        why = self._lost_after(m.sensor, singular)
        if why:
            self._restart(m, pose, pose_cov, why)

    def _lost_after(self, sensor: str, singular: int) -> str | None:
        """Why the filter is lost after a sighting of ``sensor`` (``singular``: its count of
        non-positive-definite innovation covariances before it), or None. Lost: a state or
        covariance entry not finite, an innovation covariance or P not positive definite, or
        the heading's sigma beyond LOST_HEADING_STD, where a heading is known no better than
        uniform on the circle and the linearisation about it means nothing (the gate's lock-out
        recovery inflates all of P; repeated on a landmark sighted under a wrong id it compounded
        to a pose sigma of 1e8 m on mrclam1_robot1.bag with two ids swapped)."""
        kf = self.kf
        if not (np.isfinite(kf.x).all() and np.isfinite(kf.P).all()):
            return "a state or covariance entry is not finite"
        if self.log.rejected.get((sensor, "singular"), 0) > singular:
            return "innovation covariance not positive definite"
        if kf.P[2, 2] > LOST_HEADING_STD ** 2:
            return (f"heading sigma {math.sqrt(kf.P[2, 2]):.2f} rad, more than a heading "
                    "uniform on the circle")
        try:
            np.linalg.cholesky(kf.P)
        except np.linalg.LinAlgError:
            return "covariance not positive definite"
        return None

    def _restart(self, m: LandmarkObservation, pose, pose_cov, why: str) -> None:
        """Start again from ``pose`` (x, y, psi) with covariance ``pose_cov``, the filter's
        before sighting ``m`` made it lost (``why``), with a new, empty map: the landmarks
        are added again as they are sighted. The map is dropped with the state because what
        broke it -- a landmark sighted under another's id, a compounded inflation -- is in
        the map's covariance too, and keeping it broke the filter again at the next sighting.
        Logged as a note and counted as (sensor, 'restart') in ``log.rejected``."""
        dropped = len(self.slots)
        pose = np.asarray(pose, dtype=float)
        ok = np.isfinite(pose).all() and np.isfinite(pose_cov).all()
        if not ok:  # nothing trustworthy before it either: the last estimate's pose, unknown
            pose = np.zeros(3)
        scales = self.kf.x[3:5].copy() if self.n_base == 5 else None
        self._start(pose)
        if ok:
            P = self.kf.P
            P[:3, :3] = 0.5 * (pose_cov + pose_cov.T)
            try:
                np.linalg.cholesky(P)
            except np.linalg.LinAlgError:
                P[:3, :3] = np.diag(np.square(self.init_std))
        if scales is not None and np.isfinite(scales).all():
            self.kf.x[3:5] = scales
        self.slots.clear()
        self.first_estimate.clear()
        self._frames.reset()
        self.log.rejected[(m.sensor, "restart")] += 1
        self.log.note(m.t, f"{self.name}: lost at a sighting of landmark {m.landmark_id} "
                           f"({why}); restarted from its pose before it ({pose[0]:.2f}, "
                           f"{pose[1]:.2f} m, {math.degrees(pose[2]):.1f} deg) with a new "
                           f"map ({dropped} landmarks dropped)")

    def _use_sighting(self, m: LandmarkObservation) -> None:
        i = self.slots.get(m.landmark_id)
        f = self._clock.factor(m)
        if i is not None:
            self._measure(m, self.kf.x[i:i + 2], [i, i + 1],
                          jac_at=(self._pose_prior, self.first_estimate[m.landmark_id]), fuse=f,
                          ref=m.landmark_id)
            return
        if not m.has_bearing:
            self.log.rejected[(m.sensor, "range_only_unmapped")] += 1
            return
        if m.range < MIN_RANGE:
            self.log.rejected[(m.sensor, "degenerate")] += 1
            return
        self._augment(m)

    def _augment(self, m: LandmarkObservation) -> None:
        """Append a landmark initialised from sighting ``m``: l = g(pose, r, b), with
        P_ll = Gp P_pp Gp^T + Gz R Gz^T and P_l* = Gp P_p*. The sighting is used for the
        initialisation only (using it again as an update would count it twice)."""
        kf = self.kf
        n = kf.n
        l, Gp, Gz = landmark_from_range_bearing(kf.x[:3], m.range, m.bearing)
        # with a bearing error common to the frame, the sighting's whole bearing variance
        # (own + common; its correlation with the frame's other sightings is left out)
        common = self._frames.common.get(m.sensor, 0.0)
        R = np.diag([m.range_var, m.bearing_var + common if common else m.bearing_var])
        P = kf.P
        cross = Gp @ P[:3, :]  # (2, n)
        Pll = Gp @ P[:3, :3] @ Gp.T + Gz @ R @ Gz.T
        Pn = np.zeros((n + 2, n + 2))
        Pn[:n, :n] = P
        Pn[n:, :n] = cross
        Pn[:n, n:] = cross.T
        Pn[n:, n:] = 0.5 * (Pll + Pll.T)
        _resize(kf, np.concatenate([kf.x, l]), Pn)
        self.slots[m.landmark_id] = n
        self.first_estimate[m.landmark_id] = l.copy()
        self.log.note(m.t, f"landmark {m.landmark_id} added at ({l[0]:.3f}, {l[1]:.3f}) m")

    def _frame_landmark(self, ref):
        """``ref``: the landmark id: its state's position and columns, its first estimate."""
        i = self.slots[ref]
        return self.kf.x[i:i + 2], [i, i + 1], self.first_estimate[ref]

    def landmark_positions(self) -> dict[str, tuple[float, float]]:
        """Current estimate of every mapped landmark, id -> (x, y) in metres."""
        if self.kf is None:
            return {}
        x = self.kf.x
        return {k: (float(x[i]), float(x[i + 1])) for k, i in self.slots.items()}

    def landmark_covariance(self, landmark_id: str) -> np.ndarray:
        """(2, 2) covariance (m^2) of one mapped landmark."""
        i = self.slots[landmark_id]
        return self.kf.P[i:i + 2, i:i + 2].copy()

    def _frame_rows(self, frame: list[LandmarkObservation]):
        """As the base class's, against the mapped landmarks: a landmark's own uncertainty
        (half the trace of its covariance, m^2) added to the range's variance and, over the
        range squared, to the bearing's."""
        used, rows = [], []
        x, P = self.kf.x, self.kf.P
        for m in frame:
            i = self.slots.get(m.landmark_id)
            if i is None or not m.has_bearing or m.range < MIN_RANGE:
                continue
            var = 0.5 * (P[i, i] + P[i + 1, i + 1])
            used.append(m)
            rows.append((x[i], x[i + 1], m.range, m.bearing, m.range_var + var,
                         m.bearing_var + var / m.range ** 2))
        return rows, used

    def estimate(self) -> Estimate | None:
        names = ["x", "y", "yaw"]
        for k in sorted(self.slots, key=self.slots.get):
            names += [f"landmark:{k}:x", f"landmark:{k}:y"]
        return self._pose_estimate(tuple(names))


def _resize(kf: KalmanCore, x: np.ndarray, P: np.ndarray) -> None:
    """Give ``kf`` a larger state (mean ``x``, covariance ``P``), keeping its log, gate streaks
    and recoveries. KalmanCore has no resize of its own."""
    n = x.shape[0]
    kf.x = np.array(x, dtype=float)
    kf.P = np.array(P, dtype=float)
    kf.n = n
