"""An odometry input's noise from its own samples (``evaluation.tune_inputs``), and ``tune``
holding it there where the landmark EKF's innovations leave it to the slip."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config
from ddfuse.evaluation.tune import tune
from ddfuse.evaluation.tune_inputs import MIN_WINDOWS, sample_scatter

DATA = Path(__file__).resolve().parents[1] / "data"


def _drive(n: int = 3000, dt: float = 0.1, sigma: float = 0.1, seed: int = 0):
    """Wheel speeds (rad/s) of a smooth drive (about 5 rad/s, swinging by up to 2 rad/s with
    periods of 10-50 s) sampled at ``dt`` with white noise ``sigma``: (t, measured)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    f = rng.uniform(0.02, 0.1, 4)
    ph = rng.uniform(0, 2 * math.pi, 4)
    true = 5.0 + 0.5 * np.sin(2 * math.pi * f[:, None] * t + ph[:, None]).sum(axis=0)
    return t, true + sigma * rng.standard_normal(n)


@pytest.mark.parametrize("sigma", [0.02, 0.1, 0.5])
def test_the_white_noise_of_a_smooth_drive_is_recovered(sigma):
    t, x = _drive(sigma=sigma)
    sc = sample_scatter([(t, x)])
    assert sc.sigma is not None, sc.reason
    # 2998 overlapping windows; the MAD's relative standard error on ~750 independent ones is
    # ~0.045: 4 of them
    assert abs(math.log(sc.sigma / sigma)) < 0.18
    assert 0.0 < sc.se_log < 0.1


def test_two_wheels_pool_and_rest_is_left_out():
    t, left = _drive(seed=1)
    _, right = _drive(seed=2)
    left[:1000] = 0.0  # at rest: an encoder reads exactly 0
    right[:1000] = 0.0
    sc = sample_scatter([(t, left), (t, right)])
    assert sc.windows == 2 * (len(t) - 1000 - 3) + 2 * 3  # windows with any moving sample
    assert abs(math.log(sc.sigma / 0.1)) < 0.18


def test_held_values_give_no_noise():
    t = np.arange(3000) * 0.02
    x = np.repeat(np.random.default_rng(3).uniform(-0.5, 0.5, 60), 50)  # commands held 1 s
    sc = sample_scatter([(t, x)])
    assert sc.sigma is None and "held or quantised" in sc.reason


def test_differences_filled_by_the_motion_give_no_noise():
    t = np.arange(3000) * 0.1
    x = 3.0 * np.sin(2 * math.pi * 0.6 * t) + 0.01 * np.random.default_rng(4).standard_normal(
        3000)  # a 0.6 Hz swing sampled at 10 Hz: the differences are the motion's
    sc = sample_scatter([(t, x)])
    assert sc.sigma is None and "the motion, not the noise" in sc.reason


def test_too_few_samples_give_no_noise():
    t, x = _drive(n=MIN_WINDOWS // 2)
    assert sample_scatter([(t, x)]).sigma is None


def test_a_gap_is_not_read_as_noise():
    t, x = _drive(sigma=0.05)
    t2 = t.copy()
    t2[1500:] += 30.0  # 30 s without a message; the speed jumps over it
    x2 = x.copy()
    x2[1500:] += 4.0
    assert abs(math.log(sample_scatter([(t2, x2)]).sigma / 0.05)) < 0.18


@pytest.mark.slow
def test_tune_takes_the_wheels_noise_from_their_samples_not_twice_with_the_slip():
    """data/sample_seed002.bag states the true noise (wheel speeds 0.1 rad/s, no slip); started
    at 3x the wheels' noise, the landmark EKF's likelihood cannot tell the wheels from the
    slip: the wheels' own scatter gives them, and no slip is added beside them."""
    cfg = load_config(DATA / "sample_seed002.yaml")
    stream = read_stream(DATA / "sample_seed002.bag", cfg)
    result = tune(cfg, stream, start={"sensors.wheels[0].noise.speed": 0.3}, jobs=1)
    by_key = {t.param.key: t for t in result.tuned}
    wheels = by_key["sensors.wheels[0].noise.speed"]
    assert wheels.status == "tuned" and "own samples" in wheels.reason
    assert abs(wheels.value / 0.1 - 1.0) < 0.2
    heading = by_key["robot.slip.heading"]
    assert heading.status in ("not informed", "negligible"), (heading.status, heading.value)
    for key, truth in (("range", 0.1), ("bearing", 0.05)):
        t = by_key[f"sensors.landmarks[0].noise.{key}"]
        assert abs(t.value / truth - 1.0) < 0.2, (key, t.value)
