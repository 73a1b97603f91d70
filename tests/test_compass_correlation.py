"""evaluation.compass_correlation: a heading sensor's Gauss-Markov error measured against the
gyro's integral (the correlation_time inspect suggests and tune sets), and tune's parameter."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.estimation.config import parse_config
from ddfuse.estimation.measurements import GyroYawRate, Heading, Stream, WheelOdometry
from ddfuse.evaluation.compass_correlation import drifts, measure
from ddfuse.evaluation.tune_params import Applier, parameters


def _cfg():
    return parse_config({"sensors": {
        "odometry": [{"topic": "/odom", "use": ["v"], "noise": {"v": 0.05}}],
        "imu": [{"topic": "/imu", "use": ["yaw", "yaw_rate"],
                 "noise": {"yaw": 0.02, "yaw_rate": 0.01}}]}})


def _stream(seed: int, error: str, duration: float = 120.0, bias: float = 0.004,
            scale: float = 1.02) -> Stream:
    """A 50 Hz gyro (white 0.005 rad/s, a constant ``bias`` and ``scale``) and a 50 Hz heading
    whose error is 'gm' (Gauss-Markov, sigma 0.005 rad, tau 2 s, and the samples' own white
    0.0003 rad), 'walk' (a random walk of 0.005 rad/sqrt(s)), 'drift' (its rate a random walk
    of 0.002 rad/s/sqrt(s), with the samples' own white 0.0003 rad) or 'white' (0.005 rad)."""
    rng = np.random.default_rng(seed)
    dt = 0.02
    rho = math.exp(-dt / 2.0)
    e, rate, yaw, out = 0.0, 0.0, 0.0, []
    for k in range(int(duration / dt)):
        t = k * dt
        w = 0.4 * math.sin(0.3 * t) + 0.2 * math.sin(1.1 * t)
        yaw += w * dt
        if error == "gm":
            e = rho * e + math.sqrt(1 - rho * rho) * rng.normal(0.0, 0.005)
            err = e + rng.normal(0.0, 0.0003)
        elif error == "drift":
            rate += rng.normal(0.0, 0.002 * math.sqrt(dt))
            e += rate * dt
            err = e + rng.normal(0.0, 0.0003)
        elif error == "walk":
            e += rng.normal(0.0, 0.005 * math.sqrt(dt))
            err = e
        else:
            err = rng.normal(0.0, 0.005)
        out.append(GyroYawRate(t, scale * w + bias + rng.normal(0.0, 0.005), 2.5e-5, "/imu"))
        out.append(Heading(t, (yaw + err + math.pi) % (2 * math.pi) - math.pi, 4e-4, "/imu"))
        if k % 5 == 0:
            out.append(WheelOdometry(t, 1.0, None, 0.0025, 0.0, "/odom"))
    return Stream(measurements=out)


def test_gauss_markov_error_is_measured():
    fit = measure(_cfg(), _stream(1, "gm"), "/imu")
    assert fit.tau == pytest.approx(2.0, rel=0.35)
    assert fit.sigma == pytest.approx(0.005, rel=0.25)
    assert fit.white < 0.2 * fit.sigma  # the scatter the white likelihood takes for the noise


@pytest.mark.parametrize("error", ["walk", "white"])
def test_no_correlation_time_for_a_walk_or_white_error(error):
    fit = measure(_cfg(), _stream(2, error), "/imu")
    assert fit.tau is None and fit.reason


def test_a_walk_wanders_alike_at_every_scale_a_drift_faster_at_long_lags():
    """sqrt(D(L) / L): a walk's density at every lag (its shortest lag adds nothing here: no
    white part), a drift whose rate walks grows with the lag and is said as such."""
    walk = measure(_cfg(), _stream(2, "walk"), "/imu")
    short, long_, lag = walk.wander
    assert short == pytest.approx(0.005, rel=0.25) and long_ == pytest.approx(0.005, rel=0.5)
    assert lag == pytest.approx(15.0, rel=0.05) and not drifts(walk.wander)
    assert "wanders" not in walk.reason
    drift = measure(_cfg(), _stream(2, "drift"), "/imu")
    assert drifts(drift.wander) and drift.tau is None
    assert f"at {drift.wander[1]:.2g} over 15 s" in drift.reason


def test_no_gyro_no_measurement():
    cfg = parse_config({"sensors": {"imu": [{"topic": "/imu", "use": ["yaw"]}]}})
    assert measure(cfg, _stream(1, "gm", duration=20.0), "/imu") is None


def test_tune_sets_the_measured_time_before_the_search():
    cfg, stream = _cfg(), _stream(1, "gm")
    ps = {p.key: p for p in parameters(cfg, stream)}
    p = ps["sensors.imu[0].correlation_time"]
    assert p.kind == "corr" and p.source == "measured" and p.before == 0.0
    assert p.start == pytest.approx(2.0, rel=0.35)
    params = list(ps.values())
    ap = Applier(cfg, stream, params)
    ap.apply([q.start for q in params])
    assert cfg.sensor("/imu").correlation_time == p.start
    ap.apply([None] * len(params))
    assert cfg.sensor("/imu").correlation_time == 0.0
    white = {q.key: q for q in parameters(cfg, _stream(2, "white"))}
    assert white["sensors.imu[0].correlation_time"].source == "config"


@pytest.mark.parametrize("error", ["drift", "walk"])
def test_tune_says_when_the_offset_walk_fits_only_the_samples_scale(error):
    """A tuned heading_offset_walk under a drift that wanders 7x faster at 15 s than from one
    sample to the next is said to fit the samples' scale (said, not changed); under a walk,
    whose every lag states the same density, nothing is said."""
    from types import SimpleNamespace

    from ddfuse.evaluation.tune_params import Param
    from ddfuse.evaluation.tune_result import Tuned, TuneResult
    from ddfuse.evaluation.tune_rules import drifting_heading_caveat

    cfg = parse_config({"sensors": {"imu": [{"topic": "/imu", "use": ["yaw", "yaw_rate"],
                                             "heading_offset": "estimate"}]}})
    p = Param("sensors.imu[0].noise.heading_offset_walk", "/imu heading_offset_walk", 0.01,
              None, "default", "rad/sqrt(s)", "/imu", "walk", "heading_offset_walk")
    result = TuneResult("ekf", [Tuned(p, 0.0034, "tuned")])
    drifting_heading_caveat(SimpleNamespace(cfg=cfg, stream=_stream(2, error)), result)
    said = result.tuned[0].reason
    assert ("not the heading's drift over a GPS outage" in said) == (error == "drift"), said
    assert result.tuned[0].value == 0.0034
