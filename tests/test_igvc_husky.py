"""Issue 30's ekf_igvc criteria on robot_localization's Husky bag (../shared/data): its GPS
hold-out scores within 15 % of the unicycle EKF's, and no gate lock-out where neither the
unicycle EKF nor the lagged smoother has one. Slow (six runs of the whole bag)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from ddfuse.estimation.config import load_config
from ddfuse.evaluation import pipeline

pytestmark = pytest.mark.slow

CONFIG = Path(__file__).resolve().parents[1] / "data" / "configs" / "rl_husky_gps.yaml"
_LOCKOUT = re.compile(r"^t=([0-9.]+): \S+: gate lock-out")


def _config(white_gps: bool):
    """The shipped config; ``white_gps``: its GPS fused as white (correlation_time 0, as
    shipped when issue 30 was measured)."""
    cfg = load_config(CONFIG)
    if white_gps:
        for s in cfg.of_kind("gps"):
            s.correlation_time = 0.0
    return cfg


def _lockouts(scores) -> list[float]:
    """Stamps (s) of the GPS gate lock-outs an estimator's events record."""
    return [float(m.group(1)) for m in map(_LOCKOUT.match, scores.events) if m]


@pytest.mark.parametrize("white_gps", [True, False], ids=["white_gps", "shipped"])
@pytest.mark.parametrize("holdout", ["every:5", "window:150:210"])
def test_holdout_within_15_percent_of_the_unicycle_ekf(husky_bag, tmp_path, holdout,
                                                       white_gps):
    """Measured (ekf_igvc / ekf, m): white GPS every:5 1.306 / 1.267, window 4.271 / 4.147;
    shipped every:5 2.363 / 2.418, window 3.595 / 3.631. Before the process noise took the
    unicycle EKF's slip densities (errata 000 #42) the white-GPS scores were 1.590 and 4.621
    (+25 % and +11 %)."""
    e = pipeline.run_bag(husky_bag, _config(white_gps), tmp_path, names=["ekf", "ekf_igvc"],
                         holdout=holdout).estimators
    ratio = e["ekf_igvc"].gps_holdout_rmse_m / e["ekf"].gps_holdout_rmse_m
    assert ratio <= 1.15, (holdout, white_gps, ratio)


@pytest.mark.parametrize("white_gps", [True, False], ids=["white_gps", "shipped"])
def test_no_lockout_where_the_others_have_none(husky_bag, tmp_path, white_gps):
    """Every GPS lock-out of ekf_igvc is within 1 s of one of the unicycle EKF or the lagged
    smoother (the same fixes disagreeing with every estimate). Measured: white GPS 58.5 s for
    all three; shipped 61.3 s (with the smoother) and 392.4 s (all three). Before errata 000
    #42 ekf_igvc alone locked out at 392.4 s with the white GPS (covariance x730, the issue's
    heading sigma of 30 deg and its end 3 m off the others')."""
    e = pipeline.run_bag(husky_bag, _config(white_gps), tmp_path,
                         names=["ekf", "ekf_igvc", "smoother_lagged"]).estimators
    others = _lockouts(e["ekf"]) + _lockouts(e["smoother_lagged"])
    mine = _lockouts(e["ekf_igvc"])
    assert others, "the bag's GPS jumps at 55 s and 390 s lock someone out"
    alone = [t for t in mine if min(abs(t - o) for o in others) > 1.0]
    assert not alone, (alone, others)
    # the end agrees with the lagged smoother's to the others' spread (0.3-0.5 m)
    (x, y), (xs, ys) = e["ekf_igvc"].final_xy, e["smoother_lagged"].final_xy
    assert ((x - xs) ** 2 + (y - ys) ** 2) ** 0.5 < 1.0
