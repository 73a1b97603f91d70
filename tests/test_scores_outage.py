"""Outage drift against withheld GPS fixes (a bag without truth): the path travelled and the
start and end errors must come from the fixes without their noise inflating them."""

from __future__ import annotations

import math

import numpy as np
from ddfuse.estimation.runner import Trajectory
from ddfuse.evaluation import metrics

SIGMA = 1.0  # m per axis, the sample bag's fixes
RATE = 2.5  # Hz
SPEED = 1.0  # m/s
RADIUS = 15.0  # m, the drive's turn


def _drive(t: np.ndarray) -> np.ndarray:
    """(N, 2) positions: a circle of RADIUS at SPEED."""
    a = SPEED * t / RADIUS
    return np.column_stack([RADIUS * np.sin(a), RADIUS * (1.0 - np.cos(a))])


def _fixes(rng, t0: float, t1: float):
    t = np.arange(t0, t1, 1.0 / RATE)
    xy = _drive(t) + rng.normal(0.0, SIGMA, (len(t), 2))
    return t, xy, np.tile(np.eye(2) * SIGMA**2, (len(t), 1, 1))


def _bounds(duration: float) -> tuple[float, float]:
    """Expected relative bias of the block-median path: the noise left in each median
    lengthens a segment by about var_perp / (2 D) per segment of length D (var_perp: both
    medians' noise across it), the chord across an arc of angle D / R shortens it by
    (D / R)^2 / 24."""
    n = metrics.FIX_BLOCK_S * RATE
    var = metrics.MEDIAN_VARIANCE * SIGMA**2 / n  # per axis, one median
    d = SPEED * metrics.FIX_BLOCK_S
    return 2 * var / (2 * d * d), (d / RADIUS) ** 2 / 24


def test_path_through_withheld_fixes_is_not_inflated_by_their_noise():
    rng = np.random.default_rng(7)
    duration = 30.0
    truth_len = SPEED * (duration - 1.0 / RATE)  # first to last fix
    rel, raw = [], []
    for _ in range(40):
        t, xy, cov = _fixes(rng, 0.0, duration)
        rel.append(metrics.fix_path_length(t, xy, cov) / truth_len - 1.0)
        raw.append(metrics.path_length(xy) / truth_len - 1.0)
    longer, shorter = _bounds(duration)
    # the polyline through the fixes: about sqrt(pi) sigma per fix interval of noise alone
    assert np.mean(raw) > 2.0
    se = np.std(rel) / math.sqrt(len(rel))
    assert -shorter - 3 * se <= np.mean(rel) <= longer + 3 * se, (np.mean(rel), longer, shorter)
    assert np.max(np.abs(rel)) < 0.15


def test_outage_drift_against_withheld_fixes_recovers_the_error_growth():
    """An estimate whose error grows from 0.2 to 1.4 m over a 30 s outage: against the
    withheld fixes the start and end errors are those within the noise left in the medians of
    their first and last seconds, and the drift per metre that of the truth within it."""
    rng = np.random.default_rng(3)
    te = np.arange(0.0, 40.0, 0.1)
    o = metrics.Outage(5.0, 35.0)
    err = 0.2 + 1.2 * np.clip((te - o.t0) / (o.t1 - o.t0), 0.0, 1.0)
    pose = np.column_stack([_drive(te) + np.column_stack([err, np.zeros_like(err)]),
                            np.zeros_like(te)])
    est = Trajectory(te, pose, np.zeros((len(te), 3, 3)))
    truth = Trajectory(te, np.column_stack([_drive(te), np.zeros_like(te)]), pose[:, :0])
    want = metrics.outage_drift(est, o, truth.t, truth.pose[:, :2], "truth")
    dev_start, dev_end, dev_drift = [], [], []
    for _ in range(30):
        t, xy, cov = _fixes(rng, 0.0, 40.0)
        d = metrics.outage_drift(est, o, t, xy, "withheld GPS", ref_cov=cov)
        assert min(d.fixes_start, d.fixes_end) >= metrics.FIX_BLOCK_S * RATE - 1
        # the error grows by 1.2 m / 30 s * 3 s = 0.12 m across a block: its median is the
        # mid-block error
        mid = 0.04 * metrics.FIX_BLOCK_S / 2
        dev_start.append((d.error_start_m - (want.error_start_m + mid)) / d.error_noise_m)
        dev_end.append((d.error_end_m - (want.error_end_m - mid)) / d.error_noise_m)
        # what the medians measure: the errors at the blocks' middles
        dev_drift.append(d.drift_per_m - (want.error_end_m - want.error_start_m - 2 * mid)
                         / want.distance_m)
        noise = d.error_noise_m
    # within 3 noise sigmas each (the clip at 0 and the subtraction move it less than that)
    assert np.max(np.abs(dev_start)) < 3 and np.max(np.abs(dev_end)) < 3
    # the drift per metre: the two errors' noise over 30 m (3 standard errors of the mean over
    # the draws), and the path's bias (a tenth of the drift: a few %, test above)
    se = math.sqrt(2) * noise / want.distance_m / math.sqrt(len(dev_drift))
    assert abs(np.mean(dev_drift)) < 3 * se + 0.1 * want.drift_per_m
    # a single fix at either end (the former rule) scatters the drift by its noise alone
    assert np.std(dev_drift) < math.sqrt(2) * SIGMA * math.sqrt(2) / want.distance_m
