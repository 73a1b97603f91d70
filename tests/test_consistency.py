"""NIS/NEES consistency: chi-square bands, summaries and the Pass/Warn/Fail verdict."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.estimation.estimator import Innovation
from ddfuse.evaluation import consistency as cs


def test_chi2_band_hand_computed():
    # chi-square with 2 dof is exponential: ppf(p) = -2 ln(1 - p)
    lo, hi = cs.chi2_band(2)
    assert lo == pytest.approx(-2 * math.log(0.975)) and hi == pytest.approx(-2 * math.log(0.025))
    lo1, hi1 = cs.chi2_band(1)
    assert (lo1, hi1) == pytest.approx((0.000982069, 5.023886), rel=1e-5)
    # the band of a 50-run average is narrower and still holds the mean
    lo50, hi50 = cs.chi2_band(3, n_avg=50)
    assert cs.chi2_band(3)[0] < lo50 < 3 < hi50 < cs.chi2_band(3)[1]
    # Bar-Shalom, Li & Kirubarajan (2001), sec. 5.4: 50 runs, 3 dof -> [2.36, 3.72]
    assert (lo50, hi50) == pytest.approx((2.36, 3.72), abs=0.005)


@pytest.mark.parametrize("outside, ratio, n, expected", [
    (0.05, 1.0, 100, "Pass"), (0.10, 0.5, 100, "Pass"), (0.11, 1.0, 100, "Warn"),
    (0.05, 2.5, 100, "Warn"), (0.25, 0.25, 100, "Warn"), (0.26, 1.0, 100, "Fail"),
    (0.05, 4.1, 100, "Fail"), (0.05, 0.2, 100, "Fail"), (0.0, 1.0, 19, None),
    (0.0, float("nan"), 100, None)])
def test_verdict_thresholds(outside, ratio, n, expected):
    assert cs.verdict(outside, ratio, n) == expected


def test_summarize_consistent_overconfident_and_pessimistic():
    rng = np.random.default_rng(1)
    v = rng.chisquare(2, 4000)
    ok = cs.summarize(v, 2)
    assert ok.verdict == "Pass" and ok.outside == pytest.approx(0.05, abs=0.015)
    assert ok.ratio == pytest.approx(1.0, abs=0.05) and ok.band == pytest.approx(cs.chi2_band(2))
    over = cs.summarize(4 * v, 2)  # errors twice the stated sigma
    assert over.verdict == "Fail" and over.above > 0.3 and over.below < 0.01
    pess = cs.summarize(0.1 * v, 2)  # stated sigma three times the real one
    assert pess.verdict == "Fail" and pess.below > 0.2 and pess.ratio == pytest.approx(0.1, 0.1)
    empty = cs.summarize(np.array([np.nan]), 1)
    assert empty.n == 0 and empty.verdict is None


def test_summarize_judges_each_value_by_its_own_dimension():
    # 6.0 is above the 1-dof band (5.02) but inside the 2-dof one (7.38)
    s = cs.summarize(np.array([6.0, 6.0, 1.0, 1.0]), np.array([1, 2, 1, 2]))
    assert s.above == pytest.approx(0.25) and s.band is None and s.expected == 1.5


def _inn(t, sensor, kind, nis, m=1, accepted=True):
    return Innovation(t, sensor, kind, np.zeros(m), np.eye(m), nis, accepted)


def test_nis_by_sensor_groups_and_gate_counts():
    log = [_inn(0.1 * k, "/fix", "gps", 2.0, 2, accepted=k != 3) for k in range(30)]
    log += [_inn(0.1 * k, "/imu", "gyro", 30.0) for k in range(25)]
    log += [_inn(0.1 * k, "/imu", "heading", 1.0) for k in range(5)]
    table = cs.InnovationTable.from_innovations(log)
    assert len(table) == 60 and table.dim.tolist()[:1] == [2]
    by = cs.nis_by_sensor(table)
    assert list(by) == ["/fix gps", "/imu gyro", "/imu heading"]
    gps = by["/fix gps"]
    assert (gps.accepted, gps.rejected, gps.nis.n) == (29, 1, 30)
    assert gps.nis.verdict == "Pass"  # all at the mean (2.0), inside the band
    assert by["/imu gyro"].nis.verdict == "Fail" and by["/imu gyro"].nis.above == 1.0
    assert by["/imu heading"].nis.verdict is None  # 5 values: too few to judge
    assert by["/fix gps"].as_dict()["accepted"] == 29


def test_groups_are_in_order_of_first_appearance_and_partition_the_log():
    pairs = [("/imu", "heading"), ("/fix", "gps"), ("/imu", "gyro"), ("/fix", "gps"),
             ("/imu", "heading"), ("/odom", "v"), ("/imu", "gyro"), ("/odom", "w")] * 3
    table = cs.InnovationTable.from_innovations(
        [_inn(0.1 * k, s, kind, 1.0) for k, (s, kind) in enumerate(pairs)])
    groups = table.groups()
    assert list(groups) == ["/imu heading", "/fix gps", "/imu gyro", "/odom v", "/odom w"]
    for label, mask in groups.items():
        assert mask.tolist() == [f"{s} {kind}" == label for s, kind in pairs], label
    assert sum(m.astype(int) for m in groups.values()).tolist() == [1] * len(pairs)


def test_average_nees_over_runs():
    runs = [np.array([1.0, 2.0, 3.0]), np.array([3.0, 4.0]), np.array([2.0, 3.0, 9.0, 9.0])]
    np.testing.assert_allclose(cs.average_nees(runs), [2.0, 3.0])
    assert len(cs.average_nees([])) == 0


def test_gate_rejected_outliers_count_outside_the_band_but_not_in_the_mean():
    """A consistent filter whose gate rejects 2 % gross GPS outliers (NIS ~1600, 40 sigma)
    passes: those count as outside the band, not in the mean, which they would otherwise
    raise ~17-fold. A filter whose gate rejects 30 % of its fixes fails on the fraction."""
    rng = np.random.default_rng(1)
    nis = rng.chisquare(2, 1000)
    outlier = np.zeros(1000, bool)
    outlier[::50] = True
    nis[outlier] = 1600.0
    ok = cs.summarize(nis, 2, ~outlier)
    assert ok.verdict == "Pass", ok
    assert ok.ratio == pytest.approx(1.0, abs=0.1)
    assert ok.above >= 0.02
    assert cs.summarize(nis, 2).ratio > 10  # without the gate's decisions
    wrong = rng.chisquare(2, 1000)
    rejected = np.zeros(1000, bool)
    rejected[::3] = True
    wrong[rejected] = 50.0
    bad = cs.summarize(wrong, 2, ~rejected)
    assert bad.verdict == "Fail" and bad.above > 0.3
    table = cs.InnovationTable.from_innovations(
        [_inn(0.1 * k, "/fix", "gps", float(v), 2, accepted=not o)
         for k, (v, o) in enumerate(zip(nis, outlier, strict=True))])
    gps = cs.nis_by_sensor(table)["/fix gps"]
    assert (gps.rejected, gps.nis.verdict) == (20, "Pass")
