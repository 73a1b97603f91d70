"""The smoother logs each landmark sighting's innovation against its prediction (for NIS)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from estimation.bags import read_stream
from estimation.config import load_config
from estimation.measurements import LandmarkObservation
from estimation.runner import initial_pose, run
from estimation.smoother import FixedLagSmoother

ROOT = Path(__file__).resolve().parents[1]


def test_smoother_landmark_innovations_on_the_seed002_sample():
    cfg = load_config(ROOT / "data" / "sample_seed002.yaml")
    stream = read_stream(ROOT / "data" / "sample_seed002.bag", cfg)
    stream.measurements = [m for m in stream.measurements if m.t < stream.t0 + 30.0]
    sm = FixedLagSmoother(cfg, initial_pose=initial_pose(cfg.initial_pose, stream),
                          landmarks=stream.landmarks)
    run(stream, {"smoother": sm})
    inn = [i for i in sm.log.innovations if i.kind == "landmark"]
    sightings = [m for m in stream.measurements if isinstance(m, LandmarkObservation)]
    assert len(inn) > 0.9 * len(sightings) > 500
    assert all(i.residual.shape == (2,) and i.cov.shape == (2, 2) for i in inn)
    nis = np.array([i.nis for i in inn])
    # The residual is z - h(prediction) with the factor's own model: a wrong sign of the
    # bearing or a transposed Jacobian makes these hundreds, not a few.
    assert 0.5 < np.median(nis) < 4.0
    ranges = np.array([i.residual[0] for i in inn])
    assert np.sqrt(np.mean(ranges ** 2)) < 0.3  # range noise 0.1 m plus prediction error
    for i in inn[:50]:
        np.testing.assert_allclose(i.nis, i.residual @ np.linalg.solve(i.cov, i.residual))
