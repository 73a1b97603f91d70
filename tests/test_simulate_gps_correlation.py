"""Time-correlated GPS errors in the simulator (``GpsSpec.correlation_s``, scenario
``husky-multipath``).

The bounds are derived, not tuned. For a stationary AR(1) sequence of n samples with lag-one
coefficient a (here a = exp(-dt/tau) on the nominal grid dt), the sample variance has
var(s^2) = (2 sigma^4 / n) (1 + a^2) / (1 - a^2) to first order, i.e. the samples count as
n_eff = n (1 - a^2) / (1 + a^2) independent ones, and sd(s / sigma) = 1 / sqrt(2 n_eff).
Bartlett's formula gives the sample autocorrelation at lag L samples, where the true one is
rho_L = a^L:  n var(r_L) = (1 + a^2)(1 + a^(2L)) / (1 - a^2) - 2 L a^(2L).
Every check allows 5 standard errors (two-sided p ~ 6e-7): a wrong model misses by far more
(white errors: r_L = 0, not exp(-1); the innovation scale sqrt(1 - a^2) left out: std x 8.7).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from ddfuse.evaluation import simulate as sim
from ddfuse.evaluation.cli import main
from ddfuse.evaluation.simulate.gps import gauss_markov
from ddfuse.evaluation.simulate.sensors import sample_times
from ddfuse.evaluation.simulate.sidecars import truth_comment

TAU = 4.0  # s: correlation time of the long statistics run (L = 10 fixes at 2.5 Hz)
DURATION = 16_000.0  # s: n = 40 000 fixes, n_eff = 3 990 for the std (5 sd: 5.6 %)


def _old_white_gps(sc, truth, seed):
    """The simulator's GPS before correlation_s existed, written out again: white noise of the
    stated std from the first draw of the 'gps' stream, then dropouts, outliers, outages."""
    spec = sc.gps
    rng = sim._rng(seed, "gps")
    tm = sample_times(rng, spec.rate, sc.duration)
    n = len(tm)
    noise = rng.standard_normal((n, 3)) * [spec.horizontal_std, spec.horizontal_std,
                                           spec.vertical_std]
    drop = rng.uniform(size=n) < spec.dropout_prob
    out = rng.uniform(size=n) < spec.outlier_prob
    mag = rng.uniform(*spec.outlier_range, size=n)
    ang = rng.uniform(-np.pi, np.pi, size=n)
    x, y, _, _, _ = truth.at(tm)
    enu = np.stack([x, y, np.zeros(n)], axis=1) + noise
    enu[:, 0] += np.where(out, mag * np.cos(ang), 0.0)
    enu[:, 1] += np.where(out, mag * np.sin(ang), 0.0)
    keep = ~drop & (tm + spec.delay <= sc.duration)
    for a, b in spec.outages:
        keep &= ~((tm >= a) & (tm < b))
    return tm[keep], enu[keep], out[keep]


@pytest.mark.parametrize("name", ["husky", "gps-outage", "long"])
@pytest.mark.parametrize("seed", [1, 2])
def test_white_gps_is_unchanged(name, seed):
    """correlation_s = 0 (every scenario but husky-multipath) is the old white noise, bit for
    bit: the same draws, the same arithmetic."""
    res = sim.simulate(name, seed=seed, duration=600.0 if name == "long" else None)
    assert res.scenario.gps.correlation_s == 0.0
    tm, enu, out = _old_white_gps(res.scenario, res.truth, seed)
    np.testing.assert_array_equal(res.gps.t_measured, tm)
    np.testing.assert_array_equal(res.gps.enu, enu)
    np.testing.assert_array_equal(res.gps.outlier, out)
    assert out.any() == (res.scenario.gps.outlier_prob > 0)


def _errors(res):
    """GPS error (N, 3) against the truth at the measurement time, outliers excluded."""
    g = res.gps
    good = ~g.outlier
    return g.t_measured[good], (g.enu - g.true_enu)[good]


def _lag_pairs(t, lag, period):
    """Index pairs (i, j) with t[j] - t[i] = lag (to a tenth of the period)."""
    j = np.searchsorted(t, t + lag - 0.1 * period)
    j = np.minimum(j, len(t) - 1)
    ok = np.abs(t[j] - t - lag) < 0.1 * period
    return np.flatnonzero(ok), j[ok]


@pytest.fixture(scope="module")
def correlated():
    sc = sim.get_scenario("husky-multipath", duration=DURATION)
    # only the GPS is looked at: no IMU, a coarser truth grid (the error is measured against
    # the truth at each fix's time, whatever the grid), to keep the test under a second
    sc = dataclasses.replace(sc, gps=dataclasses.replace(sc.gps, correlation_s=TAU), imu=None,
                             substep=0.05)
    return sim.simulate(sc, seed=5)


def test_correlated_errors_have_the_stated_std_and_correlation_time(correlated):
    res = correlated
    spec = res.scenario.gps
    dt = 1.0 / spec.rate
    a = math.exp(-dt / TAU)
    t, e = _errors(res)
    n = len(t)
    assert n > 0.98 * DURATION * spec.rate  # 1 % dropouts, no outliers in this scenario
    n_eff = n * (1 - a * a) / (1 + a * a)
    sd_std = 1.0 / math.sqrt(2.0 * n_eff)  # of s / sigma
    L = int(round(TAU / dt))
    rho = a**L
    assert rho == pytest.approx(math.exp(-1.0))
    sd_rho = math.sqrt(((1 + a * a) * (1 + rho * rho) / (1 - a * a) - 2 * L * rho * rho) / n)
    # the mean of an AR(1) sequence: var = sigma^2 (1 + a) / ((1 - a) n)
    sd_mean = math.sqrt((1 + a) / ((1 - a) * n))
    i, j = _lag_pairs(t, TAU, dt)
    assert len(i) > 0.97 * n
    for axis, std in enumerate((spec.horizontal_std, spec.horizontal_std, spec.vertical_std)):
        x = e[:, axis]
        s = float(np.std(x, ddof=1))
        assert abs(s / std - 1.0) < 5 * sd_std, f"axis {axis}: std {s:.4f} vs {std}"
        assert abs(x.mean()) < 5 * sd_mean * std, f"axis {axis}: mean {x.mean():.4f}"
        xc = x - x.mean()
        r = float(np.mean(xc[i] * xc[j]) / np.mean(xc * xc))
        assert abs(r - rho) < 5 * sd_rho, f"axis {axis}: lag-tau autocorrelation {r:.4f}"
    # the bound tells tau from tau / 2 or 2 tau (exp(-2), exp(-0.5): 0.23 away)
    assert 5 * sd_rho < 0.1


def test_husky_multipath_errors_at_their_own_tau():
    """The scenario as shipped (tau 30 s), over 4000 s (n_eff 133: the bounds are wide), still
    tells its correlation from white noise and keeps husky's std."""
    res = sim.simulate("husky-multipath", seed=3, duration=4000.0)
    spec = res.scenario.gps
    tau, dt = spec.correlation_s, 1.0 / spec.rate
    assert tau > 0
    a = math.exp(-dt / tau)
    t, e = _errors(res)
    n = len(t)
    L = int(round(tau / dt))
    rho = a**L
    sd_rho = math.sqrt(((1 + a * a) * (1 + rho * rho) / (1 - a * a) - 2 * L * rho * rho) / n)
    sd_std = math.sqrt((1 + a * a) / (1 - a * a) / (2.0 * n))
    i, j = _lag_pairs(t, L * dt, dt)
    for axis, std in enumerate((spec.horizontal_std, spec.horizontal_std, spec.vertical_std)):
        xc = e[:, axis] - e[:, axis].mean()
        assert abs(np.std(e[:, axis], ddof=1) / std - 1.0) < 5 * sd_std
        r = float(np.mean(xc[i] * xc[j]) / np.mean(xc * xc))
        assert abs(r - rho) < 5 * sd_rho, f"axis {axis}: {r:.3f} vs {rho:.3f} +- {sd_rho:.3f}"
        # one fix later the error is nearly the same (white: correlation 0)
        i1, j1 = _lag_pairs(t, dt, dt)
        assert np.mean(xc[i1] * xc[j1]) / np.mean(xc * xc) > 0.95


