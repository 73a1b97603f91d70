"""Scores walked a block of associated pairs at a time (ddfuse.evaluation.pair_scores,
metrics.nees_series(block=)) equal the whole-track ones, whatever the block size."""

from __future__ import annotations

import numpy as np
import pytest
from ddfuse.estimation.estimator import Estimate
from ddfuse.estimation.runner import TrackBuilder, Trajectory
from ddfuse.evaluation import metrics, pair_scores

BLOCKS = (1, 7, 100, 10**6)  # 10**6: one block longer than the track


def _random_tracks(seed: int, n: int = 400, yaw_nan: bool = False):
    """A truth at 20 Hz and an estimate at ~10 Hz with jittered stamps, noisy poses and
    random positive definite covariances (some NaN, some singular), the estimate packed as a
    run holds it."""
    rng = np.random.default_rng(seed)
    tt = np.arange(2 * n) * 0.05 + 1.7e9
    truth_pose = np.column_stack([np.cumsum(rng.normal(0.05, 0.02, 2 * n)),
                                  np.cumsum(rng.normal(0.0, 0.05, 2 * n)),
                                  metrics.wrap(np.cumsum(rng.normal(0.0, 0.1, 2 * n)))])
    if yaw_nan:
        truth_pose[:, 2] = np.nan
    truth = Trajectory(tt, truth_pose, np.full((2 * n, 3, 3), np.nan))
    te = tt[::2] + rng.uniform(-0.03, 0.03, n)
    te.sort()
    b = TrackBuilder()
    for k, t in enumerate(te):
        a = rng.normal(size=(3, 3)) * 0.3
        cov = a @ a.T + 1e-3 * np.eye(3)
        if k % 37 == 5:
            cov = np.full((3, 3), np.nan)
        elif k % 41 == 3:
            cov = np.zeros((3, 3))
        x = np.interp(t, tt, truth_pose[:, 0]) + rng.normal(0, 0.3)
        y = np.interp(t, tt, truth_pose[:, 1]) + rng.normal(0, 0.3)
        b.append(Estimate(float(t), (float(x), float(y), float(rng.uniform(-np.pi, np.pi))),
                          cov))
    return b.trajectory(), truth


def _eq(a: metrics.Stats, b: metrics.Stats) -> None:
    assert a.n == b.n
    np.testing.assert_array_equal(
        [a.rmse, a.mean, a.median, a.std, a.min, a.max], [b.rmse, b.mean, b.median, b.std,
                                                          b.min, b.max])


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("block", BLOCKS)
@pytest.mark.parametrize("align", ["none", "se2", "origin"])
def test_ape_by_blocks_equals_whole_track(seed, block, align):
    est, truth = _random_tracks(seed)
    i, j = metrics.associate(est.t, truth.t, 0.05)
    assert len(i) > 300
    whole = metrics.ape(est, truth, 0.05, align)
    pos, head = pair_scores.ape_stats(est, truth, i, j, align, block=block)
    _eq(pos, whole.position)
    _eq(head, whole.heading)


@pytest.mark.parametrize("block", BLOCKS)
def test_association_error_by_blocks_equals_whole_track(block):
    est, truth = _random_tracks(2)
    i, j = metrics.associate(est.t, truth.t, 0.05)
    _eq(pair_scores.association_stats(est, truth, i, j, block=block),
        metrics.association_error(est, truth, 0.05))


@pytest.mark.parametrize("yaw_nan", [False, True])
@pytest.mark.parametrize("pose_error", ["world", "se2"])
def test_nees_by_blocks_equals_whole_track(pose_error, yaw_nan):
    est, truth = _random_tracks(3, yaw_nan=yaw_nan)
    whole = metrics.nees_series(est, truth, 0.05, pose_error, block=10**6)
    # the samples with a NaN or singular covariance are left out, the rest scored
    assert 0 < len(whole.value) < len(metrics.associate(est.t, truth.t, 0.05)[0])
    pairs = metrics.associate(est.t, truth.t, 0.05)
    for block in BLOCKS[:-1]:
        part = metrics.nees_series(est, truth, 0.05, pose_error, pairs=pairs, block=block)
        for f in ("t", "value", "dof", "i_est"):
            np.testing.assert_array_equal(getattr(part, f), getattr(whole, f))


def test_nees_matches_a_direct_computation():
    # the world-frame NEES of one sample by hand: e^T P^-1 e
    est, truth = _random_tracks(4, n=40)
    ns = metrics.nees_series(est, truth, 0.05, "world", block=3)
    k = 5
    i = int(ns.i_est[k])
    ref = metrics.reference_at(truth, est.t[i:i + 1],
                               metrics.associate(est.t[i:i + 1], truth.t, 0.05)[1], 0.05)[0]
    e = est.pose[i] - ref
    e[2] = metrics.wrap(e[2])
    assert ns.value[k] == pytest.approx(e @ np.linalg.solve(est.cov_at(np.array([i]))[0], e),
                                        rel=1e-9)


@pytest.mark.parametrize("unit", ["s", "m"])
def test_rpe_with_given_pairs_equals_its_own_association(unit):
    est, truth = _random_tracks(5)
    pairs = metrics.associate(est.t, truth.t, 0.05)
    a = metrics.rpe(est, truth, 1.0, 0.05, unit=unit)
    b = metrics.rpe(est, truth, 1.0, 0.05, unit=unit, pairs=pairs)
    _eq(a[0], b[0])
    _eq(a[1], b[1])
    assert a[0].n > 10
    assert metrics.rpe_mean_delta(est, truth, 1.0, 0.05, unit=unit) == \
        metrics.rpe_mean_delta(est, truth, 1.0, 0.05, unit=unit, pairs=pairs)


def test_block_size_below_one_is_refused():
    est, truth = _random_tracks(6, n=20)
    i, j = metrics.associate(est.t, truth.t, 0.05)
    with pytest.raises(ValueError, match="block"):
        pair_scores.ape_stats(est, truth, i, j, block=0)
    with pytest.raises(ValueError, match="block"):
        metrics.nees_series(est, truth, 0.05, block=0)
