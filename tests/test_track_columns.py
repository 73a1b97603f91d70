"""Estimates appended as columns at once (the batch's whole trajectory) read back exactly as the
same estimates appended one at a time; the smoother window's gauge variance of many keyframes at
once is each keyframe's."""

import numpy as np
from ddfuse.estimation.estimator import Estimate
from ddfuse.estimation.runner import TrackBuilder
from ddfuse.estimation.smoother.window import Window


def test_columns_read_back_as_appended_estimates():
    rng = np.random.default_rng(4)
    n = 7
    t = np.cumsum(rng.uniform(0.05, 0.2, n))
    pose = rng.normal(size=(n, 3))
    a = rng.normal(size=(n, 3, 3))
    cov = a @ np.swapaxes(a, 1, 2)
    cov[2, 0, 1] += 1e-9  # one not exactly symmetric: the off-diagonals averaged, as append
    one, cols = TrackBuilder(), TrackBuilder()
    for i in range(n):
        one.append(Estimate(float(t[i]), tuple(pose[i].tolist()), cov[i]))
    last = Estimate(float(t[-1]), tuple(pose[-1].tolist()), cov[-1], np.arange(9.0))
    cols.extend_columns(t, pose, cov, last)
    a_tr, b_tr = one.trajectory(), cols.trajectory()
    assert len(cols) == n and cols.last is last
    np.testing.assert_array_equal(a_tr.t, b_tr.t)
    np.testing.assert_array_equal(a_tr.pose, b_tr.pose)
    np.testing.assert_array_equal(a_tr.cov, b_tr.cov)


def test_gauge_vars_are_each_keyframes():
    w = Window(10.0, keep_all=False, lagged=False)
    js = np.arange(0, 40)
    np.testing.assert_array_equal(w.gauge_vars(js), np.zeros(40))
    w.add_gauge(5, 2.0)
    w.add_gauge(12, 0.5)
    w.add_gauge(12, 1.0)  # two restarts at one keyframe: the later counts
    w.add_gauge(30, 4.0)
    np.testing.assert_array_equal(w.gauge_vars(js), [w.gauge_var(int(j)) for j in js])
    assert w.gauge_vars(np.array([4, 5, 11, 12, 29, 30])).tolist() == [0.0, 2.0, 2.0, 3.5, 3.5,
                                                                         7.5]
