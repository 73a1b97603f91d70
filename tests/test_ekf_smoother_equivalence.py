"""The unicycle EKF and the smoother's filtered output on the same data (issue 30, "EKF
equivalence as lag -> 0"): why they are not equal is docs/design/ekf_smoother_equivalence.md;
what is asserted here is the bound two consistent estimates of one pose must meet (the
smoother over the 120 s sample: ~4 s of CPU)."""

from __future__ import annotations

import numpy as np
from ddfuse.estimation.runner import run
from ddfuse.evaluation import estimators as registry


def test_filtered_smoother_and_ekf_agree_within_their_joint_covariance(sample_husky):
    """On the simulated sample (GPS, odometry, gyro, compass with an estimated offset) the
    position difference d of the two filtered tracks, at the smoother's 10 Hz output stamps,
    against P_ekf + P_smoother: for estimates e_i = x + n_i with errors that are not negatively
    correlated (both fuse the same measurements), Cov(d) = P_1 + P_2 - 2 C <= P_1 + P_2, so the
    mean of d^T (P_1 + P_2)^-1 d is at most its 2 dof. Measured 0.17 (95th percentile 0.65):
    the two differ by 0.039 m RMS (0.075 m at most) where each states ~0.11 m, a third of
    their own uncertainty; the models' differences that leave that much are listed in the
    design note. The smoother cannot run with lag 0 (its window would hold one keyframe);
    its filtered output is the newest keyframe's estimate with the lag's history behind it."""
    cfg, stream = sample_husky
    ests = registry.build(cfg, stream, ["ekf", "smoother"], tracks=["ekf", "smoother"])
    res = run(stream, ests)
    e, s = res.runs["ekf"].trajectory, res.runs["smoother"].trajectory
    keep = (s.t >= e.t[0]) & (s.t <= e.t[-1])
    t = s.t[keep]
    assert t.size > 1000
    d = np.stack([np.interp(t, e.t, e.pose[:, k]) - s.pose[keep, k] for k in (0, 1)], 1)
    P = s.cov[keep][:, :2, :2] + np.stack(
        [[np.interp(t, e.t, e.cov[:, i, j]) for j in (0, 1)] for i in (0, 1)]).transpose(2, 0, 1)
    maha = np.einsum("ni,ni->n", d, np.linalg.solve(P, d[:, :, None])[:, :, 0])
    assert maha.mean() < 2.0, maha.mean()
    # not a vacuous bound: they are close, not equal
    rms = float(np.sqrt(np.mean(np.sum(d * d, 1))))
    assert 1e-3 < rms < 0.1, rms
