"""Which estimators a config's sensors allow, and what the refusal says."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from estimation.config import load_config
from evaluation import estimators as registry

ROOT = Path(__file__).resolve().parents[1]


def test_range_only_landmarks_leave_out_ekf_slam():
    """EKF-SLAM places a new landmark from its first sighting's range and bearing: with range
    alone it rejected every sighting (6584 on seed002) and ran as dead reckoning, unsaid."""
    cfg = load_config(ROOT / "data" / "sample_seed002.yaml")
    assert "ekf_slam" in registry.select(cfg, None)
    lm = cfg.of_kind("landmarks")[0]
    ranged = replace(cfg, sensors=[replace(s, use=("range",)) if s is lm else s
                                   for s in cfg.sensors])
    chosen = registry.select(ranged, None)
    assert "ekf_slam" not in chosen and {"ekf_landmark", "smoother"} <= set(chosen)
    with pytest.raises(ValueError, match="ekf_slam .* needs an odometry or wheels sensor, and "
                                         "landmarks with bearing"):
        registry.select(ranged, ["ekf_slam"])

