"""A Ctrl-C can arrive between the column appends of one estimate or one fix: what was
recorded before it must still read back whole (CI saw 'cannot reshape array of size 2928 into
shape (489,6)' from an interrupted run)."""

import math

import numpy as np
from ddfuse.estimation.estimator import Estimate
from ddfuse.estimation.measurements import GpsFix
from ddfuse.estimation.runner import TrackBuilder, _GpsRecorder


def _estimate(i: int) -> Estimate:
    return Estimate(float(i), (float(i), 2.0 * i, 0.1 * i), np.diag([1.0, 2.0, 3.0]) * (i + 1))


def test_track_cut_between_columns_reads_the_complete_rows():
    tb = TrackBuilder()
    for i in range(5):
        tb.append(_estimate(i))
    # what append does before the stamp: a covariance and a pose without their stamp
    tb._cov.extend((9.0,) * 6)
    tb._pose.extend((9.0, 9.0, 9.0))
    tr = tb.trajectory()
    assert len(tb) == 5 and tr.pose.shape == (5, 3) and tr.cov.shape == (5, 3, 3)
    np.testing.assert_array_equal(tr.pose[:, 0], np.arange(5.0))
    np.testing.assert_allclose(tr.cov[4], np.diag([5.0, 10.0, 15.0]))


def test_last_estimate_not_counted_is_not_returned_for_the_last_row():
    tb = TrackBuilder()
    for i in range(3):
        tb.append(_estimate(i))
    tb.last = _estimate(7)  # as if cut after `last` was set for a row whose stamp never landed
    assert tb[-1].t == 2.0 and tb[-1].pose == (2.0, 4.0, 0.2)


def test_gps_recorder_cut_mid_fix_reads_the_complete_fixes():
    rec = _GpsRecorder()
    cov = np.diag([4.0, 4.0, 9.0])
    for i in range(4):
        f = GpsFix(float(i), 49.0, 8.0, 100.0, cov, 0, "gps")
        f.enu = np.array([float(i), -float(i), 0.0])
        rec.add(f, withheld=False)
    rec.xy.extend((math.nan, math.nan))
    rec.cov.extend([1.0] * 9)
    track = rec.track()
    assert len(track) == 4 and track.xy.shape == (4, 2) and track.cov.shape == (4, 2, 2)
    np.testing.assert_array_equal(track.xy[:, 0], np.arange(4.0))
