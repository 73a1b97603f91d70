"""What the smoother outputs beyond gtsam's keyframe estimates: the filtered pose between
keyframes (``compose``: the keyframe's pose and marginal carried by the partial
preintegration) and a final state restricted to the states a run estimates
(``estimated_only``). Poses (x m, y m, psi rad) in local ENU; covariances in the world frame.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from ddfuse.estimation.estimator import Estimate
from ddfuse.factors.state import BG, DIM, HOFF, KV, NAMES


def compose(state, delta, pim_cov, pose_cov):
    """Pose of (state's pose) (+) delta and its 3x3 world-frame covariance J P J^T + R C R^T,
    with J the Jacobian of the composition wrt the keyframe pose and R the keyframe rotation;
    ``pim_cov`` (3, 3) an array or three row lists. Scalar arithmetic: called for every output
    sample."""
    x, y, psi = float(state[0]), float(state[1]), float(state[2])
    dx, dy, dp = delta
    c, s = math.cos(psi), math.sin(psi)
    a, b = -s * dx - c * dy, c * dx - s * dy  # d(position)/d psi
    p = pose_cov.tolist()
    q = pim_cov if isinstance(pim_cov, list) else pim_cov.tolist()
    # J P J^T with J = [[1, 0, a], [0, 1, b], [0, 0, 1]]
    p00 = p[0][0] + 2 * a * p[0][2] + a * a * p[2][2]
    p01 = p[0][1] + a * p[1][2] + b * p[0][2] + a * b * p[2][2]
    p02 = p[0][2] + a * p[2][2]
    p11 = p[1][1] + 2 * b * p[1][2] + b * b * p[2][2]
    p12 = p[1][2] + b * p[2][2]
    # R C R^T with R the planar rotation (the yaw row is unchanged)
    q00, q01, q11 = q[0][0], q[0][1], q[1][1]
    r00 = c * c * q00 - 2 * c * s * q01 + s * s * q11
    r01 = c * s * (q00 - q11) + (c * c - s * s) * q01
    r11 = s * s * q00 + 2 * c * s * q01 + c * c * q11
    r02 = c * q[0][2] - s * q[1][2]
    r12 = s * q[0][2] + c * q[1][2]
    cov = np.array(((p00 + r00, p01 + r01, p02 + r02),
                    (p01 + r01, p11 + r11, p12 + r12),
                    (p02 + r02, p12 + r12, p[2][2] + q[2][2])))
    return (x + c * dx - s * dy, y + s * dx + c * dy, psi + dp), cov


def estimated_only(e: Estimate | None, est_bias: bool, est_hoff: bool,
                   est_scales: bool) -> Estimate | None:
    """``e`` with its state and state covariance restricted to the pose, the twist and the
    calibration states estimated (gyro bias, heading offset, odometry scales as flagged)."""
    if e is None or e.state is None:
        return e
    keep = [i for i in range(DIM) if i < BG or (i == BG and est_bias)
            or (i == HOFF and est_hoff) or (i >= KV and est_scales)]
    cov = e.state_cov[np.ix_(keep, keep)] if e.state_cov is not None else None
    return replace(e, state=e.state[keep], state_cov=cov,
                   state_names=tuple(NAMES[i] for i in keep))
