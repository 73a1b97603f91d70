"""What keeps a long run's memory from growing with the bag after its loop gives the same
results as the whole-array code it replaced: a packed track's covariances read a block at a
time (``Trajectory.cov_at``), the truth's absent covariance, the track files built a chunk of
rows at a time, and run.npz written one entry at a time."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
from ddfuse.estimation.estimator import Estimate
from ddfuse.estimation.runner import TrackBuilder, Trajectory
from ddfuse.evaluation import export, metrics


def _packed(n: int, seed: int = 0) -> Trajectory:
    """A TrackBuilder's track of ``n`` samples with SPD covariances (one of them NaN)."""
    rng = np.random.default_rng(seed)
    b = TrackBuilder()
    for k in range(n):
        a = rng.normal(size=(3, 3)) * 0.3
        cov = a @ a.T + 0.01 * np.eye(3)
        if k == 5:
            cov = np.full((3, 3), np.nan)
        b.append(Estimate(100.0 + 0.1 * k, (rng.normal() * 10, rng.normal() * 10,
                                           rng.uniform(-3, 3)), cov))
    return b.trajectory()


def _unpacked(tr: Trajectory) -> Trajectory:
    return Trajectory(tr.t.copy(), tr.pose.copy(), np.array(tr.cov_at(slice(None))))


def test_cov_at_reads_rows_of_a_packed_track_without_unpacking_it_whole():
    tr = _packed(50)
    full = _unpacked(tr).cov
    idx = np.array([0, 3, 5, 49, 3])
    assert np.array_equal(tr.cov_at(idx), full[idx], equal_nan=True)
    assert np.array_equal(tr.cov_at(slice(10, 20)), full[10:20])
    assert tr._cov is None  # still packed: cov_at kept nothing
    assert np.array_equal(tr.cov, full, equal_nan=True)  # and a whole read is the same
    assert np.array_equal(tr.cov_at(idx), full[idx], equal_nan=True)


def test_the_truths_missing_covariance_is_nan_and_takes_no_memory_per_sample():
    t = np.arange(1000) * 0.1
    truth = Trajectory.from_ground_truth((t, np.zeros((1000, 3))))
    assert truth.cov.shape == (1000, 3, 3) and np.isnan(truth.cov).all()
    assert truth.cov.strides == (0, 0, 0) and not truth.cov.flags.writeable
    assert truth.cov_at(slice(3, 7)).shape == (4, 3, 3)


@pytest.mark.parametrize("pose_error", ["world", "se2"])
def test_nees_of_a_packed_track_read_in_blocks_is_that_of_its_whole_covariances(
        monkeypatch, pose_error):
    tr = _packed(60, seed=1)
    rng = np.random.default_rng(2)
    ref = Trajectory(tr.t + 0.01, tr.pose + rng.normal(size=tr.pose.shape) * 0.1,
                     np.full((60, 3, 3), np.nan))
    whole = metrics.nees_series(_unpacked(tr), ref, 0.05, pose_error)
    monkeypatch.setattr(metrics, "_COV_BLOCK", 7)  # blocks end inside the track
    blocks = metrics.nees_series(tr, ref, 0.05, pose_error)
    assert len(whole.value) == 59  # the NaN covariance is left out
    for f in ("t", "value", "dof", "i_est"):
        assert np.array_equal(getattr(blocks, f), getattr(whole, f))
        assert getattr(blocks, f).dtype == getattr(whole, f).dtype
    assert tr._cov is None


def test_gate_nis_of_a_packed_track_is_that_of_its_whole_covariances():
    tr = _packed(80, seed=3)
    rng = np.random.default_rng(4)
    t = tr.t[::7] + 0.03
    xy = tr.pose[::7, :2] + rng.normal(size=(len(t), 2))
    cov = np.broadcast_to(np.eye(2), (len(t), 2, 2)).copy()
    a = metrics.gate_nis(tr, t, xy, cov, (0.2, 0.1), 0.05)
    b = metrics.gate_nis(_unpacked(tr), t, xy, cov, (0.2, 0.1), 0.05)
    assert np.isfinite(a).sum() > 5 and np.array_equal(a, b, equal_nan=True)


@pytest.mark.parametrize("n", [0, 1, 4, 5, 9])
def test_track_files_built_a_chunk_at_a_time_are_what_savetxt_writes(tmp_path, monkeypatch, n):
    monkeypatch.setattr(export, "_CHUNK", 4)  # chunk edges at 4 and 8 rows
    tr = _packed(n, seed=n)
    export.write_tum(tmp_path / "a.tum", tr)
    export.write_csv(tmp_path / "a.csv", tr)
    yaw, z = np.nan_to_num(tr.pose[:, 2]), np.zeros(n)
    np.savetxt(tmp_path / "b.tum", np.column_stack([tr.t, tr.pose[:, :2], z, z, z,
                                                    np.sin(yaw / 2), np.cos(yaw / 2)]),
               fmt="%.9f %.6f %.6f %.6f %.9f %.9f %.9f %.9f")
    np.savetxt(tmp_path / "b.csv", np.column_stack([tr.t, tr.pose, tr.cov.reshape(n, 9)]),
               delimiter=",", header=",".join(export.CSV_COLUMNS), comments="",
               fmt=["%.9f"] + ["%.10g"] * 12)
    for ext in ("tum", "csv"):
        assert (tmp_path / f"a.{ext}").read_bytes() == (tmp_path / f"b.{ext}").read_bytes()


