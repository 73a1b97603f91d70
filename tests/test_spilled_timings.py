"""The loop's per-call timings written to the run directory in blocks as they grow
(ddfuse.estimation.spill), scored from there (evaluation.latency_stats), the files removed
when the results are written, and nothing lost when the run is interrupted."""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation import spill
from ddfuse.estimation.config import load_config
from ddfuse.estimation.dead_reckoning import DeadReckoning
from ddfuse.estimation.errors import RunInterrupted
from ddfuse.estimation.runner import run
from ddfuse.estimation.spill import SpilledColumn
from ddfuse.evaluation import estimators as registry
from ddfuse.evaluation import latency_stats, pipeline

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("block", [1, 5, 1000])
def test_a_spilled_column_reads_back_what_was_appended(tmp_path, block):
    x = np.random.default_rng(block).lognormal(-9, 1, 777).astype(np.float32)
    c = SpilledColumn(tmp_path / "u.f32", block=block)
    for v in x.tolist():
        c.append(v)
    assert len(c) == 777 and len(c.tail) < block
    assert c.spilled == (777 // block) * block
    # no file until a block is full (block 1000: never)
    assert (os.path.getsize(tmp_path / "u.f32") if block < 777 else 0) == 4 * c.spilled
    assert (tmp_path / "u.f32").exists() == (block < 777)
    np.testing.assert_array_equal(np.asarray(c), x)
    for size in (1, 7, 10**6):
        got = list(c.blocks(size))
        assert max(len(b) for b in got) <= size
        np.testing.assert_array_equal(np.concatenate(got), x)
    c.remove()
    assert not (tmp_path / "u.f32").exists()


def test_a_failed_write_loses_nothing(tmp_path, monkeypatch):
    c = SpilledColumn(tmp_path / "u.f32", block=4)
    for v in range(8):
        c.append(float(v))
    real = c._file

    class Half:  # writes half the bytes, then the disk is full
        def __getattr__(self, name):
            return getattr(real, name)

        def write(self, b):
            real.write(bytes(b)[:len(b) // 2])
            raise OSError(28, "No space left on device")

    c._file = Half()
    for v in (8.0, 9.0, 10.0):
        c.append(v)
    with pytest.raises(OSError, match="No space"):
        c.append(11.0)
    c._file = real
    c.append(12.0)  # the next block overwrites the half-written one
    np.testing.assert_array_equal(np.asarray(c), np.arange(13, dtype=np.float32)[
        [*range(12), 12]])


@pytest.mark.parametrize("block", [1, 7, 10**6])
def test_streamed_latency_equals_numpy_on_the_whole_series(block):
    rng = np.random.default_rng(block)
    for n in (1, 2, 3, 1001):
        x = rng.lognormal(-9, 1.5, n)
        x[::50] = x[0]  # repeated values (timer resolution)

        def blocks(x=x):
            return (x[a:a + block] for a in range(0, len(x), block))

        qs = (0, 1, 50, 99, 99.9, 100)
        assert latency_stats.percentiles(blocks, qs) == [float(np.percentile(x, q))
                                                         for q in qs]
        m, k = latency_stats.mean(blocks())
        assert k == n and m == pytest.approx(float(np.mean(x)), rel=1e-12)
        x32 = x.astype(np.float32)

        def blocks32(x32=x32):
            return (x32[a:a + block] for a in range(0, len(x32), block))

        np.testing.assert_allclose(latency_stats.percentiles(blocks32, qs),
                                   [float(np.percentile(x32, q)) for q in qs], rtol=1e-6)
    assert all(np.isnan(latency_stats.percentiles(lambda: iter(()), (50, 99))))


def _dr_spec(at=None):
    from tests.test_runner_interrupt import _CtrlC  # noqa: PLC0415 - the same Ctrl-C double

    def make(cfg, stream, pose, lag, _):
        return _CtrlC(cfg, at=at, initial_pose=pose) if at else DeadReckoning(
            cfg, initial_pose=pose)
    return replace(registry.SPECS["dr"], make=make)


def test_runner_spills_the_timings_and_gives_them_back_whole(sample_husky, tmp_path, monkeypatch):
    monkeypatch.setattr(spill, "BLOCK", 100)
    cfg, stream = sample_husky
    g = stream.ground_truth[0]
    ests = {"dr": DeadReckoning(cfg, initial_pose=(g.x, g.y, g.yaw))}
    res = run(stream, ests, spill_dir=tmp_path)
    upd = res.runs["dr"].update_s
    assert isinstance(upd, SpilledColumn)
    calls = len(stream.measurements)
    assert len(upd) == calls and upd.spilled > calls - 1100  # spilled every 1000 messages
    assert os.path.getsize(tmp_path / "update_s.0.f32") == 4 * upd.spilled
    a = np.asarray(upd)
    assert a.dtype == np.float32 and len(a) == calls and (a >= 0).all()


def test_run_bag_removes_its_spill_and_writes_every_timing(tmp_path, monkeypatch):
    monkeypatch.setattr(spill, "BLOCK", 256)
    monkeypatch.setitem(registry.SPECS, "dr", _dr_spec())
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    (tmp_path / pipeline.SPILL_DIR).mkdir()
    (tmp_path / pipeline.SPILL_DIR / "update_s.0.f32").write_bytes(b"left by a killed run")
    pipeline.run_bag(ROOT / "data" / "sample_husky.bag", cfg, tmp_path, names=["dr"])
    assert not (tmp_path / pipeline.SPILL_DIR).exists()
    m = json.loads((tmp_path / "metrics.json").read_text())
    with np.load(tmp_path / "run.npz") as z:
        u = z["update_s/dr"]
    assert u.dtype == float and len(u) == m["estimators"]["dr"]["update_ms"]["n"] > 1000
    # the float32 timings times 1e3 in float32, rounded to 6 digits: within 1e-6 relative
    assert m["estimators"]["dr"]["update_ms"]["max"] == pytest.approx(float(u.max()) * 1e3,
                                                                       rel=1e-6)


@pytest.mark.slow
def test_an_interrupted_run_keeps_the_spilled_timings(tmp_path, monkeypatch):
    monkeypatch.setattr(spill, "BLOCK", 256)
    monkeypatch.setitem(registry.SPECS, "dr", _dr_spec(at=3000))
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    with pytest.raises(RunInterrupted, match="after 2999 measurements"):
        pipeline.run_bag(ROOT / "data" / "sample_husky.bag", cfg, tmp_path, names=["ekf", "dr"])
    assert not (tmp_path / pipeline.SPILL_DIR).exists()
    m = json.loads((tmp_path / "metrics.json").read_text())
    with np.load(tmp_path / "run.npz") as z:
        # every call made before the stop, the spilled blocks and the tail: the EKF, first,
        # had its 3000th call; the double's 3000th raised
        assert len(z["update_s/ekf"]) == m["estimators"]["ekf"]["update_ms"]["n"] == 3000
        assert len(z["update_s/dr"]) == m["estimators"]["dr"]["update_ms"]["n"] == 2999


def test_a_spilled_track_is_the_in_memory_one(sample_husky, tmp_path, monkeypatch):
    from ddfuse.estimation import runner

    monkeypatch.setattr(runner, "TRACK_BLOCK", 64)
    cfg, stream = sample_husky
    g = stream.ground_truth[0]

    def once(spill_dir):
        ests = {"dr": DeadReckoning(cfg, initial_pose=(g.x, g.y, g.yaw))}
        return run(stream, ests, spill_dir=spill_dir).runs["dr"].trajectory

    mem, disk = once(None), once(tmp_path)
    n = len(mem.t)
    assert n > 10 * 64 and os.path.getsize(tmp_path / "track.0.t") == 8 * n  # all on disk
    np.testing.assert_array_equal(disk.t, mem.t)
    np.testing.assert_array_equal(disk.pose, mem.pose)
    np.testing.assert_array_equal(disk.cov_at(slice(0, n)), mem.cov_at(slice(0, n)))
    assert not disk.t.flags.writeable
    disk.release()  # the pages dropped: the values are read again from the file
    np.testing.assert_array_equal(disk.pose, mem.pose)


def test_a_spilling_track_builder_indexes_spilled_rows(tmp_path, monkeypatch):
    from ddfuse.estimation import runner
    from ddfuse.estimation.estimator import Estimate

    monkeypatch.setattr(runner, "TRACK_BLOCK", 4)
    b = runner.TrackBuilder(spill_to=tmp_path / "x")
    for k in range(11):
        b.append(Estimate(float(k), (k, 2.0 * k, 0.1), np.diag([k + 1.0, 2.0, 3.0])))
        b.spill()
    assert len(b) == 11 and os.path.getsize(tmp_path / "x.t") == 8 * 8
    assert b[1].t == 1.0 and b[1].pose == (1.0, 2.0, 0.1) and b[1].pose_cov[0, 0] == 2.0
    assert b[-1] is b.last and [e.t for e in b[9:]] == [9.0, 10.0]
