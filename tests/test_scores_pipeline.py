"""pipeline.score on hand-made runs: which fixes, stamps and spans every track is scored on."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from ddfuse.estimation.estimator import EstimatorLog
from ddfuse.estimation.measurements import Stream
from ddfuse.estimation.runner import EstimatorRun, GpsTrack, RunResult, Trajectory
from ddfuse.evaluation.pipeline import score
from ddfuse.evaluation.verdict import verdict_lines

SPEED = 1.0  # m/s along a circle of radius 20 m


def _pose(t: np.ndarray) -> np.ndarray:
    a = SPEED * t / 20.0
    return np.column_stack([20.0 * np.sin(a), 20.0 * (1.0 - np.cos(a)), np.arctan2(
        np.sin(a), np.cos(a))])


def _track(t, err=0.0, sigma=0.1) -> Trajectory:
    """The true drive at stamps ``t`` moved ``err`` m (scalar or per stamp) along y."""
    t = np.asarray(t, float)
    pose = _pose(t)
    pose[:, 1] += err
    return Trajectory(t, pose, np.tile(np.diag([sigma**2, sigma**2, 1e-4]), (len(t), 1, 1)))


def _result(tracks: dict[str, Trajectory], fix_t, fix_xy, withheld, truth=None,
            sigma=1.0, t1=120.0) -> RunResult:
    fix_t = np.asarray(fix_t, float)
    runs = {n: EstimatorRun(n, tr, np.zeros(1, np.float32), 0.0, EstimatorLog())
            for n, tr in tracks.items()}
    gps = GpsTrack(fix_t, np.asarray(fix_xy, float),
                   np.tile(np.eye(2) * sigma**2, (len(fix_t), 1, 1)), np.asarray(withheld, bool))
    return RunResult(Stream([], t0=0.0, t1=t1), runs, gps, truth)


def test_tracks_without_a_common_withheld_fix_are_not_ranked_on_their_own_ones():
    """ekf ends at 50 s, ekf_igvc starts at 60 s: no withheld fix lies in both spans. Each
    could only be scored on its own fixes (different things), so neither gets a hold-out
    score and the verdict ranks nothing and says why."""
    rng = np.random.default_rng(0)
    fix_t = np.arange(0.0, 120.0, 0.4)
    fix_xy = _pose(fix_t)[:, :2] + rng.normal(0.0, 1.0, (len(fix_t), 2))
    withheld = np.arange(len(fix_t)) % 5 == 0
    tracks = {"ekf": _track(np.arange(0.0, 50.0, 0.1)),
              "ekf_igvc": _track(np.arange(60.0, 120.0, 0.1), err=3.0)}
    m = replace(score(_result(tracks, fix_t, fix_xy, withheld)), gps_holdout="every:5")
    assert m.gps_holdout_fixes == withheld.sum() and m.gps_holdout_scored_fixes == 0
    for n, tr in tracks.items():
        e = m.estimators[n]
        assert e.gps_holdout_rmse_m is None
        own = withheld & (fix_t >= tr.t[0]) & (fix_t <= tr.t[-1])
        assert e.gps_holdout_m.n == own.sum()
        assert e.gps_holdout_span_s == pytest.approx([tr.t[0], tr.t[-1]])
    lines = verdict_lines(m)
    assert lines[0].startswith("No score: the bag has no ground truth, and none of the")
    assert "lies inside every estimator's span" in lines[0] and "not comparable" in lines[0]
    assert not any(line.startswith("Best here") for line in lines)
    # one common fix is enough to rank on it (and only on it)
    tracks["ekf_igvc"] = _track(np.arange(47.5, 120.0, 0.1), err=3.0)
    m = score(_result(tracks, fix_t, fix_xy, withheld))
    common = withheld & (fix_t >= 47.5) & (fix_t <= tracks["ekf"].t[-1])
    assert m.gps_holdout_scored_fixes == common.sum() > 0
    assert all(e.gps_holdout_m.n == common.sum() for e in m.estimators.values())


def _truth(t1=120.0) -> Trajectory:
    return _track(np.arange(0.0, t1 + 1e-9, 0.05))


def test_the_ranking_is_over_the_common_span_and_a_late_start_is_stated():
    """'late' starts at 10 s, after 'early's worst seconds (2 m off, then 0.1 m): over its own
    span 'late' (0.3 m throughout) scores better, but over the span both have, 'early' is
    better. The verdict ranks on the common span and says who started later by how much."""
    t = np.arange(0.0, 120.0, 0.1)
    early = _track(t, np.where(t < 10.0, 2.0, 0.1))
    late = _track(t[t >= 10.0], 0.3)
    m = score(_result({"early": early, "late": late}, [], np.zeros((0, 2)), [],
                      truth=_truth()))
    e = m.estimators
    assert e["late"].ate_rmse_m < e["early"].ate_rmse_m  # own spans: late is better
    # the common span [10, 119.9] s: constant offsets of 0.1 and 0.3 m
    assert m.ate_common.span_s == pytest.approx([10.0, t[-1]])
    assert e["early"].ate_common_rmse_m == pytest.approx(0.1, abs=1e-6)
    assert e["late"].ate_common_rmse_m == pytest.approx(0.3, abs=1e-6)
    lines = verdict_lines(m)
    assert lines[1] == "Best here: early with 0.100 m."
    assert any(line.startswith("late starts 10.0 s after the first track (at 10.0 s): every "
                               "track is ranked from 10.0 s") for line in lines)
    assert any("there late is best, not early" in line for line in lines)


def test_a_track_that_stopped_early_is_not_ranked_and_cuts_no_span():
    """'broken' stopped at 20 s with an error (0.1 m off until then); 'steady' is 0.05 m off
    for those 20 s and 1 m after, 'other' 0.5 m throughout. On its own span 'broken' scores
    best, and a common span cut to its 20 s would rank 'steady' first on its best seconds.
    The stopped track is left out of the ranking, which covers the whole run."""
    t = np.arange(0.0, 120.0, 0.1)
    broken = _track(t[t < 20.0], 0.1)
    steady = _track(t, np.where(t < 20.0, 0.05, 1.0))
    other = _track(t, 0.5)
    res = _result({"broken": broken, "steady": steady, "other": other}, [],
                  np.zeros((0, 2)), [], truth=_truth())
    res.runs["broken"].error = "RuntimeError at t=20: boom"
    m = score(res)
    e = m.estimators
    assert e["broken"].ate_rmse_m < e["other"].ate_rmse_m < e["steady"].ate_rmse_m
    assert m.ate_common.span_s == pytest.approx([0.0, t[-1]])
    assert e["broken"].ate_common_rmse_m is None
    lines = verdict_lines(m)
    assert lines[1] == "Best here: other with 0.500 m."
    assert "Not ranked, having stopped with an error (said below): broken." in lines[0]
    assert any(line.startswith("broken stopped early: RuntimeError") for line in lines)
    assert not any("ranked only up to" in line for line in lines)


def test_holdout_scores_the_antenna_with_the_configured_lever_arm_and_delay():
    """Noise-free fixes of an antenna 0.5 m ahead and 0.2 m left of the base, stamped 0.2 s
    late (the sample config's delay): a track exactly on the truth scores the lever arm (or
    the motion over the delay) unless the fix is compared with its antenna at t - delay."""
    import copy
    from pathlib import Path

    from ddfuse.estimation.config import load_config

    cfg = copy.deepcopy(load_config(Path(__file__).parent.parent / "data" / "sample_husky.yaml"))
    gps = next(s for s in cfg.sensors if s.kind == "gps")
    gps.lever_arm, gps.delay = (0.5, 0.2), 0.2
    fix_t = np.arange(1.0, 119.0, 0.4)
    p = _pose(fix_t - gps.delay)  # the antenna when the fix was taken
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    fix_xy = p[:, :2] + np.column_stack([0.5 * c - 0.2 * s, 0.5 * s + 0.2 * c])
    exact = _track(np.arange(0.0, 120.0, 0.1))
    res = _result({"exact": exact, "other": _track(exact.t, 0.3)}, fix_t, fix_xy,
                  np.ones(len(fix_t), bool))
    m = score(res, cfg=cfg)
    assert m.gps_antenna.lever_arm == (0.5, 0.2) and m.gps_antenna.delay_s == 0.2
    # the track's linear interpolation between 0.1 s samples on a 20 m circle: v^2 dt^2 / 8 R
    # of sag, and as much again from the yaw's
    assert m.estimators["exact"].gps_holdout_rmse_m < 2 * (SPEED * 0.1) ** 2 / (8 * 20.0)
    assert m.estimators["other"].gps_holdout_rmse_m == pytest.approx(0.3, abs=1e-3)
    # without the model (no config) the exact track scores the lever arm less the 0.2 m
    # driven over the delay along the heading: |(0.5 - 0.2, 0.2)|
    bare = score(res)
    assert bare.gps_antenna.note.startswith("no config")
    assert bare.estimators["exact"].gps_holdout_rmse_m == pytest.approx(
        math.hypot(0.5 - SPEED * 0.2, 0.2), abs=5e-3)


def test_a_gross_gps_error_no_track_comes_near_is_left_out_for_every_track():
    """One withheld fix 30 m off (multipath) would dominate every track's RMSE alike. Withheld
    fixes that every track's chi-square gate rejects (the fix's and the track's own
    covariance) and that the used fixes on either side reject too are left out for all and
    counted; a track that drifted with a covariance to match keeps them. In an outage (no used
    fix near) nothing is left out, however far every track has drifted."""
    from scipy.stats import chi2

    rng = np.random.default_rng(5)
    fix_t = np.arange(1.0, 119.0, 0.4)
    fix_xy = _pose(fix_t)[:, :2] + rng.normal(0.0, 1.0, (len(fix_t), 2))
    fix_xy[100, 0] += 30.0
    withheld = np.arange(len(fix_t)) % 5 == 0  # fix 100 among them
    t = np.arange(0.0, 120.0, 0.1)
    tracks = {"good": _track(t, 0.0), "fair": _track(t, 0.3),
              "drifted": _track(t, 6.0, sigma=5.0)}  # 6 m off, and says so
    m = score(_result(tracks, fix_t, fix_xy, withheld))
    # independently: the withheld fixes every track's gate (R + P, the default 0.9999)
    # rejects, and the mean of the two used fixes beside them (R + R / 2) rejects
    limit = chi2.ppf(m.gps_antenna.gate, 2)
    rejected = withheld.copy()
    for tr in tracks.values():
        d = tr.pose[np.searchsorted(tr.t, fix_t), :2] - fix_xy
        rejected &= np.sum(d * d, axis=1) / (1.0 + tr.cov[0, 0, 0]) > limit
    i = np.flatnonzero(withheld)
    between = 0.5 * (fix_xy[np.maximum(i - 1, 0)] + fix_xy[np.minimum(i + 1, len(fix_t) - 1)])
    rejected[i] &= np.sum((fix_xy[i] - between) ** 2, axis=1) / 1.5 > limit
    assert np.flatnonzero(rejected).tolist() == [100]
    held = withheld.sum()
    assert m.gps_holdout_outliers == 1 and m.gps_holdout_scored_fixes == held - 1
    for n, tr in tracks.items():
        d = (tr.pose[np.searchsorted(tr.t, fix_t), :2] - fix_xy)[withheld & ~rejected]
        want = math.sqrt(np.mean(np.sum(d * d, axis=1)))
        assert m.estimators[n].gps_holdout_rmse_m == pytest.approx(want, abs=1e-5)
    m = replace(m, gps_holdout="every:5")
    assert "1 withheld fix that no estimator comes near" in verdict_lines(m)[0]
    # a 30 s outage over which every track drifts to 20 m with a sigma of 1 m: its fixes are
    # what the score is for, none is left out
    outage = (fix_t >= 40.0) & (fix_t < 70.0)
    far = {n: _track(t, np.where((t >= 40.0) & (t < 70.0), 20.0, 0.1)) for n in ("a", "b")}
    m = score(_result(far, fix_t, _pose(fix_t)[:, :2], outage))
    assert m.gps_holdout_outliers == 0 and m.gps_holdout_scored_fixes == outage.sum()


def test_the_interpolation_reference_leaves_out_gross_errors_among_the_used_fixes():
    """The no-estimator reference interpolates the used fixes: one 30 m used fix would put
    about 15 m on each withheld fix beside it. Used fixes that every track's gate and their
    two neighbours reject are left out of it and counted; a drift every track shares in an
    outage is not (no neighbours near)."""
    rng = np.random.default_rng(7)
    fix_t = np.arange(1.0, 119.0, 0.4)
    fix_t = np.delete(fix_t, [52, 53])  # a dropout after a withheld fix: a 1.2 s used gap
    fix_xy = _pose(fix_t)[:, :2] + rng.normal(0.0, 1.0, (len(fix_t), 2))
    withheld = np.arange(len(fix_t)) % 5 == 0
    bad = [51, 101]  # used fixes; 51 has the dropout after it
    assert not withheld[bad].any()
    fix_xy[bad, 1] -= 30.0
    t = np.arange(0.0, 120.0, 0.1)
    tracks = {"good": _track(t, 0.0), "fair": _track(t, 0.3)}
    m = score(_result(tracks, fix_t, fix_xy, withheld))
    assert m.gps_holdout_interpolation_outliers == 2
    keep = ~withheld
    keep[bad] = False
    held = withheld & (fix_t > fix_t[keep][0]) & (fix_t < fix_t[keep][-1])

    def rmse(keep):
        ix = np.column_stack([np.interp(fix_t[held], fix_t[keep], fix_xy[keep, k])
                              for k in (0, 1)])
        return math.sqrt(np.mean(np.sum((ix - fix_xy[held]) ** 2, axis=1)))

    want = rmse(keep)
    assert want < 2.0
    assert m.gps_holdout_interpolation_rmse_m == pytest.approx(want, abs=1e-5)
    # without the test: every used fix interpolated, the 30 m fixes included
    assert rmse(~withheld) > 1.5 * want


def test_position_only_truth_gives_no_rpe_rather_than_nulls_with_a_pair_count():
    """A NavSatFix ground truth has no heading: the RPE's relative poses cannot be formed.
    The track's RPE is left out with the reason; its ATE is still scored."""
    t = np.arange(0.0, 60.0, 0.1)
    truth = _track(np.arange(0.0, 60.0, 0.2))
    truth.pose[:, 2] = np.nan
    m = score(_result({"ekf": _track(t, 0.2)}, [], np.zeros((0, 2)), [], truth=truth, t1=60.0))
    e = m.estimators["ekf"]
    assert e.ate_rmse_m == pytest.approx(0.2, abs=1e-6)
    assert e.rpe is None and e.rpe_rmse_m is None
    assert "no heading" in e.rpe_note
    # with the truth's heading the RPE is there, with finite values for every pair it counts
    truth.pose[:, 2] = _pose(truth.t)[:, 2]
    e = score(_result({"ekf": _track(t, 0.2)}, [], np.zeros((0, 2)), [], truth=truth,
                      t1=60.0)).estimators["ekf"]
    assert e.rpe["1s"].position_m.n > 0 and e.rpe_rmse_m is not None