def _result(n_calls: int):
    """A RunResult as ``runner.run`` leaves it: a track and its lagged one sharing the log and
    the float32 per-call timings, GPS fixes (some withheld), a landmark, innovations."""
    from types import SimpleNamespace

    from ddfuse.estimation.estimator import EstimatorLog
    from ddfuse.estimation.runner import EstimatorRun, GpsTrack, RunResult

    rng = np.random.default_rng(5)
    log = EstimatorLog()
    for k in range(300):
        log.innovations.add(float(k), "gps" if k % 3 else "imu", "gps" if k % 3 else "gyro",
                            (0.1, 0.2), ((1.0, 0.0), (0.0, 1.0)), float(rng.random()),
                            bool(k % 7))
    upd = rng.random(n_calls).astype(np.float32) * 1e-3
    runs = {name: EstimatorRun(name, _packed(40), upd, 1.5, log)
            for name in ("smoother", "smoother_lagged")}
    g = 25
    gps = GpsTrack(np.arange(g) * 1.0, rng.normal(size=(g, 2)),
                   np.broadcast_to(np.eye(2), (g, 2, 2)).copy(), np.arange(g) % 5 == 0)
    return RunResult(SimpleNamespace(landmarks={"7": (1.0, 2.0)}), runs, gps)


def test_run_npz_written_entry_by_entry_holds_the_members_savez_wrote(monkeypatch):
    """Each .npy member byte for byte, the per-call timings (float32 in the run) widened to
    float64 a block at a time as ``run_arrays`` widens them whole."""
    from ddfuse.evaluation import run_files

    result = _result(2500)
    monkeypatch.setattr(run_files, "_NPY_BLOCK", 1000)  # three blocks, the last one short
    old, new = io.BytesIO(), io.BytesIO()
    np.savez_compressed(old, **run_files.run_arrays(result, "cfg text"))
    run_files._write_npz(new, run_files._run_entries(result, "cfg text"))
    with zipfile.ZipFile(old) as a, zipfile.ZipFile(new) as b:
        assert a.namelist() == b.namelist()
        assert {"update_s/smoother_lagged.npy", "innov/smoother/nis.npy"} <= set(a.namelist())
        assert "innov/smoother_lagged/nis.npy" not in a.namelist()  # the shared log once
        for name in a.namelist():
            assert a.read(name) == b.read(name), name
    z = np.load(io.BytesIO(new.getvalue()))
    assert z["update_s/smoother"].dtype == np.float64
    assert np.array_equal(z["update_s/smoother"], result.runs["smoother"].update_s)


@pytest.mark.parametrize("unit", ["s", "m"])
def test_rpe_pairs_walked_in_blocks_are_the_pairs_of_one_walk(monkeypatch, unit):
    rng = np.random.default_rng(6)
    t = np.cumsum(rng.random(500) * 0.2)
    xy = np.cumsum(rng.normal(size=(500, 2)) * 0.3, axis=0)
    whole = metrics.rpe_pairs(t, xy, 1.0, unit)
    monkeypatch.setattr(metrics, "_STEP_BLOCK", 3)  # a pair's run of steps spans blocks
    blocks = metrics.rpe_pairs(t, xy, 1.0, unit)
    assert len(whole[0]) > 20
    assert all(np.array_equal(a, b) for a, b in zip(whole, blocks, strict=True))


def test_the_reference_interpolated_in_blocks_is_that_of_one_block(monkeypatch):
    rng = np.random.default_rng(7)
    ref = Trajectory(np.cumsum(rng.random(300) * 0.1), rng.normal(size=(300, 3)),
                     np.full((300, 3, 3), np.nan))
    t = np.sort(rng.uniform(ref.t[0] - 1, ref.t[-1] + 1, 200))
    j = np.clip(np.searchsorted(ref.t, t), 0, 299)
    whole = metrics.reference_at(ref, t, j, 0.05)
    monkeypatch.setattr(metrics, "_REF_BLOCK", 9)
    assert np.array_equal(metrics.reference_at(ref, t, j, 0.05), whole, equal_nan=True)
    assert not np.array_equal(whole, ref.pose[j])  # some stamps were interpolated


def test_estimates_mcap_encoded_in_small_blocks_is_the_same_file(tmp_path, monkeypatch):
    from ddfuse.estimation.runner import Trajectory as Tr
    from ddfuse.evaluation import estimates_mcap

    result = _result(10)
    tr = result.runs["smoother"].trajectory
    # the lagged track shares stamps with the truth and the filtered track (ties across topics)
    result.runs["smoother_lagged"].trajectory = Tr(tr.t[::3].copy(), tr.pose[::3].copy(),
                                                   tr.cov_at(slice(None, None, 3)))
    result.truth = Tr(tr.t.copy(), tr.pose.copy() + 0.1, np.full((len(tr), 3, 3), np.nan))
    estimates_mcap.write_estimates(tmp_path / "a.mcap", result)
    monkeypatch.setattr(estimates_mcap, "_BLOCK", 7)
    estimates_mcap.write_estimates(tmp_path / "b.mcap", result)
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()
