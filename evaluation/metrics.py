"""Trajectory metrics: pure math on arrays, no I/O or plotting (evo's core/metrics split).

Trajectories are ``ddfuse.estimation.runner.Trajectory``: ``t`` (N,) s, ``pose`` (N, 3) as
(x m, y m, yaw rad) in the local frame, ``cov`` (N, 3, 3). The semantics follow evo (1.38) so
that ``evo_ape`` / ``evo_rpe`` on the TUM files ddfuse writes give the same numbers:

* association (``evo.core.sync``): the samples of the shorter trajectory (the estimate when both
  are equally long) are each paired with the nearest-in-time sample of the other, if within
  ``max_diff`` seconds; a sample of the longer one may serve several pairs;
* alignment (``PosePath3D.align`` / ``align_origin``) of the estimate onto the reference, on the
  associated pairs: ``none``; ``se2``, Umeyama's least-squares rotation and translation of the
  positions (no scale; on planar data this is evo's SE(3) Umeyama); ``origin``, the rigid motion
  taking the first associated estimate pose onto the reference's;
* ATE (evo's APE): the position error |p_est - p_ref| (m) and the heading error
  |wrap(yaw_est - yaw_ref)| (rad, evo's ``rotation_angle_rad`` for planar poses) per pair;
* RPE: for index pairs (i, j) a time or path ``delta`` apart, E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)
  with Q the reference and P the estimate; translation |t(E)| (m) and angle |angle(E)| (rad).
  Pairs are consecutive (evo's default) or all pairs; path pairs are taken on the estimate's path
  unless ``pairs_from_reference`` (evo's default and option). evo has no time delta; ours is the
  same rule with elapsed seconds in place of path metres.

Statistics (``Stats``) are evo's: RMSE, mean, median, std (population), min, max.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np
from ddfuse.estimation.runner import Trajectory
from ddfuse.factors.kinematics import antenna_position

ALIGNMENTS = ("none", "se2", "origin")
PAIRINGS = ("nearest", "interpolate")
RPE_UNITS = ("s", "m")


def wrap(a):
    """Wrap angles (rad) to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def associate(t_est: np.ndarray, t_ref: np.ndarray, max_diff: float) -> tuple[np.ndarray, ...]:
    """Indices (i_est, i_ref) of associated pairs, evo's nearest-time rule (module docstring).

    Both stamp arrays (s) must be sorted. Pairs come in increasing order of the shorter
    trajectory's index; ties between two equally near samples go to the earlier one."""
    t_est, t_ref = np.asarray(t_est, float), np.asarray(t_ref, float)
    if len(t_est) == 0 or len(t_ref) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    # evo starts from the trajectory with fewer poses so that none of its poses is lost.
    est_short = len(t_est) <= len(t_ref)
    short, long_ = (t_est, t_ref) if est_short else (t_ref, t_est)
    k = np.minimum(np.searchsorted(long_, short, side="right"), len(long_) - 1)
    diff_ub = long_[k] - short
    diff_lb = np.where(k > 0, short - long_[np.maximum(k - 1, 0)], np.inf)
    take_ub = (diff_ub <= max_diff) & (diff_ub < diff_lb)
    take_lb = ~take_ub & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
    inside = (short >= long_[0] - max_diff) & (short <= long_[-1] + max_diff)
    ok = inside & (take_ub | take_lb)
    i_short = np.nonzero(ok)[0]
    i_long = np.where(take_ub, k, k - 1)[ok]
    return (i_short, i_long) if est_short else (i_long, i_short)


def association_error(est: Trajectory, ref: Trajectory, max_diff: float = 0.05) -> Stats:
    """What the nearest-time association alone costs the position ATE (m): for each associated
    pair, the distance between the reference at its own stamp and the reference interpolated at
    the estimate's stamp. An estimate exactly on the reference's path at its own time still
    scores this much (evo's rule, which does not interpolate); with truth at 10 Hz and 0.5 m/s
    it reaches 2.5 cm for an estimate midway between two truth samples."""
    i_est, i_ref = associate(est.t, ref.t, max_diff)
    if len(i_est) == 0 or len(ref) < 2:
        return Stats.of(np.zeros(0))
    t = est.t[i_est]
    d = np.column_stack([np.interp(t, ref.t, ref.pose[:, 0]),
                         np.interp(t, ref.t, ref.pose[:, 1])]) - ref.pose[i_ref, :2]
    return Stats.of(np.hypot(d[:, 0], d[:, 1]))


@dataclass
class Stats:
    """Statistics of an error series (units of the series); NaN for an empty series."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    n: int

    @classmethod
    def of(cls, e: np.ndarray) -> Stats:
        e = np.asarray(e, float)
        if e.size == 0:
            nan = math.nan
            return cls(nan, nan, nan, nan, nan, nan, 0)
        return cls(float(np.sqrt(np.mean(e * e))), float(np.mean(e)), float(np.median(e)),
                   float(np.std(e)), float(np.min(e)), float(np.max(e)), int(e.size))

    def scaled(self, k: float) -> Stats:
        """The same statistics of the series times ``k`` > 0 (e.g. rad -> deg)."""
        return Stats(self.rmse * k, self.mean * k, self.median * k, self.std * k,
                     self.min * k, self.max * k, self.n)

    def as_dict(self) -> dict:
        return asdict(self)

    to_json = as_dict

    @classmethod
    def from_json(cls, d: dict) -> Stats:
        """From ``to_json``'s dictionary (an absent key: None)."""
        return cls(*(d.get(f.name) for f in fields(cls)))


