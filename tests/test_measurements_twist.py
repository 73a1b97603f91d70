"""WheelSpeeds.twist: the one conversion of left/right wheel speeds to (v, yaw rate) that the
smoother, the landmark EKF, dead reckoning and the live forecast share."""

from __future__ import annotations

import numpy as np
from ddfuse.estimation.measurements import WheelSpeeds


def test_twist_matches_the_kinematics_and_the_sampled_variances():
    r, L = 0.165, 0.555
    m = WheelSpeeds(t=0.0, left=3.0, right=5.0, left_var=0.04, right_var=0.09)
    v, w, v_var, w_var = m.twist(r, L)
    assert np.isclose(v, r * 4.0) and np.isclose(w, r * 2.0 / L)
    rng = np.random.default_rng(3)
    n = 200_000
    left = m.left + rng.normal(0.0, np.sqrt(m.left_var), n)
    right = m.right + rng.normal(0.0, np.sqrt(m.right_var), n)
    vs, ws = 0.5 * r * (left + right), r * (right - left) / L
    # sample variances of 2e5 draws are within ~1 % (4 standard errors: 4 * sqrt(2/n) = 1.3 %)
    assert abs(vs.var() / v_var - 1.0) < 0.013
    assert abs(ws.var() / w_var - 1.0) < 0.013
