"""evaluation.tune_whiteness: the autocorrelation figures of a sensor's normalised innovations
against an AR(1) sequence's known ones, white sequences not reported, and the log's filter."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.estimation.estimator import Innovation
from ddfuse.evaluation.tune_whiteness import (
    MIN_CORRELATION,
    autocorrelation,
    coarse_factor,
    integrated_time,
    whiteness,
)


def _ar1(phi: float, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    e = rng.standard_normal(n) * math.sqrt(1.0 - phi * phi)
    z = np.empty(n)
    z[0] = rng.standard_normal()
    for k in range(1, n):
        z[k] = phi * z[k - 1] + e[k]
    return z


def _log(z: np.ndarray, scale: float = 0.01, period: float = 1.0 / 30.0,
         sensor: str = "/imu", kind: str = "heading") -> list[Innovation]:
    # each innovation with its own S: the figures must not depend on it
    s = scale ** 2 * (1.0 + 0.5 * np.sin(np.arange(len(z))))
    return [Innovation(k * period, sensor, kind, np.array([zk * math.sqrt(sk)]),
                       np.array([[sk]]), float(zk * zk), True)
            for k, (zk, sk) in enumerate(zip(z, s, strict=True))]


@pytest.mark.parametrize("phi", [0.5, 0.8])
def test_ar1_figures_recovered(phi):
    """An AR(1) of coefficient phi: rho_1 = phi, tau = (1 + phi) / (1 - phi), g(m) its sum."""
    z = _ar1(phi, 40_000, seed=3)
    (w,) = whiteness(_log(z), {("/imu", "heading"): 0.4})
    assert not w.white
    assert w.rho1 == pytest.approx(phi, abs=0.02)
    assert w.tau == pytest.approx((1 + phi) / (1 - phi), rel=0.1)
    assert w.period == pytest.approx(1.0 / 30.0)
    ((m, g),) = w.coarse.items()
    assert m == 12
    exact = 1.0 + 2.0 * sum((1 - k / m) * phi ** k for k in range(1, m))
    assert g == pytest.approx(exact, rel=0.1)
    assert "not white" in w.describe() and "12 samples" in w.describe()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_white_innovations_pass(seed):
    z = np.random.default_rng(seed).standard_normal(12_000)
    (w,) = whiteness(_log(z), {("/imu", "heading"): 0.4})
    assert w.white
    assert abs(w.rho1) < 3.0 / math.sqrt(len(z))
    assert w.tau == pytest.approx(1.0, abs=0.3)
    assert w.coarse[12] == pytest.approx(1.0, abs=0.3)
    assert w.describe().endswith("white enough")


def test_small_correlation_is_white_enough():
    """rho_1 = 0.05 is significant over 40 000 samples but under MIN_CORRELATION: not
    reported."""
    (w,) = whiteness(_log(_ar1(0.05, 40_000, seed=4)))
    assert 0.03 < w.rho1 < 0.07
    assert w.white


def test_filter_and_grouping():
    """Rejected, multi-dimensional and non-positive-S entries are left out; sensors under
    MIN_SAMPLES are not reported; each (sensor, kind) on its own."""
    a = _log(_ar1(0.6, 500, seed=5), sensor="/a")
    b = _log(np.random.default_rng(6).standard_normal(500), sensor="/b", kind="gyro")
    rej = [Innovation(k, "/a", "heading", np.array([50.0]), np.array([[1.0]]), 2500.0, False)
           for k in range(0, 500, 2)]
    two = [Innovation(k, "/a", "gps", np.array([1.0, 1.0]), np.eye(2), 2.0, True)
           for k in range(300)]
    bad = [Innovation(k, "/a", "heading", np.array([1.0]), np.array([[0.0]]), 0.0, True)
           for k in range(50)]
    few = _log(np.ones(99), sensor="/c")
    out = {(w.sensor, w.kind): w for w in whiteness(a + b + rej + two + bad + few)}
    assert set(out) == {("/a", "heading"), ("/b", "gyro")}
    assert out["/a", "heading"].n == 500
    assert not out["/a", "heading"].white
    assert out["/b", "gyro"].white
    assert out["/a", "heading"].coarse == {}


def test_helpers():
    rho = autocorrelation(np.array([1.0, -1.0] * 50), 3)
    assert rho[0] == pytest.approx(-0.99, abs=0.01)
    assert integrated_time(np.zeros(10)) == pytest.approx(1.0)
    assert coarse_factor(np.array([0.5, 0.25]), 1) == 1.0
    assert coarse_factor(np.array([0.5, 0.25]), 2) == pytest.approx(1.5)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    from ddfuse.evaluation.cli import main

    bag = tmp_path_factory.mktemp("white") / "husky.bag"
    assert main(["simulate", "husky", "--seed", "2", "--duration", "60", "-o", str(bag)]) == 0
    return bag, bag.with_suffix(".yaml")


def test_check_reports_a_smooth_compass_and_not_a_white_one(sim):
    """tune's check at the config's true values: the simulator's white compass passes; the same
    compass with a smooth (AR(1), 1 s at its 30 Hz) error of its stated sigma added is
    reported, with the over-confidence of the smoothers' keyframe average (GPS 2.5 Hz: 12
    samples) well over 1, and the other sensors stay white."""
    from ddfuse.estimation.bags import read_stream
    from ddfuse.estimation.config import load_config
    from ddfuse.estimation.measurements import Heading
    from ddfuse.evaluation.tune import check
    from ddfuse.evaluation.tune_params import parameters

    bag, yaml = sim
    cfg = load_config(yaml)
    stream = read_stream(bag, cfg)
    params = parameters(cfg, stream)
    white = check(cfg, stream, [None] * len(params), estimator="ekf", params=params)
    heads = [m for m in stream.measurements if type(m) is Heading]
    assert len(heads) > 1000
    got = {(w.sensor, w.kind): w for w in white.whiteness}
    key = (heads[0].sensor, "heading")
    assert got[key].white, got[key].describe()
    assert got[key].coarse and all(0.5 < g < 1.6 for g in got[key].coarse.values())
    sigma = math.sqrt(heads[0].var)
    err = _ar1(math.exp(-1.0 / 30.0), len(heads), seed=7) * sigma
    for m, e in zip(heads, err, strict=True):
        m.yaw += e
    smooth = check(cfg, stream, [None] * len(params), estimator="ekf", params=params)
    bad = {(w.sensor, w.kind): w for w in smooth.whiteness}
    assert not bad[key].white
    assert bad[key].rho1 > 2 * MIN_CORRELATION and bad[key].tau > 5.0
    assert max(bad[key].coarse.values()) > 3.0
    assert [k for k, w in bad.items() if not w.white] == [key]
