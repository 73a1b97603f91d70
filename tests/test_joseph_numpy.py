"""joseph_numpy, the cold path's update: the same covariance, correction and fused noise as the
compiled ``joseph`` entry points, to rounding, over random stacked updates (blocks accepted and
rejected, fusion factors) and over the sample bag's reference EKFs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from ddfuse.ekf_baseline import joseph, joseph_numpy, kalman

ROOT = Path(__file__).resolve().parents[1]


def _case(rng):
    n = int(rng.choice([3, 5, 11]))
    m = int(rng.integers(1, 7))
    A = rng.normal(size=(n, n))
    P = A @ A.T + 0.1 * np.eye(n)
    H = rng.normal(size=(m, n)) * (rng.random((m, n)) < 0.4)
    B = rng.normal(size=(m, m))
    R = B @ B.T + 0.5 * np.eye(m)
    cuts = sorted({0, m, *rng.integers(1, m + 1, 2).tolist()})
    blk = np.array([v for a, b in zip(cuts[:-1], cuts[1:], strict=True) for v in (a, b, 0, 0)],
                   dtype=np.int64)
    nb = len(cuts) - 1
    verdict = (rng.random(nb) < 0.3).astype(np.int64)
    verdict[rng.integers(nb)] = 0  # at least one accepted block
    fs = rng.choice([1.0, 2.0, 150.0], nb)
    return P, H, rng.normal(size=m), R, blk, verdict, fs


def test_numpy_twins_agree_with_the_compiled_update():
    rng = np.random.default_rng(7)
    for _ in range(80):
        P, H, y, R, blk, verdict, fs = _case(rng)
        Ut1, S1 = joseph.innovation_cov(P, H, R)
        Ut2, S2 = joseph_numpy.innovation_cov(P, H, R)
        R1, R2 = R.copy(), R.copy()
        P1, dx1 = joseph.apply_update(P, H, y, R1, Ut1, blk, verdict, fs)
        P2, dx2 = joseph_numpy.apply_update(P, H, y, R2, Ut2, blk, verdict, fs)
        scale = np.abs(P).max()
        assert np.abs(Ut2 - Ut1).max() <= 1e-12 * scale
        assert np.abs(S2 - S1).max() <= 1e-12 * np.abs(S1).max()
        assert np.array_equal(R2, R1)  # the same fusion, in place
        assert np.abs(P2 - P1).max() <= 1e-12 * scale
        assert np.abs(dx2 - dx1).max() <= 1e-12 * (1 + np.abs(dx1).max())
        assert np.array_equal(P2, P2.T)  # exactly symmetric, as the compiled update's


@pytest.mark.slow
@pytest.mark.parametrize("which", ["unicycle", "igvc"])
def test_the_cold_reference_filters_track_the_warm_ones_on_the_sample_bag(which, monkeypatch):
    from ddfuse.ekf_baseline.igvc import IgvcEkf
    from ddfuse.ekf_baseline.unicycle import UnicycleEkf
    from ddfuse.estimation.bags import read_stream
    from ddfuse.estimation.config import load_config
    from ddfuse.estimation.runner import initial_pose

    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    stream = read_stream(ROOT / "data" / "sample_husky.bag", cfg)
    pose = initial_pose(cfg.initial_pose, stream)

    def run(functions):
        monkeypatch.setattr(kalman, "update_functions", lambda: functions)
        est = (UnicycleEkf(cfg, initial_pose=pose, reference=True) if which == "unicycle"
               else IgvcEkf(cfg, initial_pose=pose, datum=stream.datum, reference=True))
        out = []
        for m in stream.measurements:
            est.process(m)
            e = est.estimate()
            if e is not None and e.state is not None:
                out.append(np.concatenate([e.state, e.state_cov.ravel()]))
        return np.array(out)

    warm = run((joseph.innovation_cov, joseph.apply_update))
    cold = run((joseph_numpy.innovation_cov, joseph_numpy.apply_update))
    assert warm.shape == cold.shape and len(warm) > 1000
    assert np.abs(cold - warm).max() <= 1e-9