@dataclass
class PoseErrors:
    """Per-pair errors of an estimate against a reference, at the associated stamps."""

    t: np.ndarray  # (M,) s, the estimate's stamps
    dxy: np.ndarray  # (M, 2) m, estimate - reference (after alignment), local frame
    dyaw: np.ndarray  # (M,) rad, wrapped; NaN where the reference has no yaw
    i_est: np.ndarray  # (M,) indices into the estimate
    i_ref: np.ndarray | None = None  # (M,) indices into the reference

    @property
    def position(self) -> np.ndarray:
        """(M,) horizontal position error, m."""
        return np.hypot(self.dxy[:, 0], self.dxy[:, 1])


def umeyama_se2(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (2, 2) and translation t (2,) minimising sum |R src_k + t - dst_k|^2.

    ``src``, ``dst``: (N, 2) corresponding points, m. Umeyama (1991) without scale, with the
    reflection guard (det R = +1). Raises ValueError if the source points are all equal."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)
    u, d, vt = np.linalg.svd(cov)
    if len(src) < 2 or d[0] <= np.finfo(float).eps * max(1.0, float(np.abs(src).max())):
        raise ValueError("SE(2) alignment needs at least two distinct positions")
    s = np.diag([1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0])
    r = u @ s @ vt
    return r, mu_d - r @ mu_s


def _apply_se2(pose: np.ndarray, r: np.ndarray, t: np.ndarray) -> np.ndarray:
    out = pose.copy()
    # elementwise, not ``pose[:, :2] @ r.T``: BLAS rounds a row differently with the number of
    # rows, and pair_scores applies this a block of rows at a time
    x, y = pose[:, 0], pose[:, 1]
    out[:, 0] = r[0, 0] * x + r[0, 1] * y + t[0]
    out[:, 1] = r[1, 0] * x + r[1, 1] * y + t[1]
    out[:, 2] = wrap(pose[:, 2] + math.atan2(r[1, 0], r[0, 0]))
    return out


def alignment(est_pose: np.ndarray, ref_pose: np.ndarray, method: str
              ) -> tuple[np.ndarray, np.ndarray]:
    """The rigid motion (R (2, 2), t (2,)) that ``method`` applies to the estimate, from the
    associated poses ``est_pose``, ``ref_pose`` (M, 3). ValueError if it cannot be computed."""
    if method == "none":
        return np.eye(2), np.zeros(2)
    if len(est_pose) == 0:
        raise ValueError(f"{method} alignment of an empty trajectory")
    if method == "se2":
        return umeyama_se2(est_pose[:, :2], ref_pose[:, :2])
    if method == "origin":
        if not math.isfinite(ref_pose[0, 2]):
            raise ValueError("origin alignment needs the reference's heading")
        a = ref_pose[0, 2] - est_pose[0, 2]
        r = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        return r, ref_pose[0, :2] - r @ est_pose[0, :2]
    raise ValueError(f"alignment must be one of {ALIGNMENTS}, got {method!r}")


# relative slack on the largest truth gap reference_at interpolates across (see there)
GAP_REL_TOL = 1e-3


def reference_at(ref: Trajectory, t: np.ndarray, j: np.ndarray, max_diff: float) -> np.ndarray:
    """The reference's poses (M, 3) at the estimate's stamps ``t`` (M,) s: interpolated between
    the two samples that bracket each stamp where they are at most 2 ``max_diff`` apart (dense
    truth: position linearly, yaw along the shorter arc; NaN yaw stays NaN), else the
    associated sample ``j`` (M,) itself."""
    pr = ref.pose[j].copy()
    if len(ref) < 2 or len(t) == 0:
        return pr
    for a in range(0, len(t), _REF_BLOCK):  # a block's temporaries at a time, not a track's
        _interpolate_into(pr[a:a + _REF_BLOCK], ref, t[a:a + _REF_BLOCK], max_diff)
    return pr


_REF_BLOCK = 8192  # stamps reference_at interpolates at a time


def _interpolate_into(pr: np.ndarray, ref: Trajectory, t: np.ndarray, max_diff: float) -> None:
    """``reference_at`` for the stamps ``t``, written into their rows ``pr`` (a view)."""
    k = np.clip(np.searchsorted(ref.t, t, side="right"), 1, len(ref) - 1)
    t0, t1 = ref.t[k - 1], ref.t[k]
    # Truth at exactly 1 / (2 max_diff) Hz (10 Hz for 0.05 s) has gaps that float rounding of
    # epoch stamps (ulp 2.4e-7 s at 1.7e9 s) puts just over 2 max_diff: 40-63 % of them fell
    # back to the nearest sample. A relative tolerance of GAP_REL_TOL keeps them.
    dense = ((t0 <= t) & (t <= t1) & (t1 - t0 <= 2.0 * max_diff * (1.0 + GAP_REL_TOL))
             & (t1 > t0))
    if not dense.any():
        return
    k = k[dense]
    w = ((t[dense] - t0[dense]) / (t1[dense] - t0[dense]))[:, None]
    a, b = ref.pose[k - 1], ref.pose[k]
    pr[dense, :2] = a[:, :2] + w * (b[:, :2] - a[:, :2])
    pr[dense, 2] = wrap(a[:, 2] + w[:, 0] * wrap(b[:, 2] - a[:, 2]))


def pose_errors(est: Trajectory, ref: Trajectory, max_diff: float = 0.05,
                align: str = "none", pairing: str = "nearest") -> PoseErrors:
    """Errors of ``est`` against ``ref`` at the associated stamps, after ``align`` (module
    docstring; 'none': both already in the run's local frame). ``pairing``: 'nearest', the
    associated reference sample (evo's rule); 'interpolate', the reference at the estimate's own
    stamp (``reference_at``), so that an estimate exactly on the true path at its time scores 0
    (the same pairs, only their reference poses differ)."""
    if pairing not in PAIRINGS:
        raise ValueError(f"pairing must be one of {PAIRINGS}, got {pairing!r}")
    i, j = associate(est.t, ref.t, max_diff)
    pe = est.pose[i]
    pr = ref.pose[j] if pairing == "nearest" else reference_at(ref, est.t[i], j, max_diff)
    if align != "none":
        pe = _apply_se2(pe, *alignment(pe, pr, align))
    return PoseErrors(est.t[i], pe[:, :2] - pr[:, :2], wrap(pe[:, 2] - pr[:, 2]), i, j)


@dataclass
class Ape:
    """Absolute trajectory error: position (m) and heading (rad) statistics, and the errors."""

    position: Stats
    heading: Stats
    errors: PoseErrors
    align: str


def ape(est: Trajectory, ref: Trajectory, max_diff: float = 0.05, align: str = "none") -> Ape:
    """ATE of ``est`` against ``ref`` (evo's APE, translation part and rotation angle)."""
    err = pose_errors(est, ref, max_diff, align)
    yaw = np.abs(err.dyaw)
    return Ape(Stats.of(err.position), Stats.of(yaw[np.isfinite(yaw)]), err, align)


def ate(est: Trajectory, ref: Trajectory, max_diff: float = 0.05, align: str = "none"
        ) -> Stats:
    """Absolute position error (m) statistics after ``align``."""
    return ape(est, ref, max_diff, align).position


@dataclass
class Nees:
    """Pose NEES e^T P^-1 e at the associated stamps ``t`` (s), with its degrees of freedom
    ``dof`` (3, or 2 where the reference has no yaw)."""

    t: np.ndarray
    value: np.ndarray
    dof: np.ndarray
    i_est: np.ndarray  # indices into the estimate of the scored samples


def se2_log_errors(est_pose: np.ndarray, ref_pose: np.ndarray) -> np.ndarray:
    """xi = Log(X_est^-1 X_ref) (N, 3) of poses (N, 3) (x m, y m, yaw rad): the SE(2)
    exponential coordinates (rho_x m, rho_y m, theta rad) of the reference in the estimate's
    body frame, X_ref = X_est Exp(xi); rho = V(theta)^-1 R(yaw_est)^T (p_ref - p_est),
    V = [[S, -C], [C, S]], S = sin(theta)/theta, C = (1 - cos theta)/theta, theta wrapped."""
    est_pose = np.asarray(est_pose, dtype=float).reshape(-1, 3)
    ref_pose = np.asarray(ref_pose, dtype=float).reshape(-1, 3)
    th = wrap(ref_pose[:, 2] - est_pose[:, 2])
    c, s = np.cos(est_pose[:, 2]), np.sin(est_pose[:, 2])
    dx, dy = ref_pose[:, 0] - est_pose[:, 0], ref_pose[:, 1] - est_pose[:, 1]
    bx, by = c * dx + s * dy, -s * dx + c * dy
    small = np.abs(th) < 1e-6
    ts = np.where(small, 1.0, th)
    sa = np.where(small, 1.0 - th * th / 6.0, np.sin(ts) / ts)
    ca = np.where(small, 0.5 * th, (1.0 - np.cos(ts)) / ts)
    det = sa * sa + ca * ca
    return np.column_stack([(sa * bx + ca * by) / det, (-ca * bx + sa * by) / det, th])


_COV_BLOCK = 4096  # pairs (and their covariances) nees_series scores at a time


def nees_series(est: Trajectory, ref: Trajectory, max_diff: float = 0.05,
                pose_error: str = "world", *, pairs: tuple[np.ndarray, np.ndarray] | None = None,
                block: int = _COV_BLOCK) -> Nees:
    """NEES of ``est`` against ``ref`` (no alignment: the covariance is in the local frame).

    ``pose_error`` (``estimation.estimator.Estimate.pose_error``) says in which coordinates the
    estimator's Gaussian describes its error: 'world', e = pose_est - pose_ref (yaw wrapped)
    with P = ``est.cov``; 'se2', xi = Log(X_est^-1 X_ref) (``se2_log_errors``) with
    P_xi = A^-1 P A^-T, A = blockdiag(R(yaw_est), 1) (``est.cov`` is then the first-order
    world image A P_xi A^T of the filter's covariance). Where the reference has no yaw, both
    score the world-frame position error with ``est.cov[:2, :2]`` (2 dof).

    The reference is taken at each estimate's own stamp (``reference_at``, where the truth is
    dense): the nearest truth sample would add the robot's motion over the stamp difference to
    the error, which no estimator's covariance claims (the sample bag's 10 Hz outputs sit
    0.025 s from its 20 Hz truth: mean NEES 5.3 instead of 2.9 for the EKF, all at the turns).

    Samples whose covariance is missing or not positive definite are left out. ``pairs``: the
    associated pairs (i_est, i_ref) if the caller has them (``associate(est.t, ref.t,
    max_diff)``); they are scored ``block`` at a time (per pair the same values whatever the
    block: only one block's temporaries are held)."""
    if pose_error not in ("world", "se2"):
        raise ValueError(f"pose_error must be 'world' or 'se2', got {pose_error!r}")
    if block < 1:
        raise ValueError(f"block must be >= 1, got {block}")
    i_all, j_all = pairs if pairs is not None else associate(est.t, ref.t, max_diff)
    m = len(i_all)
    ts, vals, dofs, idx = np.empty(m), np.empty(m), np.empty(m, int), np.empty(m, np.int64)
    n = 0
    for a in range(0, m, block):
        i_b = i_all[a:a + block]
        t_b, pe = est.t[i_b], est.pose[i_b]
        pr = reference_at(ref, t_b, j_all[a:a + block], max_diff)
        dxy, dyaw = pe[:, :2] - pr[:, :2], wrap(pe[:, 2] - pr[:, 2])
        xi = se2_log_errors(pe, pr) if pose_error == "se2" else None
        covs = est.cov_at(i_b)  # a packed track unpacks these rows only
        for k, i in enumerate(i_b.tolist()):
            p = covs[k]
            if math.isnan(dyaw[k]):
                e, p = dxy[k], p[:2, :2]
            elif xi is not None:
                e = xi[k]
                c, s = math.cos(pe[k, 2]), math.sin(pe[k, 2])
                ai = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # A^-1
                p = ai @ p @ ai.T
            else:
                e = np.array([dxy[k, 0], dxy[k, 1], dyaw[k]])
            if not np.all(np.isfinite(p)):
                continue
            try:
                c = np.linalg.cholesky(0.5 * (p + p.T))
            except np.linalg.LinAlgError:
                continue
            z = np.linalg.solve(c, e)
            ts[n], vals[n], dofs[n], idx[n] = t_b[k], float(z @ z), len(e), i
            n += 1
    return Nees(ts[:n].copy(), vals[:n].copy(), dofs[:n].copy(), idx[:n].copy())


def nees(est: Trajectory, ref: Trajectory, max_diff: float = 0.05,
         pose_error: str = "world") -> np.ndarray:
    """Pose NEES values per associated sample (see ``nees_series``)."""
    return nees_series(est, ref, max_diff, pose_error).value


def nees_samples(est: Trajectory, ref: Trajectory, max_diff: float = 0.05,
                 pose_error: str = "world") -> tuple[np.ndarray, np.ndarray]:
    """``nees`` with the indices into ``est`` of the samples it could score: (i_est, nees)."""
    s = nees_series(est, ref, max_diff, pose_error)
    return s.i_est, s.value


def interpolate_xy(est: Trajectory, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linearly interpolated (x, y) of ``est`` at ``t`` and a mask of stamps inside its span."""
    inside = (t >= est.t[0]) & (t <= est.t[-1]) if len(est) else np.zeros(len(t), bool)
    xy = np.column_stack([np.interp(t, est.t, est.pose[:, 0]),
                          np.interp(t, est.t, est.pose[:, 1])]) if len(est) else np.zeros((0, 2))
    return xy, inside


# the estimators' lever-arm equation, element-wise over the fixes' yaws
_antenna_offsets = np.vectorize(antenna_position, otypes=[float] * 4)


def antenna_xy(est: Trajectory, t: np.ndarray, lever_arm=(0.0, 0.0), delay: float = 0.0
               ) -> tuple[np.ndarray, np.ndarray]:
    """Where ``est`` puts a GPS antenna when fixes stamped ``t`` (M,) s were taken: the pose at
    t - ``delay`` (a fix describes the antenna ``delay`` s before its stamp; position and
    unwrapped yaw linearly interpolated) plus R(yaw) ``lever_arm`` (body x, y, m), the model
    the estimators fuse the fixes with. Returns (xy (M, 2), mask of stamps inside the span)."""
    t = np.asarray(t, float)
    ts = t - delay
    if len(est) == 0:
        return np.zeros((len(t), 2)), np.zeros(len(t), bool)
    xy, inside = interpolate_xy(est, ts)
    lx, ly = float(lever_arm[0]), float(lever_arm[1])
    if lx or ly:
        yaw = np.interp(ts, est.t, np.unwrap(est.pose[:, 2]))
        ex, ny, _, _ = _antenna_offsets(0.0, 0.0, yaw, lx, ly)
        xy = xy + np.column_stack([ex, ny])
    return xy, inside


def holdout_errors(est: Trajectory, t: np.ndarray, enu_xy: np.ndarray, lever_arm=(0.0, 0.0),
                   delay: float = 0.0) -> np.ndarray:
    """Horizontal distance (m) from the estimate's GPS antenna (``antenna_xy``: ``lever_arm``,
    ``delay``) to withheld GPS fixes ``enu_xy`` at their stamps ``t``; fixes whose antenna
    time lies outside the estimate's span are left out."""
    if len(est) < 2 or len(t) == 0:
        return np.zeros(0)
    xy, inside = antenna_xy(est, t, lever_arm, delay)
    d = xy - enu_xy
    return np.hypot(d[inside, 0], d[inside, 1])


def gate_nis(est: Trajectory, t: np.ndarray, fix_xy: np.ndarray, fix_cov: np.ndarray,
             lever_arm=(0.0, 0.0), delay: float = 0.0) -> np.ndarray:
    """Normalised squared distance d^T (R + P)^-1 d of fixes ``fix_xy`` (M, 2) at ``t`` (M,)
    to the estimate's antenna (``antenna_xy``), R the fix's covariance ``fix_cov`` (M, 2, 2),
    P the estimate's position covariance at its sample nearest t - ``delay`` (R alone where P
    is missing or not positive definite): what an estimator's chi-square gate tests a fix
    with. NaN outside the estimate's span."""
    out = np.full(len(t), np.nan)
    if len(est) < 2 or len(t) == 0:
        return out
    xy, inside = antenna_xy(est, t, lever_arm, delay)
    k = np.clip(np.searchsorted(est.t, np.asarray(t, float) - delay), 1, len(est) - 1)
    k = np.where(np.abs(est.t[k - 1] - (t - delay)) <= np.abs(est.t[k] - (t - delay)), k - 1, k)
    pk = est.cov_at(k)[:, :2, :2]
    for i in np.nonzero(inside)[0]:
        r = np.asarray(fix_cov[i], float)
        p = pk[i]
        c = r + p if np.all(np.isfinite(p)) and np.linalg.eigvalsh(0.5 * (p + p.T))[0] >= 0 \
            else r
        d = xy[i] - fix_xy[i]
        out[i] = float(d @ np.linalg.solve(c, d))
    return out


def interpolation_errors(used_t: np.ndarray, used_xy: np.ndarray, t: np.ndarray,
                         xy: np.ndarray) -> np.ndarray:
    """Horizontal distance (m) from withheld fixes ``xy`` (M, 2) at ``t`` (M,) to the used fixes
    ``used_xy`` (N, 2) at ``used_t`` (N,) linearly interpolated in time: the hold-out score of
    no estimator at all, the reference a track's hold-out score is read against. Fixes outside
    the used fixes' span are left out."""
    used_t, t = np.asarray(used_t, float), np.asarray(t, float)
    if len(used_t) < 2 or len(t) == 0:
        return np.zeros(0)
    inside = (t >= used_t[0]) & (t <= used_t[-1])
    ix = np.column_stack([np.interp(t[inside], used_t, used_xy[:, 0]),
                          np.interp(t[inside], used_t, used_xy[:, 1])])
    d = ix - np.asarray(xy, float)[inside]
    return np.hypot(d[:, 0], d[:, 1])


def correlation_time(t: np.ndarray, resid: np.ndarray, max_lag: float = 120.0,
                     min_samples: int = 30) -> float | None:
    """Time (s) over which residuals ``resid`` (N, D) at stamps ``t`` (N,) stay correlated:
    the first time lag at which their autocorrelation (components pooled, each demeaned) falls
    below 1/e, linearly interpolated. The autocorrelation at lag k median intervals pairs each
    sample with the one nearest k intervals later, if within half an interval of it, so gaps
    (withheld fixes, outages) do not pair samples at the wrong lag. 0.0 when already the first
    lag is below 1/e (white); None with fewer than ``min_samples`` residuals, or when it stays
    above 1/e up to ``max_lag`` s.

    For GPS fixes minus an estimated track this is the time over which a fix's error repeats
    in its neighbours (the receiver's, where the track is good), the scale on which a
    hold-out of single fixes scores following the GPS rather than position accuracy."""
    t = np.asarray(t, float)
    if len(t) < min_samples:
        return None
    r = np.asarray(resid, float).reshape(len(t), -1)
    ok = np.isfinite(t) & np.isfinite(r).all(axis=1)
    t, r = t[ok], r[ok]
    if len(t) < min_samples:
        return None
    r = r - r.mean(axis=0)
    var = float((r * r).sum(axis=1).mean())
    dt = float(np.median(np.diff(t)))
    if var <= 0.0 or dt <= 0.0:
        return None
    threshold = math.exp(-1.0)
    prev_lag, prev_rho = 0.0, 1.0
    n = len(t)
    for k in range(1, int(max_lag / dt) + 1):
        target = t + k * dt
        j = np.clip(np.searchsorted(t, target), 1, n - 1)
        j = np.where(np.abs(t[j - 1] - target) < np.abs(t[j] - target), j - 1, j)
        pair = np.abs(t[j] - target) <= 0.5 * dt
        if pair.sum() < min_samples // 2:
            return None
        rho = float((r[pair] * r[j[pair]]).sum(axis=1).mean()) / var
        lag = k * dt
        if rho < threshold:
            if k == 1:
                return 0.0
            return prev_lag + (prev_rho - threshold) / (prev_rho - rho) * (lag - prev_lag)
        prev_lag, prev_rho = lag, rho
    return None


def path_length(xy: np.ndarray) -> float:
    """Length (m) of the polyline through the points ``xy`` (N, 2)."""
    return float(np.hypot(*np.diff(np.asarray(xy, float), axis=0).T).sum()) if len(xy) > 1 \
        else 0.0


_STEP_BLOCK = 8192  # steps rpe_pairs walks at a time


def rpe_pairs(t: np.ndarray, xy: np.ndarray, delta: float, unit: str = "s",
              all_pairs: bool = False, rel_tol: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (a, b) for the RPE, ``delta`` seconds (``unit`` 's') or path metres ('m')
    apart along stamps ``t`` (N,) / positions ``xy`` (N, 2) (unused for seconds: may be None).

    Consecutive pairs (evo's default): the first sample, then each sample at which the time or
    path since the last chosen one reaches ``delta``. All pairs: each sample with the later one
    whose distance is nearest to ``delta``, kept if within ``rel_tol * delta`` of it."""
    if unit not in RPE_UNITS:
        raise ValueError(f"RPE delta unit must be one of {RPE_UNITS}, got {unit!r}")
    if not delta > 0:
        raise ValueError(f"RPE delta must be > 0, got {delta}")
    n = len(t)
    steps = np.diff(t) if unit == "s" else np.linalg.norm(np.diff(xy, axis=0), axis=1)
    if n < 2:
        return np.zeros(0, int), np.zeros(0, int)
    if not all_pairs:
        # The running sum, reset at each chosen sample, is evo's loop, kept as a loop so that
        # the floating-point sums (and so the chosen samples) are the same as evo's.
        # (the steps made Python floats a block at a time: a 2 h track's whole list is 3 MB)
        ids, acc = [0], 0.0
        for k0 in range(0, len(steps), _STEP_BLOCK):
            for k, s in enumerate(steps[k0:k0 + _STEP_BLOCK].tolist(), start=k0 + 1):
                acc += s
                if acc >= delta:
                    ids.append(k)
                    acc = 0.0
        return np.array(ids[:-1], int), np.array(ids[1:], int)
    cum = np.concatenate([[0.0], np.cumsum(steps)])
    a = np.arange(n - 1)
    target = cum[a] + delta
    hi = np.clip(np.searchsorted(cum, target, side="left"), a + 1, n - 1)
    # The candidate below the target: the first sample holding the last value under it (evo's
    # argmin returns the first of equal distances, e.g. while the robot stands still).
    below = np.clip(np.searchsorted(cum, cum[np.maximum(hi - 1, 0)], side="left"), a + 1, n - 1)
    # Distances as evo forms them (cum[b] - cum[a], then minus delta), for the same roundings.
    d_hi, d_lo = np.abs(cum[hi] - cum[a] - delta), np.abs(cum[below] - cum[a] - delta)
    b = np.where(d_lo <= d_hi, below, hi)
    keep = np.minimum(d_lo, d_hi) <= rel_tol * delta
    return a[keep], b[keep]


def rpe(est: Trajectory, ref: Trajectory, delta: float = 1.0, max_diff: float = 0.05, *,
        unit: str = "s", all_pairs: bool = False, rel_tol: float = 0.1,
        pairs_from_reference: bool = False,
        pairs: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[Stats, Stats]:
    """Relative pose error over ``delta`` (``unit`` 's' or 'm'): translation (m) and heading
    (rad) statistics of (ref_i^-1 ref_j)^-1 (est_i^-1 est_j) over the pairs of ``rpe_pairs``
    taken on the associated samples (``pairs``: (i_est, i_ref) if the caller has them)."""
    i, j = pairs if pairs is not None else associate(est.t, ref.t, max_diff)
    if len(i) < 2:
        return Stats.of(np.zeros(0)), Stats.of(np.zeros(0))
    a, b = _rpe_index_pairs(est, ref, i, j, delta, unit, all_pairs, rel_tol,
                            pairs_from_reference)

    def rel(pose, idx):  # the poses at the chosen pairs only, not every associated one
        pa, pb = pose[idx[a]], pose[idx[b]]
        c, s = np.cos(pa[:, 2]), np.sin(pa[:, 2])
        dx, dy = pb[:, 0] - pa[:, 0], pb[:, 1] - pa[:, 1]
        return c * dx + s * dy, -s * dx + c * dy, wrap(pb[:, 2] - pa[:, 2])

    ex, ey, eyaw = rel(est.pose, i)
    rx, ry, ryaw = rel(ref.pose, j)
    # |t(E)| = |R_rel_ref^T (t_est_rel - t_ref_rel)| = |t_est_rel - t_ref_rel|.
    trans = np.hypot(ex - rx, ey - ry)
    yaw = np.abs(wrap(eyaw - ryaw))
    return Stats.of(trans), Stats.of(yaw[np.isfinite(yaw)])


def _rpe_index_pairs(est, ref, i, j, delta, unit, all_pairs, rel_tol, pairs_from_reference):
    """``rpe_pairs`` over the associated samples (i, j): indices into i and j."""
    # the positions only for path pairs (a time delta needs the stamps alone)
    src = (ref.pose[j, :2] if pairs_from_reference else est.pose[i, :2]) if unit == "m" \
        else None
    return rpe_pairs(est.t[i], src, delta, unit, all_pairs, rel_tol)


def rpe_mean_delta(est: Trajectory, ref: Trajectory, delta: float = 1.0, max_diff: float = 0.05,
                   *, unit: str = "s", all_pairs: bool = False, rel_tol: float = 0.1,
                   pairs_from_reference: bool = False,
                   pairs: tuple[np.ndarray, np.ndarray] | None = None) -> float | None:
    """The mean time (``unit`` 's') or path length ('m', on the positions the pairs are taken
    on) actually spanned by ``rpe``'s pairs (same arguments): consecutive pairs reach at least
    ``delta`` at the next sample, so a track sampled every 0.4 s has pairs 1.2 s apart for a
    1 s RPE. None without pairs."""
    i, j = pairs if pairs is not None else associate(est.t, ref.t, max_diff)
    if len(i) < 2:
        return None
    a, b = _rpe_index_pairs(est, ref, i, j, delta, unit, all_pairs, rel_tol,
                            pairs_from_reference)
    if not len(a):
        return None
    if unit == "s":
        return float(np.mean(est.t[i[b]] - est.t[i[a]]))
    src = ref.pose[j, :2] if pairs_from_reference else est.pose[i, :2]
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(src, axis=0), axis=1))])
    return float(np.mean(cum[b] - cum[a]))


@dataclass
class Outage:
    """A stretch of the run in which no GPS fix reached the estimators: [t0, t1) s."""

    t0: float
    t1: float

    def to_json(self) -> dict:
        return {"t0": self.t0, "t1": self.t1}

    @classmethod
    def from_json(cls, d: dict) -> Outage:
        return cls(d.get("t0"), d.get("t1"))


def gps_outages(t_used: np.ndarray, t_end: float, min_gap: float | None = None
                ) -> list[Outage]:
    """Gaps of at least ``min_gap`` s between the GPS fixes the estimators received (stamps
    ``t_used``, sorted), including one from the last fix to ``t_end``; the time before the first
    fix is not an outage (nothing was lost). Default ``min_gap``: max(5 s, 5 fix intervals)."""
    t = np.asarray(t_used, float)
    if len(t) < 2:
        return []
    if min_gap is None:
        min_gap = max(5.0, 5.0 * float(np.median(np.diff(t))))
    edges = np.concatenate([t, [max(t_end, t[-1])]])
    gaps = np.diff(edges)
    return [Outage(float(edges[k]), float(edges[k + 1])) for k in np.nonzero(gaps >= min_gap)[0]]


# Outage drift against withheld fixes (no truth): the fixes' own noise (sigma ~1 m at 2.5 Hz
# on the sample bag) inflates a polyline through them (121 m for a 30 m drive over 30 s) and
# a single fix is a poor start or end error. Both are taken from the fixes' medians over
# FIX_BLOCK_S instead (per axis: the noise divided by about sqrt(fixes per block), and one
# gross outlier, 20-60 m in the gps-outage scenario, moves a median little where it would
# drag a mean by metres); the robot's motion within a block stays small at walking pace.
FIX_BLOCK_S = 3.0
# variance of the median of n Gaussian samples: pi / 2 times the mean's (large n)
MEDIAN_VARIANCE = math.pi / 2.0
# consecutive block medians kept for the path at least this many of their combined noise sigmas
# apart, so that a robot standing still adds no path made of noise
FIX_BLOCK_SIGMAS = 3.0


def _fix_blocks(t: np.ndarray, block: float) -> list[np.ndarray]:
    """Index arrays of the consecutive ``block``-second stretches of stamps ``t`` (sorted)."""
    k = np.floor((t - t[0]) / block).astype(int)
    return [np.nonzero(k == v)[0] for v in np.unique(k)]


def fix_path_length(t: np.ndarray, xy: np.ndarray, cov: np.ndarray,
                    block: float = FIX_BLOCK_S, sigmas: float = FIX_BLOCK_SIGMAS) -> float:
    """Path length (m) travelled between the first and last of noisy position fixes ``xy``
    (M, 2) at ``t`` (M,) s with covariances ``cov`` (M, 2, 2) m^2, such that the fixes' noise
    does not inflate it: the polyline through the fixes' medians (per axis) over
    ``block``-second stretches, leaving out a median closer than ``sigmas`` combined sigmas to
    the last one kept (a robot standing still), then scaled from the span of the first to the
    last block's mean stamp to the span of the fixes (the half blocks at either end the
    medians do not reach). 0 for fixes within one block.

    Its error (measured against the truth's path, 1 m fixes at 2.5 Hz, ten 30 s windows each
    of 120 s runs): the sample bag -9 % to +7 % (mean -1.2 %); simulated figure-eight seed 3
    -6 % to +5 % (+0.5 %), loop-stops seed 3 -8 % to +11 % (+2.7 %), gps-outage seed 3 with
    its 20-60 m outliers -4 % to +8 % (+0.7 %). Against 4.1 times the path for the polyline
    through the fixes themselves. The noise left in the medians lengthens the path, the chords
    across turns shorten it."""
    t, xy = np.asarray(t, float), np.asarray(xy, float)
    if len(t) < 2:
        return 0.0
    var = np.asarray(cov, float)[:, [0, 1], [0, 1]].mean(axis=1)  # per axis, m^2
    idx = _fix_blocks(t, block)
    if len(idx) < 2:
        return 0.0  # one block: the noise is not averaged down, no length is resolved
    med = np.array([np.median(xy[i], axis=0) for i in idx])
    tc = np.array([t[i].mean() for i in idx])
    sd = np.sqrt(np.array([MEDIAN_VARIANCE * var[i].mean() / len(i) for i in idx]))  # per axis
    keep = [0]
    for k in range(1, len(idx)):
        j = keep[-1]
        if np.hypot(*(med[k] - med[j])) >= sigmas * math.hypot(sd[k], sd[j]):
            keep.append(k)
    span = tc[-1] - tc[0]
    return path_length(med[keep]) * (t[-1] - t[0]) / span if span > 0 else 0.0


def block_error(d: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
    """The size (m) of a position error that ``d`` (n, 2) measures n times through fixes with
    noise covariances ``cov`` (n, 2, 2): |median d| (per axis, robust to an outlier), less the
    fixes' noise in that median in the square (E|med d|^2 ~ |e|^2 + (pi/2) tr(mean cov) / n;
    clipped at 0), and that noise, the floor below which the error is not resolved."""
    noise2 = MEDIAN_VARIANCE * float(np.trace(np.asarray(cov, float).mean(axis=0))) / len(d)
    m2 = float(np.sum(np.median(np.asarray(d, float), axis=0) ** 2))
    return math.sqrt(max(m2 - noise2, 0.0)), math.sqrt(noise2)


@dataclass
class OutageDrift:
    """Error growth of one estimate over one outage.

    ``distance_m`` is the path travelled in the outage; errors (m) are at its start and end;
    ``drift_per_m`` = (end - start) / distance (m/m, x100 for % of distance travelled);
    ``reference`` is 'truth' or 'withheld GPS'. Against the truth: the truth's path, the
    errors at the first and last truth samples in the outage. Against withheld fixes: the path
    of ``fix_path_length``, the errors over the first and last ``block_s`` seconds of fixes
    (``block_error``: ``fixes_start`` / ``fixes_end`` of them, below ``error_noise_m`` not
    resolved); ``error_max_m`` is then the largest single-fix distance, noise included."""

    t0: float
    t1: float
    distance_m: float | None = None
    error_start_m: float | None = None
    error_end_m: float | None = None
    error_max_m: float | None = None
    drift_per_m: float | None = None
    samples: int | None = None
    reference: str | None = None  # None: an outage the track could not be scored over
    block_s: float | None = None
    fixes_start: int | None = None
    fixes_end: int | None = None
    error_noise_m: float | None = None

    def to_json(self) -> dict:
        """metrics.json's entry: every field, or {t0, t1, drift_per_m: None} unscored."""
        if self.reference is None:
            return {"t0": self.t0, "t1": self.t1, "drift_per_m": None}
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> OutageDrift:
        """From ``to_json``'s dictionary (an absent key: None)."""
        return cls(**{f.name: d.get(f.name) for f in fields(cls)})


def outage_drift(est: Trajectory, outage: Outage, ref_t: np.ndarray, ref_xy: np.ndarray,
                 reference: str, min_distance: float = 1.0, ref_cov: np.ndarray | None = None,
                 est_xy: np.ndarray | None = None) -> OutageDrift | None:
    """Position error of ``est`` over ``outage`` against reference positions ``ref_xy`` (M, 2)
    at ``ref_t`` (M,) s: the truth, or (``ref_cov`` (M, 2, 2) m^2 given) noisy fixes withheld
    in the outage, scored through block medians (``OutageDrift``). ``est_xy`` (M, 2): the
    estimate's positions to compare at ``ref_t`` where they are not its own (a GPS antenna's,
    ``antenna_xy``; NaN outside its span), default ``est`` interpolated. None with fewer than
    two reference samples inside both the outage and the estimate's span. ``drift_per_m`` is
    None when the path is shorter than ``min_distance`` m (a robot standing still)."""
    sel = (ref_t >= outage.t0) & (ref_t < outage.t1)
    t, xy = ref_t[sel], ref_xy[sel]
    if len(t) < 2 or len(est) < 2:
        return None
    if est_xy is None:
        exy, inside = interpolate_xy(est, t)
    else:
        exy = np.asarray(est_xy, float)[sel]
        inside = np.isfinite(exy).all(axis=1)
    if inside.sum() < 2:
        return None
    t, d = t[inside], exy[inside] - xy[inside]
    e = np.hypot(d[:, 0], d[:, 1])
    if ref_cov is None:
        dist = path_length(xy[inside])
        start, end, extra = float(e[0]), float(e[-1]), {}
    else:
        cov = np.asarray(ref_cov, float)[sel][inside]
        dist = fix_path_length(t, xy[inside], cov)
        first = t <= t[0] + FIX_BLOCK_S
        last = t >= t[-1] - FIX_BLOCK_S
        start, n0 = block_error(d[first], cov[first])
        end, n1 = block_error(d[last], cov[last])
        extra = {"block_s": FIX_BLOCK_S, "fixes_start": int(first.sum()),
                 "fixes_end": int(last.sum()), "error_noise_m": max(n0, n1)}
    drift = (end - start) / dist if dist >= min_distance else None
    return OutageDrift(outage.t0, outage.t1, dist, start, end, float(e.max()),
                       None if drift is None else float(drift), int(inside.sum()), reference,
                       **extra)
