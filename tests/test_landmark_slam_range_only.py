"""ekf_slam and range-only landmark sensors (issue 30): one range cannot place a new landmark,
so the default set leaves ekf_slam out of such a config, and ``ddfuse run`` says why."""

from __future__ import annotations

import dataclasses
from importlib.resources import files

from ddfuse.estimation.config import load_config
from ddfuse.evaluation import estimators as registry

CONFIG = files("ddfuse.data") / "sample_seed002.yaml"


def _range_only(cfg):
    for s in cfg.of_kind("landmarks"):
        s.use = tuple(u for u in s.use if u != "bearing")
    return cfg


def test_range_only_landmarks_leave_ekf_slam_out_and_say_why():
    cfg = load_config(str(CONFIG))
    assert "ekf_slam" in registry.select(cfg, None) and registry.left_out(cfg) == []
    ro = _range_only(dataclasses.replace(cfg, sensors=[dataclasses.replace(s) for s in
                                                        cfg.sensors]))
    chosen = registry.select(ro, None)
    assert "ekf_slam" not in chosen and "ekf_landmark" in chosen
    (line,) = registry.left_out(ro)
    assert line.startswith("ekf_slam left out") and "/landmarks" in line and "range" in line
    # a config without landmarks has nothing to explain
    no_marks = dataclasses.replace(cfg, sensors=[s for s in cfg.sensors
                                                 if s.kind != "landmarks"])
    assert registry.left_out(no_marks) == []
