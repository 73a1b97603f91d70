"""The ``urban`` scenario's GPS (evaluation/simulate/urban_gps.py): deterministic per seed, its
error statistics those UrbanGpsSpec states, settable, and the config written beside it."""

from dataclasses import replace

import numpy as np
import pytest
from ddfuse.estimation.config import parse_config
from ddfuse.evaluation.simulate import get_scenario, sim_config, simulate
from ddfuse.evaluation.simulate.scenarios import UrbanGpsSpec
from ddfuse.evaluation.simulate.urban_gps import CANYON, MULTIPATH, NLOS, OPEN, urban_errors


def _errors(seed=0, duration=10000.0, **kw):
    u = UrbanGpsSpec(**kw)
    tm = np.arange(0.0, duration, 0.2)
    return tm, u, urban_errors(tm, duration, u, np.random.default_rng(seed))


def test_urban_fixes_are_deterministic_per_seed():
    a, b, c = simulate("urban", 4, 120.0), simulate("urban", 4, 120.0), simulate("urban", 5, 120.0)
    np.testing.assert_array_equal(a.gps.enu, b.gps.enu)
    np.testing.assert_array_equal(a.gps.environment, b.gps.environment)
    assert not np.array_equal(a.gps.enu[:50], c.gps.enu[:50])


def test_error_statistics_are_the_specs():
    """Over 10 000 s: canyon time near canyon_fraction, the open sky's error per axis near
    open_std (its wander correlated over base_tau_s), multipath bursts within burst_range of
    the truth (give or take their wobble and the canyon's wander), NLOS jumps within nlos_range,
    bridges removing fixes at about bridge_rate x mean length."""
    tm, u, e = _errors()
    canyon = e.label != OPEN
    assert abs(canyon.mean() - u.canyon_fraction) < 0.1
    op = e.error[e.label == OPEN]
    assert abs(np.sqrt(np.mean(op ** 2)) - u.open_std) < 0.25 * u.open_std
    # correlated: fix-to-fix changes far smaller than the error itself
    d = np.diff(e.error[:, 0])[(e.label[1:] == OPEN) & (e.label[:-1] == OPEN)]
    assert np.std(d) < 0.2 * u.open_std
    mp = np.hypot(*e.error[e.label == MULTIPATH].T)
    assert np.median(mp) > u.burst_range[0] and np.median(mp) < u.burst_range[1] + 5.0
    nl = np.hypot(*e.error[e.label == NLOS].T)
    assert np.median(nl) > u.nlos_range[0] - 5.0
    assert 0.005 < (e.label == NLOS).sum() / canyon.sum() < 0.15
    expected = u.bridge_rate * np.mean(u.bridge_length_s)
    assert 0.5 * expected < e.bridge.mean() < 1.5 * expected


def test_statistics_are_settable():
    _, _, open_only = _errors(duration=2000.0, canyon_fraction=0.0, bridge_rate=0.0)
    assert np.all(open_only.label == OPEN) and not open_only.bridge.any()
    _, _, more = _errors(duration=5000.0, canyon_fraction=0.8)
    assert (more.label != OPEN).mean() > 0.6
    assert np.any(more.label == CANYON)
    with pytest.raises(ValueError, match="canyon_fraction"):
        UrbanGpsSpec(canyon_fraction=1.0)
    with pytest.raises(ValueError, match="burst_range"):
        UrbanGpsSpec(burst_range=(40.0, 10.0))


def test_the_scenario_and_its_config():
    """A car (5-15 m/s for most of the drive), its fixes' stated 1.5 m optimistic against the
    open sky's 2 m, a gyro alone (no heading), the open sky's wander as correlation_time, the
    slip a car has; and the other scenarios' GPS draws unchanged (no environment)."""
    res = simulate("urban", 1, 300.0)
    v = res.truth.v[res.truth.t > 10.0][:-1000]
    assert np.percentile(v, 5) > 4.0 and np.percentile(v, 95) < 16.0
    cfg = sim_config(res)
    gps = cfg["sensors"]["gps"][0]
    assert gps["noise"]["horizontal"] == 1.5 < res.scenario.gps.urban.open_std
    assert gps["correlation_time"] == res.scenario.gps.urban.base_tau_s
    imu = cfg["sensors"]["imu"][0]
    assert imu["use"] == ["yaw_rate"] and "heading_offset" not in imu and "yaw" not in imu["noise"]
    assert cfg["robot"]["slip"] == {"longitudinal": 0.05, "lateral": 0.02, "heading": 0.01}
    parsed = parse_config(cfg)
    assert parsed.sensor("/imu/data").use == ("yaw_rate",)
    husky = simulate(replace(get_scenario("husky"), duration=30.0), 1)
    assert husky.gps.environment is None and sim_config(husky)["robot"]["slip"]["lateral"] == 0.0


def test_the_configs_header_says_what_the_urban_fixes_were():
    """The header of the config beside an urban bag counts this draw's fixes by environment
    (they add up to every fix) and names the model for them; the generic 'outliers 0.0' of the
    other scenarios, which an urban bag's fixes belie, is not said."""
    import re

    from ddfuse.evaluation.simulate.sidecars import truth_comment

    res = simulate("urban", 3, 300.0)
    text = " ".join(line[2:] for line in truth_comment(res, "ros1").splitlines())
    m = re.search(r"of (\d+) fixes (\d+) in open sky .*?, (\d+) in street canyons .*?, (\d+) in "
                  r"multipath bursts .*?, (\d+) NLOS", text)
    assert m, text
    n, *parts = map(int, m.groups())
    assert n == len(res.gps.t) == sum(parts) and parts[2] + parts[3] > 0
    assert "gps: {model: dcs}" in text and "outliers" not in text
    gps = truth_comment(res, "ros1").split("# GPS: ")[1].splitlines()
    assert len(gps) > 1 and all(len(line) <= 100 for line in gps)  # wrapped
