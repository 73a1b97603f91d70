"""``ddfuse tune`` on every heading sensor kind, not the IMU's alone: a magnetometer's heading
noise (as ``noise.yaw``, rad), its correlation time and heading-offset walk are parameters, set
in the stream as the reader would, and tuned."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.measurements import Heading
from ddfuse.evaluation.cli import main
from ddfuse.evaluation.tune import tune
from ddfuse.evaluation.tune_params import Applier, parameters


@pytest.fixture(scope="module")
def mag_bag(tmp_path_factory):
    bag = tmp_path_factory.mktemp("tune_mag") / "mag.bag"
    assert main(["simulate", "husky-magnetometer", "--seed", "2", "--duration", "60",
                 "-o", str(bag)]) == 0
    return bag, bag.with_suffix(".yaml")


def _mag_sigma(stream) -> float:
    """The magnetometer's true per-sample heading sigma (rad): what the reader made of the
    config's true field noise (T) over each sample's horizontal field."""
    v = [m.var for m in stream.measurements if type(m) is Heading and m.sensor == "/imu/mag"]
    return math.sqrt(float(np.median(v)))


def test_a_magnetometer_has_its_heading_noise_and_correlation_time(mag_bag):
    bag, yaml = mag_bag
    cfg = load_config(yaml)
    cfg.sensor("/imu/mag").heading_offset = "estimate"
    stream = read_stream(bag, cfg)
    params = {p.key: p for p in parameters(cfg, stream)}
    yaw = params["sensors.magnetometer[0].noise.yaw"]
    # the config states the field (T), not yaw: the search starts from the messages' own
    assert yaw.before is None and yaw.source == "messages"
    assert yaw.start == pytest.approx(_mag_sigma(stream))
    assert params["sensors.magnetometer[0].correlation_time"].kind == "corr"
    assert params["sensors.magnetometer[0].noise.heading_offset_walk"].kind == "walk"
    assert "sensors.magnetometer[0].noise.gyro_bias_walk" not in params  # no gyro in it


def test_the_applier_sets_and_restores_the_magnetometer_headings(mag_bag):
    bag, yaml = mag_bag
    cfg = load_config(yaml)
    stream = read_stream(bag, cfg)
    params = parameters(cfg, stream)
    k = next(i for i, p in enumerate(params) if p.key == "sensors.magnetometer[0].noise.yaw")
    mags = [m for m in stream.measurements if type(m) is Heading and m.sensor == "/imu/mag"]
    read = [m.var for m in mags]
    ap = Applier(cfg, stream, params)
    values = [None] * len(params)
    values[k] = 0.03
    ap.apply(values)
    assert all(m.var == pytest.approx(0.03**2) for m in mags)
    assert cfg.sensor("/imu/mag").noise["yaw"] == 0.03
    ap.apply([None] * len(params))
    assert [m.var for m in mags] == read and "yaw" not in cfg.sensor("/imu/mag").noise


@pytest.mark.slow
def test_tune_recovers_the_magnetometer_noise_from_3x_off(mag_bag):
    bag, yaml = mag_bag
    cfg = load_config(yaml)
    stream = read_stream(bag, cfg)
    truth = _mag_sigma(stream)
    result = tune(cfg, stream, start={"sensors.magnetometer[0].noise.yaw": 3.0 * truth},
                  jobs=1)
    got = next(t for t in result.tuned if t.param.key == "sensors.magnetometer[0].noise.yaw")
    assert got.status == "tuned"
    # ~1 500 magnetometer samples in 60 s: a sigma's relative standard error ~0.02, the fit's
    # own +- ~0.03 where it shares the heading with the IMU's yaw and the gyro
    assert abs(math.log(got.value / truth)) < 0.2, (got.value, truth)
