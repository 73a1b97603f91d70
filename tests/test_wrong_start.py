"""A wrong stated start under a robust GPS model: the initial pose 4 m and 172 deg off, stated
to 1 cm and 5 mrad (``initial_pose``). Every fix is then an outlier to the estimate. Before
session 31 the smoother followed the odometry for the rest of the run ("GPS and odometry
disagree"), and the EKFs' recovery after ``fault_hold`` fused the fix at the kernel's weight
for its distance, a no-op (covariance "inflated x1"): all ended 21 m RMS and 35 m from the
truth (the batch, holding its tight link across the widening, 20.8 m). The GPS's many fixes
outweigh one stated value: each estimator follows the GPS and
says why. Under the gate (``default``) the filters already left it through the lock-out; the
batch, which tied the widened keyframe tightly to the one before ("the robot did not jump"),
was held at the start for the whole run (14.3 m RMS, 15.0 m from 20 s on). A lock-out of a
GPS that never agreed with the estimate since the start is a wrong start there too."""

from __future__ import annotations

import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.runner import run
from ddfuse.evaluation import estimators as registry

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wrong_start():
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    cfg = replace(cfg, initial_pose=(3.0, -3.0, 3.0), gps=replace(cfg.gps, model="dcs"))
    stream = read_stream(ROOT / "data" / "sample_husky.bag", cfg)
    names = ["ekf", "ekf_igvc", "smoother", "batch"]
    built = registry.build(cfg, stream, names, pose=cfg.initial_pose)
    return stream, run(stream, built).runs


@pytest.mark.parametrize("name", ["ekf", "ekf_igvc", "smoother", "smoother_lagged", "batch"])
def test_a_wrong_start_is_left_for_the_gps(wrong_start, name):
    stream, runs = wrong_start
    r = runs[name]
    assert r.error is None
    end = r.trajectory.pose[-1]
    truth = stream.ground_truth[-1]
    assert math.hypot(end[0] - truth.x, end[1] - truth.y) < 1.0, (end, truth)
    notes = " ".join(r.log.messages)
    assert "the start is taken for wrong" in notes
    if name.startswith("ekf"):
        (factor,) = re.findall(r"covariance inflated x([0-9.e+]+)", notes)
        assert float(factor) > 100.0  # the fix followed, not weighed away


@pytest.fixture(scope="module")
def wrong_start_gated():
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    cfg = replace(cfg, initial_pose=(3.0, -3.0, 3.0))
    assert cfg.gps.model == "default"
    stream = read_stream(ROOT / "data" / "sample_husky.bag", cfg)
    built = registry.build(cfg, stream, ["smoother", "batch"], pose=cfg.initial_pose)
    return stream, run(stream, built).runs


@pytest.mark.parametrize("name", ["smoother", "smoother_lagged", "batch"])
def test_a_gated_lockout_from_the_start_lets_the_batch_leave_it(wrong_start_gated, name):
    """Measured: from 20 s on smoother 0.18, lagged 0.10, batch 0.09 m RMS (batch 15.0 m
    before)."""
    stream, runs = wrong_start_gated
    r = runs[name]
    assert r.error is None
    tr = r.trajectory
    truth = stream.ground_truth
    gt = np.array([(g.t, g.x, g.y) for g in truth])
    late = tr.t >= gt[0, 0] + 20.0
    ex = tr.pose[late, 0] - np.interp(tr.t[late], gt[:, 0], gt[:, 1])
    ey = tr.pose[late, 1] - np.interp(tr.t[late], gt[:, 0], gt[:, 2])
    assert float(np.sqrt(np.mean(ex * ex + ey * ey))) < 0.5
    notes = " ".join(r.log.messages)
    assert "gate lock-out" in notes and "the start is taken for wrong" in notes


@pytest.fixture(scope="module", params=[("default", 4.7), ("dcs", 4.7), ("dcs", 3.5)])
def wrong_heading(request):
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    # the truth starts at (0, 0, pi/2): the position right, the heading 180 or 110 deg off
    model, yaw = request.param
    cfg = replace(cfg, initial_pose=(0.0, 0.0, yaw), gps=replace(cfg.gps, model=model))
    stream = read_stream(ROOT / "data" / "sample_husky.bag", cfg)
    built = registry.build(cfg, stream, ["smoother", "batch"], pose=cfg.initial_pose)
    return stream, run(stream, built).runs


@pytest.mark.parametrize("name", ["smoother", "smoother_lagged", "batch"])
def test_a_wrong_start_heading_is_widened_with_the_position(wrong_heading, name):
    """A start taken for wrong widens the heading by START_HEADING_VAR too: the lock-out's
    alpha alone scaled a 5 mrad sigma that a 180 deg error outlasts. Measured, from 30 s on
    (smoother, lagged, batch): `default` 0.13, 0.10, 0.09 m (before 4 lock-outs, 1.2 m from 20 s
    on); `dcs` 0.17, 0.12, 0.16 m, where before the smoother never left the start's heading
    (42.5 m from 30 s on, 24 m from the truth at the end). 110 deg off under `dcs` the first
    fixes agree (the robot has not gone far), and a disagreement is the GPS's; once its fixes
    have moved as the odometry does (the GPS watch) for ESTIMATE_WRONG_S, it is the estimate's:
    from 50 s on 0.23, 0.18, 0.17 m (before 23.9, 23.8, 23.7 m RMS from 30 s on: the odometry
    followed for good)."""
    stream, runs = wrong_heading
    r = runs[name]
    assert r.error is None
    tr = r.trajectory
    gt = np.array([(g.t, g.x, g.y) for g in stream.ground_truth])
    late = tr.t >= gt[0, 0] + 50.0
    ex = tr.pose[late, 0] - np.interp(tr.t[late], gt[:, 0], gt[:, 1])
    ey = tr.pose[late, 1] - np.interp(tr.t[late], gt[:, 0], gt[:, 2])
    assert float(np.sqrt(np.mean(ex * ex + ey * ey))) < 0.4
    assert math.hypot(ex[-1], ey[-1]) < 0.4
