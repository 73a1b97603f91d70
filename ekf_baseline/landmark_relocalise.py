"""A pose from one frame of landmark sightings alone: the relocalisation after a gap.

After a gap the landmark filters know their heading to no better than what the robot could
have turned (``estimation.gaps``); an EKF update linearised at such a heading collapses the
pose covariance around a wrong pose (docs/design/gaps.md). A frame of two or more range and
bearing sightings of known landmarks fixes the pose by itself: ``fit_pose`` solves for it
without the filter's linearisation point, so the filter can restart from it.

Frames and units as in ``ekf_baseline.landmark``: pose (x m, y m, psi rad) in the map frame,
a bearing in the body frame, counter-clockwise from forward x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from ddfuse.ekf_baseline.landmark_model import MIN_RANGE, range_bearing_terms
from ddfuse.estimation import chi2
from ddfuse.estimation.estimator import wrap_angle

__all__ = ["PoseFit", "fit_pose", "usable_fit", "with_common_bearing", "MIN_SIGHTINGS"]

MIN_SIGHTINGS = 2  # range-bearing sightings: with one the heading is not fixed
P_CONSISTENT = 0.999  # the residual's chi-square below this quantile: the frame agrees with itself
_MAX_ITER = 20


@dataclass(frozen=True)
class PoseFit:
    """A pose fitted to one frame's sightings.

    ``pose`` (3,) x, y, psi (wrapped to [-pi, pi)); ``cov`` (3, 3) its covariance (the inverse of
    the Gauss-Newton information at the fit); ``chi2`` the weighted squared residual, ``dof``
    its degrees of freedom (2 per sighting less 3)."""

    pose: np.ndarray
    cov: np.ndarray
    chi2: float
    dof: int

    @property
    def consistent(self) -> bool:
        """Whether the residual is within the chi-square quantile ``P_CONSISTENT`` of ``dof``
        (a misidentified landmark in the frame makes it fail)."""
        return self.chi2 <= chi2.ppf(P_CONSISTENT, self.dof)


def _initial(sight: np.ndarray) -> np.ndarray:
    """The rigid motion taking the body-frame points r (cos b, sin b) onto the landmarks
    (least squares, closed form in 2-D)."""
    body = sight[:, 2:3] * np.column_stack([np.cos(sight[:, 3]), np.sin(sight[:, 3])])
    world = sight[:, :2]
    pb, pw = body - body.mean(0), world - world.mean(0)
    h = pb.T @ pw
    psi = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    c, s = math.cos(psi), math.sin(psi)
    xy = world.mean(0) - np.array([[c, -s], [s, c]]) @ body.mean(0)
    return np.array([xy[0], xy[1], psi])


def fit_pose(sightings) -> PoseFit | None:
    """The pose that best explains ``sightings``: rows (lx, ly, range, bearing, range_var,
    bearing_var), landmark positions in the map frame (m), range (m), bearing (rad), their
    variances (m^2, rad^2).

    Weighted least squares (Gauss-Newton on the range and bearing model of
    ``landmark_model.range_bearing_terms``) from the closed-form rigid fit of the sightings.
    None when there are fewer than ``MIN_SIGHTINGS`` rows, when the landmarks are too close
    together to fix the heading (the information is singular) or when a sighting is at the
    body origin."""
    s = np.asarray(sightings, float).reshape(-1, 6)
    if len(s) < MIN_SIGHTINGS or np.any(s[:, 2] < MIN_RANGE) or np.any(s[:, 4:] <= 0.0):
        return None
    x = _initial(s)
    w = 1.0 / s[:, 4:].ravel()
    for _ in range(_MAX_ITER):
        r, J = _residual(x, s)
        info = J.T @ (w[:, None] * J)
        try:
            step = np.linalg.solve(info, J.T @ (w * r))
        except np.linalg.LinAlgError:
            return None
        x = x + step
        x[2] = wrap_angle(x[2])
        if np.max(np.abs(step)) < 1e-10:
            break
    r, J = _residual(x, s)
    info = J.T @ (w[:, None] * J)
    if np.linalg.cond(info) > 1e12:
        return None
    cov = np.linalg.inv(info)
    return PoseFit(x, 0.5 * (cov + cov.T), float(r @ (w * r)), 2 * len(s) - 3)


def _residual(x: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Measured minus predicted (range, bearing) per sighting, bearings wrapped, and the
    Jacobian of the prediction with respect to the pose, (2n,), (2n, 3)."""
    n = len(s)
    res = np.empty(2 * n)
    J = np.zeros((2 * n, 3))
    for i, (lx, ly, zr, zb, _, _) in enumerate(s):
        r, b, ar, br, aq, bq = range_bearing_terms(x[0], x[1], x[2], lx, ly)
        res[2 * i] = zr - r
        res[2 * i + 1] = wrap_angle(zb - b)
        J[2 * i] = (-ar, -br, 0.0)
        J[2 * i + 1] = (aq, -bq, -1.0)
    return res, J


AGREE_P = 0.9999  # the fit and the filter's pose, both uncertain, disagree beyond this quantile


def with_common_bearing(fit: PoseFit, common_var: float) -> PoseFit:
    """``fit`` with a bearing error common to all its sightings, of variance ``common_var``
    (rad^2; ``noise.bearing_common`` squared), added. Such an error shifts every predicted
    bearing as a heading change does (the bearing rows' Jacobian in psi is -1, the ranges' 0),
    so the fit's pose is the generalised least-squares one as it stands, its chi-square is
    unchanged, and the heading's variance grows by exactly ``common_var``."""
    if common_var <= 0.0:
        return fit
    cov = fit.cov.copy()
    cov[2, 2] += common_var
    return PoseFit(fit.pose, cov, fit.chi2, fit.dof)


def usable_fit(pose: np.ndarray, pose_cov: np.ndarray, rows,
               common_var: float = 0.0) -> PoseFit | None:
    """``fit_pose(rows)`` if the filter at ``pose`` (3,) with ``pose_cov`` (3, 3) should restart
    from it: the frame is consistent, it knows the heading better than the filter does, and it
    agrees with the filter's pose within their joint covariance (a gap's grown covariance admits
    nearly any pose; a tight one keeps a frame with a misidentified landmark out). Else None.
    ``common_var``: the variance (rad^2) of a bearing error common to the rows
    (:func:`with_common_bearing`); the rows' bearing variances are their own parts."""
    fit = fit_pose(rows)
    if fit is not None:
        fit = with_common_bearing(fit, common_var)
    if fit is None or not fit.consistent or fit.cov[2, 2] >= pose_cov[2, 2]:
        return None
    d = fit.pose - np.asarray(pose, float)
    d[2] = wrap_angle(d[2])
    try:
        m2 = float(d @ np.linalg.solve(pose_cov + fit.cov, d))
    except np.linalg.LinAlgError:
        return None
    return fit if m2 <= chi2.ppf(AGREE_P, 3) else None
