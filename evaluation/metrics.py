"""Trajectory metrics: pure math on arrays, no I/O or plotting (evo's core/metrics split).

Trajectories are ``estimation.runner.Trajectory``: ``t`` (N,) s, ``pose`` (N, 3) as
(x m, y m, yaw rad) in the local frame, ``cov`` (N, 3, 3). Association follows evo: each
estimate is paired with the reference sample nearest in time, if within ``max_diff`` seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimation.runner import Trajectory


def wrap(a):
    """Wrap angles (rad) to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def associate(t_est: np.ndarray, t_ref: np.ndarray, max_diff: float) -> tuple[np.ndarray, ...]:
    """Indices (i_est, i_ref) of pairs whose stamps differ by at most ``max_diff`` s; each
    estimate takes its nearest reference sample. ``t_ref`` must be sorted."""
    if len(t_est) == 0 or len(t_ref) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    j = np.clip(np.searchsorted(t_ref, t_est), 1, len(t_ref) - 1)
    left_closer = np.abs(t_est - t_ref[j - 1]) <= np.abs(t_ref[j] - t_est)
    j = np.where(left_closer, j - 1, j)
    ok = np.abs(t_ref[j] - t_est) <= max_diff
    return np.nonzero(ok)[0], j[ok]


@dataclass
class Stats:
    """Statistics of an error series (units of the series)."""

    rmse: float
    mean: float
    median: float
    std: float
    max: float
    n: int

    @classmethod
    def of(cls, e: np.ndarray) -> Stats:
        e = np.asarray(e, float)
        if e.size == 0:
            nan = math.nan
            return cls(nan, nan, nan, nan, nan, 0)
        return cls(float(np.sqrt(np.mean(e * e))), float(np.mean(e)), float(np.median(e)),
                   float(np.std(e)), float(np.max(e)), int(e.size))


@dataclass
class PoseErrors:
    """Per-sample errors of an estimate against a reference, at the associated stamps."""

    t: np.ndarray  # (M,) s
    dxy: np.ndarray  # (M, 2) m, estimate - reference
    dyaw: np.ndarray  # (M,) rad, wrapped; NaN where the reference has no yaw
    i_est: np.ndarray  # indices into the estimate

    @property
    def position(self) -> np.ndarray:
        return np.hypot(self.dxy[:, 0], self.dxy[:, 1])


def pose_errors(est: Trajectory, ref: Trajectory, max_diff: float = 0.05) -> PoseErrors:
    """Errors of ``est`` against ``ref`` with no alignment (both in the run's local frame)."""
    i, j = associate(est.t, ref.t, max_diff)
    dxy = est.pose[i, :2] - ref.pose[j, :2]
    dyaw = wrap(est.pose[i, 2] - ref.pose[j, 2])
    return PoseErrors(est.t[i], dxy, dyaw, i)


def ate(est: Trajectory, ref: Trajectory, max_diff: float = 0.05) -> Stats:
    """Absolute position error (m) statistics, no alignment."""
    return Stats.of(pose_errors(est, ref, max_diff).position)


def nees(est: Trajectory, ref: Trajectory, max_diff: float = 0.05) -> np.ndarray:
    """Pose NEES e^T P^-1 e per associated sample (3 dof; 2 where the reference has no yaw).

    Samples whose covariance is missing or not positive definite are left out."""
    return nees_samples(est, ref, max_diff)[1]


def nees_samples(est: Trajectory, ref: Trajectory, max_diff: float = 0.05
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``nees`` with the indices into ``est`` of the samples it could score: (i_est, nees)."""
    err = pose_errors(est, ref, max_diff)
    idx, out = [], []
    for k, i in enumerate(err.i_est):
        p = est.cov[i]
        if math.isnan(err.dyaw[k]):
            e, p = err.dxy[k], p[:2, :2]
        else:
            e = np.array([err.dxy[k, 0], err.dxy[k, 1], err.dyaw[k]])
        if not np.all(np.isfinite(p)):
            continue
        try:
            c = np.linalg.cholesky(0.5 * (p + p.T))
        except np.linalg.LinAlgError:
            continue
        z = np.linalg.solve(c, e)
        idx.append(int(i))
        out.append(float(z @ z))
    return np.array(idx, dtype=np.int64), np.array(out)


def interpolate_xy(est: Trajectory, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linearly interpolated (x, y) of ``est`` at ``t`` and a mask of stamps inside its span."""
    inside = (t >= est.t[0]) & (t <= est.t[-1]) if len(est) else np.zeros(len(t), bool)
    xy = np.column_stack([np.interp(t, est.t, est.pose[:, 0]),
                          np.interp(t, est.t, est.pose[:, 1])]) if len(est) else np.zeros((0, 2))
    return xy, inside


def holdout_errors(est: Trajectory, t: np.ndarray, enu_xy: np.ndarray) -> np.ndarray:
    """Horizontal distance (m) from the estimate to withheld GPS fixes at their stamps."""
    if len(est) < 2 or len(t) == 0:
        return np.zeros(0)
    xy, inside = interpolate_xy(est, t)
    d = xy - enu_xy
    return np.hypot(d[inside, 0], d[inside, 1])


def rpe(est: Trajectory, ref: Trajectory, delta: float = 1.0, max_diff: float = 0.05
        ) -> tuple[Stats, Stats]:
    """Relative pose error over a time delta (s): translation (m) and heading (rad) statistics
    of (ref_i^-1 ref_j)^-1 (est_i^-1 est_j) for pairs about ``delta`` apart."""
    i, j = associate(est.t, ref.t, max_diff)
    if len(i) < 2:
        return Stats.of(np.zeros(0)), Stats.of(np.zeros(0))
    te, pe, pr = est.t[i], est.pose[i], ref.pose[j]
    k2 = np.searchsorted(te, te + delta)
    ok = k2 < len(te)
    a, b = np.nonzero(ok)[0], k2[ok]

    def rel(p):
        c, s = np.cos(p[a, 2]), np.sin(p[a, 2])
        dx, dy = p[b, 0] - p[a, 0], p[b, 1] - p[a, 1]
        return c * dx + s * dy, -s * dx + c * dy, wrap(p[b, 2] - p[a, 2])

    ex, ey, eyaw = rel(pe)
    rx, ry, ryaw = rel(pr)
    trans = np.hypot(ex - rx, ey - ry)
    yaw = np.abs(wrap(eyaw - ryaw))
    yaw = yaw[np.isfinite(yaw)]
    return Stats.of(trans), Stats.of(yaw)
