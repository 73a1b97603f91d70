"""Our ATE and RPE equal evo's on the same TUM files (written by our exporter).

evo is a test-only dependency (the ``test`` extra); without it these tests skip."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.estimation.runner import Trajectory
from ddfuse.evaluation import metrics
from ddfuse.evaluation.export import read_tum, write_tum

evo_metrics = pytest.importorskip("evo.core.metrics")
evo_sync = pytest.importorskip("evo.core.sync")
file_interface = pytest.importorskip("evo.tools.file_interface")

MAX_DIFF = 0.03


def _pair(tmp_path, seed: int = 4):
    """A truth at 20 Hz on a smooth random path and an estimate at ~10 Hz with jittered stamps,
    a drifting error and an offset and rotation against the truth; both as TUM files."""
    rng = np.random.default_rng(seed)
    t = 1_700_000_000.0 + np.arange(0, 60, 0.05)
    yaw_rate = np.convolve(rng.normal(0, 0.4, len(t)), np.ones(40) / 40, mode="same")
    yaw = 0.3 + np.cumsum(yaw_rate) * 0.05
    v = 1.0 + 0.3 * np.sin(t / 7)
    v[300:340] = 0.0  # a stop: repeated positions for the path-delta pairs
    x, y = np.cumsum(v * np.cos(yaw)) * 0.05, np.cumsum(v * np.sin(yaw)) * 0.05
    truth = Trajectory(t, np.column_stack([x, y, metrics.wrap(yaw)]), np.full((len(t), 3, 3), 0))
    te = 1_700_000_000.0 + np.arange(0.01, 59.9, 0.1) + rng.uniform(-0.02, 0.02, 599)
    ex = np.interp(te, t, x) + np.cumsum(rng.normal(0, 0.02, len(te))) + 0.5
    ey = np.interp(te, t, y) + np.cumsum(rng.normal(0, 0.02, len(te))) - 0.3
    eyaw = metrics.wrap(np.interp(te, t, np.unwrap(yaw)) + np.cumsum(rng.normal(0, 0.004, 599))
                        + 0.05)
    a = 0.2  # rotate the estimate about the origin, as a wrong initial heading would
    c, s = math.cos(a), math.sin(a)
    pose = np.column_stack([c * ex - s * ey, s * ex + c * ey, metrics.wrap(eyaw + a)])
    est = Trajectory(te, pose, np.full((len(te), 3, 3), np.nan))
    write_tum(tmp_path / "truth.tum", truth)
    write_tum(tmp_path / "est.tum", est)
    return tmp_path / "truth.tum", tmp_path / "est.tum"


def _evo_synced(ref_path, est_path):
    ref = file_interface.read_tum_trajectory_file(str(ref_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    return evo_sync.associate_trajectories(ref, est, max_diff=MAX_DIFF)


def _evo_stats(metric) -> dict:
    return {k: metric.get_statistic(getattr(evo_metrics.StatisticsType, k))
            for k in ("rmse", "mean", "median", "std", "min", "max")}


def _ours(stats: metrics.Stats) -> dict:
    return {k: getattr(stats, k) for k in ("rmse", "mean", "median", "std", "min", "max")}


@pytest.mark.parametrize("align", ["none", "se2", "origin"])
def test_ate_equals_evo_ape(tmp_path, align):
    ref_path, est_path = _pair(tmp_path)
    ref, est = _evo_synced(ref_path, est_path)
    if align == "se2":
        est.align(ref, correct_scale=False)
    elif align == "origin":
        est.align_origin(ref)
    ours = metrics.ape(read_tum(est_path), read_tum(ref_path), MAX_DIFF, align)
    assert ours.position.n == ref.num_poses > 500
    for relation, mine in ((evo_metrics.PoseRelation.translation_part, ours.position),
                           (evo_metrics.PoseRelation.rotation_angle_rad, ours.heading)):
        ape = evo_metrics.APE(relation)
        ape.process_data((ref, est))
        theirs = _evo_stats(ape)
        for k, v in _ours(mine).items():
            assert v == pytest.approx(theirs[k], rel=1e-7, abs=1e-9), (relation, k)
    # The alignments differ from each other here (offset and rotation), so the test can fail.
    if align != "none":
        assert ours.position.rmse < metrics.ate(read_tum(est_path), read_tum(ref_path),
                                                MAX_DIFF).rmse


@pytest.mark.parametrize("all_pairs", [False, True])
@pytest.mark.parametrize("delta", [2.0, 7.5])
def test_rpe_over_path_delta_equals_evo(tmp_path, delta, all_pairs):
    ref_path, est_path = _pair(tmp_path, seed=9)
    ref, est = _evo_synced(ref_path, est_path)
    trans, yaw = metrics.rpe(read_tum(est_path), read_tum(ref_path), delta, MAX_DIFF, unit="m",
                             all_pairs=all_pairs)
    for relation, mine in ((evo_metrics.PoseRelation.translation_part, trans),
                           (evo_metrics.PoseRelation.rotation_angle_rad, yaw)):
        rpe = evo_metrics.RPE(relation, delta, evo_metrics.Unit.meters, all_pairs=all_pairs)
        rpe.process_data((ref, est))
        assert mine.n == len(rpe.error) > 5
        theirs = _evo_stats(rpe)
        for k, v in _ours(mine).items():
            assert v == pytest.approx(theirs[k], rel=1e-7, abs=1e-9), (relation, k)


def test_association_equals_evo_on_jittered_stamps():
    rng = np.random.default_rng(2)
    t_ref = np.sort(rng.uniform(0, 100, 700))
    t_est = np.sort(rng.uniform(-1, 101, 400))
    ours = metrics.associate(t_est, t_ref, 0.05)
    theirs = evo_sync.matching_time_indices(t_est, t_ref, 0.05)
    assert len(ours[0]) > 50
    np.testing.assert_array_equal(ours[0], theirs[0])
    np.testing.assert_array_equal(ours[1], theirs[1])