def test_gauss_markov_on_an_irregular_grid():
    """The exact discretisation over uneven spacings: across M independent sequences on the
    grid 0, 0.3 tau, 2 tau, every sample has the stated std and corr(e_i, e_k) =
    exp(-|t_k - t_i| / tau). For M independent pairs sd(r) = (1 - rho^2) / sqrt(M) and
    sd(s / sigma) = 1 / sqrt(2 M)."""
    tau, m = 7.0, 40_000
    t = np.array([0.0, 0.3, 2.0]) * tau
    w = np.random.default_rng(0).standard_normal((3, m))
    e = gauss_markov(t, w, np.full(m, 1.5), tau)
    np.testing.assert_array_equal(e[0], 1.5 * w[0])  # e_0 from the stationary distribution
    for k in range(3):
        assert abs(np.std(e[k]) / 1.5 - 1) < 5 / math.sqrt(2 * m)
    for i, k in ((0, 1), (1, 2), (0, 2)):
        rho = math.exp(-(t[k] - t[i]) / tau)
        r = float(np.corrcoef(e[i], e[k])[0, 1])
        assert abs(r - rho) < 5 * (1 - rho * rho) / math.sqrt(m), (i, k, r, rho)


def test_dropped_fixes_do_not_change_the_others():
    """Dropouts and outages remove samples from the process; the kept fixes' errors are those
    of the run without them."""
    base = sim.get_scenario("husky-multipath", duration=300.0)
    full = dataclasses.replace(base, gps=dataclasses.replace(base.gps, dropout_prob=0.0))
    holey = dataclasses.replace(base, gps=dataclasses.replace(
        base.gps, dropout_prob=0.3, outages=((100.0, 160.0),)))
    a, b = sim.simulate(full, seed=9), sim.simulate(holey, seed=9)
    assert len(b.gps.t) < 0.6 * len(a.gps.t)
    idx = np.searchsorted(a.gps.t_measured, b.gps.t_measured)
    np.testing.assert_array_equal(a.gps.t_measured[idx], b.gps.t_measured)
    np.testing.assert_array_equal(a.gps.enu[idx], b.gps.enu)