def test_the_path_length_from_gps_fixes_is_not_their_noise(sample_husky):
    """Without truth the report's path length comes from the fixes: a polyline through the
    1 m fixes at 2.5 Hz was 561 m for the sample bag's 117 m drive."""
    from dataclasses import replace as _replace

    from ddfuse.estimation.runner import run
    from ddfuse.evaluation import metrics
    from ddfuse.evaluation.pipeline import data_facts

    cfg, stream = sample_husky
    res = run(stream, {})
    truth_m = metrics.path_length(res.truth.pose[:, :2])
    res.truth = None
    facts = data_facts(res, _replace(cfg, ground_truth_topic=None), surveys=[])
    assert facts.path_length_from == "GPS fixes"
    assert facts.path_length_m == pytest.approx(truth_m, rel=0.1)


def test_holdout_nees_tells_a_lucky_track_from_a_calibrated_one():
    """Two tracks 3 m off the withheld fixes (exact, stated at 1 m): the same hold-out RMSE,
    but one claims 0.1 m and the other 2.5 m. The hold-out NEES is d' (P + R)^-1 d per fix:
    9 / 1.01 (over-confident: Fail) and 9 / 7.25 (inside the 2-dof band: Pass)."""
    fix_t = np.arange(0.0, 120.0, 0.4)
    fix_xy = _pose(fix_t)[:, :2]
    withheld = np.arange(len(fix_t)) % 5 == 0
    t = np.arange(0.0, 120.0, 0.1)
    tracks = {"tight": _track(t, err=3.0, sigma=0.1), "wide": _track(t, err=3.0, sigma=2.5)}
    m = score(_result(tracks, fix_t, fix_xy, withheld))
    tight, wide = m.estimators["tight"], m.estimators["wide"]
    assert tight.gps_holdout_rmse_m == pytest.approx(wide.gps_holdout_rmse_m) == \
        pytest.approx(3.0, abs=1e-6)
    assert tight.gps_holdout_nees.n == wide.gps_holdout_nees.n == m.gps_holdout_scored_fixes
    assert tight.gps_holdout_nees.mean == pytest.approx(9.0 / 1.01, rel=1e-4)
    assert wide.gps_holdout_nees.mean == pytest.approx(9.0 / 7.25, rel=1e-4)
    assert tight.gps_holdout_nees.verdict == "Fail" and tight.gps_holdout_nees.above == 1.0
    assert wide.gps_holdout_nees.verdict == "Pass"
    # written and read back with the run's metrics
    back = type(m).from_json(m.to_json())
    assert back.estimators["tight"].gps_holdout_nees == tight.gps_holdout_nees


def test_no_holdout_no_holdout_nees():
    t = np.arange(0.0, 60.0, 0.1)
    m = score(_result({"ekf": _track(t)}, [], np.zeros((0, 2)), [], truth=_truth(60.0)))
    assert m.estimators["ekf"].gps_holdout_nees is None
