"""A compass whose configured fixed offset is wrong (0 where it is 0.35 rad) on a GPS without lever
arm or delay: every estimator keeps it out because the GPS fixes it accepts meanwhile corroborate
the heading (``ddfuse.ekf_baseline.kalman.CORROBORATED_BY``,
``smoother.heading.HeadingAccumulator.gate``).

By H columns alone such a GPS never observes the heading, so both EKFs declared themselves lost
after a second of rejected compass samples, recovered onto the compass and ended 2.66 m off
(three GPS lock-outs), where the smoother, with the rule, ended 0.24 m off."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.runner import run
from ddfuse.evaluation import estimators as registry


def _rmse(res, name: str, t_min: float = 20.0) -> float:
    tr, tt = res.runs[name].trajectory, res.truth
    k = tr.t >= tt.t[0] + t_min
    ex = tr.pose[k, 0] - np.interp(tr.t[k], tt.t, tt.pose[:, 0])
    ey = tr.pose[k, 1] - np.interp(tr.t[k], tt.t, tt.pose[:, 1])
    return math.sqrt(float(np.mean(ex * ex + ey * ey)))


@pytest.fixture(scope="module")
def runs(sample_husky):
    cfg, _ = sample_husky
    bag = cfg.path.with_suffix(".bag")
    no_delay = [replace(s, delay=0.0) if s.kind == "gps" else s for s in cfg.sensors]
    wrong = replace(cfg, sensors=[replace(s, heading_offset=0.0) if s.kind == "imu" else s
                                  for s in no_delay])
    no_compass = replace(cfg, sensors=[replace(s, use=("yaw_rate",)) if s.kind == "imu" else s
                                       for s in no_delay])
    out = {}
    for label, c in (("wrong", wrong), ("none", no_compass)):
        stream = read_stream(bag, c)
        ests = registry.build(c, stream, ["ekf", "ekf_igvc", "smoother"])
        out[label] = (run(stream, ests), ests)
    return out


@pytest.mark.parametrize("name", ["ekf", "ekf_igvc", "smoother"])
def test_a_compass_off_its_offset_is_kept_out_by_every_estimator(runs, name):
    res, ests = runs["wrong"]
    log = ests[name].log
    assert not [k for k in log.rejected if k[1] == "lockout_recovery"], dict(log.rejected)
    assert log.rejected[("/imu/data", "gate")] > 1000
    assert any("not recovering" in n for n in log.messages)
    # as good as without the compass (the sample's own GPS delay is 0.2 s; here 0)
    ref, _ = runs["none"]
    assert _rmse(res, name) < 1.1 * _rmse(ref, name) + 0.01, (_rmse(res, name),
                                                                 _rmse(ref, name))