def test_husky_multipath_is_husky_with_correlated_gps(tmp_path):
    """Same drive, sensors, fixes and stated noise as husky; only the GPS errors differ (the
    first is the same draw: e_0 is the stationary, i.e. white, error). The config states husky's
    GPS noise plus the correlation time (the true error model); its header names it too."""
    a, b = sim.simulate("husky", seed=4), sim.simulate("husky-multipath", seed=4)
    assert b.scenario.duration == a.scenario.duration
    assert dataclasses.replace(b.scenario.gps, correlation_s=0.0) == a.scenario.gps
    assert dataclasses.replace(b.scenario, name="husky", description=a.scenario.description,
                               gps=a.scenario.gps) == a.scenario
    np.testing.assert_array_equal(a.truth.x, b.truth.x)
    np.testing.assert_array_equal(a.imu.yaw_rate, b.imu.yaw_rate)
    np.testing.assert_array_equal(a.encoders.v, b.encoders.v)
    np.testing.assert_array_equal(a.gps.t, b.gps.t)
    np.testing.assert_array_equal(a.gps.enu[0], b.gps.enu[0])
    assert not np.allclose(a.gps.enu[1:], b.gps.enu[1:])
    ca, cb = sim.sim_config(a), sim.sim_config(b)
    assert "correlation_time" not in ca["sensors"]["gps"][0]
    assert cb["sensors"]["gps"][0].pop("correlation_time") == b.scenario.gps.correlation_s
    assert ca == cb
    bag = tmp_path / "m.bag"
    assert main(["simulate", "husky-multipath", "--duration", "20", "-o", str(bag)]) == 0
    head = (tmp_path / "m.yaml").read_text()
    assert f"correlation time {b.scenario.gps.correlation_s:g} s" in head
    assert "correlation" not in truth_comment(a, "ros1")


@pytest.mark.parametrize("bad", [-1.0, -1e-9, math.nan, math.inf])
def test_bad_correlation_time_is_refused(bad):
    with pytest.raises(ValueError, match=r"GpsSpec\.correlation_s must be .* >= 0"):
        sim.GpsSpec(correlation_s=bad)


def test_the_command_lines_offer_the_scenario(tmp_path, capsys):
    """ddfuse simulate and ddfuse mc take the name (mc gets as far as checking the duration)."""
    assert "husky-multipath" in sim.SCENARIOS
    with pytest.raises(SystemExit) as e:
        main(["simulate", "--help"])
    assert e.value.code == 0
    assert "husky-multipath:" in capsys.readouterr().out
    assert main(["mc", "husky-multipath", "--duration", "1", "-o", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "--duration 1" in err and "invalid choice" not in err
