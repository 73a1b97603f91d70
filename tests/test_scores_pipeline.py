"""pipeline.score on hand-made runs: which fixes, stamps and spans every track is scored on."""

from __future__ import annotations

import numpy as np
import pytest

from estimation.estimator import EstimatorLog
from estimation.measurements import Stream
from estimation.runner import EstimatorRun, GpsTrack, RunResult, Trajectory
from evaluation.pipeline import score
from evaluation.verdict import verdict_lines

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
    m = score(_result(tracks, fix_t, fix_xy, withheld))
    m["gps_holdout"] = "every:5"
    assert m["gps_holdout_fixes"] == withheld.sum() and m["gps_holdout_scored_fixes"] == 0
    for n, tr in tracks.items():
        e = m["estimators"][n]
        assert e["gps_holdout_rmse_m"] is None
        own = withheld & (fix_t >= tr.t[0]) & (fix_t <= tr.t[-1])
        assert e["gps_holdout_m"]["n"] == own.sum()
        assert e["gps_holdout_span_s"] == pytest.approx([tr.t[0], tr.t[-1]])
    lines = verdict_lines(m)
    assert lines[0].startswith("No score: the bag has no ground truth, and none of the")
    assert "lies inside every estimator's span" in lines[0] and "not comparable" in lines[0]
    assert not any(line.startswith("Best here") for line in lines)
    # one common fix is enough to rank on it (and only on it)
    tracks["ekf_igvc"] = _track(np.arange(47.5, 120.0, 0.1), err=3.0)
    m = score(_result(tracks, fix_t, fix_xy, withheld))
    common = withheld & (fix_t >= 47.5) & (fix_t <= tracks["ekf"].t[-1])
    assert m["gps_holdout_scored_fixes"] == common.sum() > 0
    assert all(e["gps_holdout_m"]["n"] == common.sum() for e in m["estimators"].values())
