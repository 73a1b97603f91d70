"""Monte Carlo runner: the NEES band, the across-run aggregation, and short real runs."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from ddfuse.evaluation.cli.mc import main
from ddfuse.evaluation.montecarlo import (
    aggregate,
    draw_truth,
    monte_carlo,
    nees_band,
    run_seed,
)
from ddfuse.evaluation.montecarlo_results import MonteCarloRun, SeedRun
from scipy.stats import chi2


def test_nees_band_values():
    """Bar-Shalom et al. (2001) sec. 5.4.2's example: 50 runs of a 2-state filter give the
    95 % interval [1.5, 2.6]; and 20 runs of the 3-dof pose give [2.02, 4.17]."""
    lo, hi = nees_band(50, 2)
    assert (round(lo, 1), round(hi, 1)) == (1.5, 2.6)
    lo, hi = nees_band(20, 3)
    assert lo == pytest.approx(chi2.ppf(0.025, 60) / 20) and lo == pytest.approx(2.024, abs=1e-3)
    assert hi == pytest.approx(chi2.ppf(0.975, 60) / 20) and hi == pytest.approx(4.165, abs=1e-3)
    with pytest.raises(ValueError):
        nees_band(0, 3)


@pytest.mark.parametrize(("n_runs", "dim"), [(3, 3), (20, 3), (5, 2)])
def test_nees_band_covers_95_percent_of_consistent_averages(n_runs, dim):
    """The average over N runs of the NEES of a consistent filter (e ~ N(0, P)) falls inside
    the band 95 % of the time."""
    rng = np.random.default_rng(n_runs * 10 + dim)
    trials = 40000
    avg = (rng.standard_normal((trials, n_runs, dim)) ** 2).sum(axis=2).mean(axis=1)
    lo, hi = nees_band(n_runs, dim)
    inside = np.mean((avg >= lo) & (avg <= hi))
    assert inside == pytest.approx(0.95, abs=0.005)
    assert np.mean(avg < lo) == pytest.approx(0.025, abs=0.004)


def _seeds(*dicts) -> list[SeedRun]:
    return [SeedRun.from_json(d) for d in dicts]


def _fake_seed(seed, nees_by_tick, rmse, dr):
    """A seed's results as mc_<scenario>.json holds them (before the series are dropped)."""
    ticks = sorted(nees_by_tick)
    return {"seed": seed, "duration_s": 1.0, "dr_rmse_m": dr, "estimators": {
        "ekf": {"rmse_m": rmse, "nees_mean": float(np.mean([nees_by_tick[k] for k in ticks])),
                "runtime_s": 0.5, "error": None, "ticks": ticks,
                "nees": [nees_by_tick[k] for k in ticks]},
        "dr": {"rmse_m": dr, "nees_mean": math.nan, "runtime_s": 0.01, "error": None,
               "ticks": [], "nees": []}}}


def test_aggregate_averages_over_runs_then_ticks():
    """eps_bar(k) is the mean over runs at each tick both runs have (tick 3 only in one run is
    dropped), ANEES its mean over those ticks; RMSE and DR statistics per estimator."""
    a = _fake_seed(0, {0: 1.0, 1: 2.0, 2: 6.0, 3: 100.0}, rmse=0.2, dr=2.0)
    b = _fake_seed(1, {0: 3.0, 1: 4.0, 2: 2.0}, rmse=0.4, dr=1.0)
    s = aggregate(_seeds(a, b))
    e = s["ekf"]
    # eps_bar = (2, 3, 4) -> ANEES 3
    assert e.anees == pytest.approx(3.0)
    assert e.ticks == 3
    lo, hi = nees_band(2, 3)
    assert e.band == [lo, hi] and e.anees_in_band is True
    assert e.frac_ticks_in_band == pytest.approx(np.mean([lo <= v <= hi for v in (2, 3, 4)]))
    assert e.rmse_mean == pytest.approx(0.3) and e.rmse_max == pytest.approx(0.4)
    assert e.dr_rmse_mean == pytest.approx(1.5)
    assert e.ratio == pytest.approx(1.5 / 0.3) and e.ratio_min == pytest.approx(2.5)
    assert s["dr"].anees is None and s["dr"].ticks == 0


@pytest.mark.slow
def test_gps_scenario_beats_dead_reckoning_and_is_reproducible(tmp_path):
    """Two short husky runs in two processes: the unicycle EKF beats dead reckoning, its NEES
    is finite, and a seed run again gives identical numbers (a different seed does not)."""
    mc = monte_carlo("husky", [0, 1], ["ekf"], duration=40.0, jobs=2)
    e = mc.summary["ekf"]
    assert e.runs == 2 and not e.errors
    assert e.rmse_mean < 0.6  # GPS 1 m per axis, 2.5 Hz, fused with odometry and IMU
    assert e.dr_rmse_mean > e.rmse_mean
    assert 0.1 < e.anees < 30.0 and e.ticks > 300
    again = run_seed("husky", 1, ["ekf"], duration=40.0)
    first = next(r for r in mc.per_seed if r.seed == 1)
    assert again.estimators["ekf"].rmse_m == first.estimators["ekf"].rmse_m
    assert again.estimators["ekf"].nees_mean == first.estimators["ekf"].nees_mean
    assert again.dr_rmse_m == first.dr_rmse_m
    other = next(r for r in mc.per_seed if r.seed == 0)
    assert other.estimators["ekf"].rmse_m != first.estimators["ekf"].rmse_m
    # each estimator scored in its own error coordinates: the unicycle EKF's SE(2) ones
    assert first.estimators["ekf"].pose_error == "se2"
    assert first.estimators["dr"].pose_error == "world"
    # per_seed keeps no NEES series; the JSON reads back as the same run
    assert first.estimators["ekf"].nees is None and again.estimators["ekf"].nees
    d = json.loads(json.dumps(mc.to_json()))
    assert "nees" not in d["per_seed"][0]["estimators"]["ekf"]
    assert list(d) == ["scenario", "seeds", "duration_s", "estimators_requested", "fixed_truth",
                       "lag_s", "per_seed", "summary", "nees_convention"]
    # (as text: dead reckoning's NEES is NaN, which equals nothing)
    assert json.dumps(MonteCarloRun.from_json(d).to_json()) == json.dumps(mc.to_json())


def test_command_writes_json_and_markdown(tmp_path, capsys):
    assert main(["seed002", "--seeds", "1", "--duration", "20", "--jobs", "1",
                 "--estimators", "ekf_landmark", "-o", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "mc_seed002.json").read_text())
    assert set(data["summary"]) == {"ekf_landmark", "dr"}
    md = (tmp_path / "mc_seed002.md").read_text()
    assert "| ekf_landmark | 1 |" in md and md in capsys.readouterr().out


def test_runs_with_other_settings_do_not_overwrite_each_other(tmp_path):
    from ddfuse.evaluation.montecarlo import report_stem

    assert report_stem(MonteCarloRun(scenario="husky")) == "mc_husky"
    assert report_stem(MonteCarloRun(scenario="husky", fixed_truth=True, lag_s=30.0)) == \
        "mc_husky_fixed-truth_lag30"
    for extra in ([], ["--fixed-truth"], ["--lag", "2"]):
        assert main(["husky", "--seeds", "1", "--duration", "20", "--jobs", "1",
                     "--estimators", "ekf", "-o", str(tmp_path), *extra]) == 0
    names = sorted(p.name for p in tmp_path.glob("*.json"))
    assert names == ["mc_husky.json", "mc_husky_fixed-truth.json", "mc_husky_lag2.json"]


def test_command_errors_name_the_problem(capsys):
    assert main(["husky", "--seeds", "1", "--duration", "1"]) == 2
    assert "duration" in capsys.readouterr().err
    assert main(["husky", "--seeds", "1", "--duration", "20", "--estimators", "ekf_landmark"]) \
        == 2
    assert "ekf_landmark" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["no-such-scenario"])


def test_aggregate_off_grid_tracks_use_one_second_bins():
    """Keyframe tracks (lagged, batch) have samples at GPS stamps that differ per seed, so few
    10 Hz ticks are common to all runs; the runs are then compared in 1 s bins. Every sample
    has NEES 3, so the average must be 3 (it was ~0 when only the shared first tick counted)."""
    rng = np.random.default_rng(0)
    seeds = []
    for seed in range(5):
        ticks = np.unique(np.cumsum(rng.integers(3, 6, size=80)))  # ~2.5 Hz, off the grid
        seeds.append(_fake_seed(seed, {int(k): 3.0 for k in ticks}, rmse=0.2, dr=2.0))
    e = aggregate(_seeds(*seeds))["ekf"]
    assert e.anees == pytest.approx(3.0)
    assert e.ticks >= 25


def test_truth_is_drawn_per_seed_from_the_stated_priors():
    """The NEES test presumes the truth is a draw from the filters' prior: the true geometry
    from N(nominal, geometry_std^2), the initial pose error from N(0, GIVEN_POSE_STD^2), per
    seed. Standardised draws over 400 seeds: mean and variance inside their 99.9 % bounds."""
    from ddfuse.ekf_baseline import GIVEN_POSE_STD
    from ddfuse.evaluation.simulate import get_scenario

    sc0 = get_scenario("seed002")
    n = 400
    z = []
    for seed in range(n):
        sc, err = draw_truth(sc0, seed)
        g, nom, sd = sc.true_geometry, sc0.nominal_geometry, sc0.geometry_std
        z.append(((g.wheel_radius - nom.wheel_radius) / sd.wheel_radius,
                  (g.track_width - nom.track_width) / sd.track_width,
                  err[0] / GIVEN_POSE_STD[0], err[1] / GIVEN_POSE_STD[0],
                  err[2] / GIVEN_POSE_STD[1]))
    z = np.array(z)
    assert np.all(np.abs(z.mean(axis=0)) < 3.3 / math.sqrt(n))
    lo, hi = chi2.ppf([0.0005, 0.9995], n - 1) / (n - 1)
    assert np.all((z.var(axis=0, ddof=1) > lo) & (z.var(axis=0, ddof=1) < hi))
    assert abs(np.corrcoef(z.T)[0, 1]) < 3.3 / math.sqrt(n)
    assert draw_truth(sc0, 7) == draw_truth(sc0, 7)  # deterministic per seed


def test_run_seed_records_the_drawn_or_fixed_truth():
    from ddfuse.evaluation.simulate import get_scenario

    sc = get_scenario("seed002")
    drawn = run_seed("seed002", 3, ["ekf_landmark"], duration=10.0)
    want, err = draw_truth(get_scenario("seed002", 10.0), 3)
    assert drawn.true_geometry == [want.true_geometry.wheel_radius,
                                   want.true_geometry.track_width]
    assert drawn.initial_error == list(err) and any(err)
    fixed = run_seed("seed002", 3, ["ekf_landmark"], duration=10.0, fixed_truth=True)
    assert fixed.true_geometry == [sc.true_geometry.wheel_radius, sc.true_geometry.track_width]
    assert fixed.initial_error == [0.0, 0.0, 0.0]


def test_calibration_errors_against_the_simulated_truth():
    """The final calibration states against what the simulation drew: k_v, k_w of the drawn
    geometry, the IMU's heading offset (wrapped), the walking gyro bias at the state's time.
    An estimate that equals the truth has error 0; one 2 sigma off has z = 2."""

    from ddfuse.estimation.estimator import Estimate
    from ddfuse.evaluation.montecarlo import _calibration_errors, calibration_truth
    from ddfuse.evaluation.simulate import get_scenario, simulate

    sc, _ = draw_truth(get_scenario("husky", 20.0), 4)
    sim = simulate(sc, seed=4)
    truth = calibration_truth(sim)
    g, ng = sc.true_geometry, sc.nominal_geometry
    assert truth["k_v"] == g.wheel_radius / ng.wheel_radius
    assert truth["k_w"] == pytest.approx(truth["k_v"] * ng.track_width / g.track_width)
    t_end = sim.t0 + 15.0
    bias = float(np.interp(15.0, sim.imu.t, sim.imu.bias))
    assert bias != sc.imu.gyro_bias0  # it walked
    sd = np.array([1.0, 1.0, 1.0, 0.1, 0.1, 1e-3, 0.01, 0.004, 0.02])
    x = np.array([0.0, 0.0, 0.0, 1.0, 0.0, bias, sc.imu.heading_offset - 2 * math.pi,
                  truth["k_v"] + 2 * sd[7], truth["k_w"] - 0.5 * sd[8]])
    names = ("x", "y", "psi", "v", "w", "bg", "hoff", "k_v", "k_w")
    e = Estimate(t_end, (0.0, 0.0, 0.0), np.eye(3), x, np.diag(sd**2), names)
    got = _calibration_errors(sim, e)
    assert got["bg"].error == pytest.approx(0.0, abs=1e-15)
    assert got["hoff"].error == pytest.approx(0.0, abs=1e-12)
    assert got["k_v"].z == pytest.approx(2.0) and got["k_w"].z == pytest.approx(-0.5)
    seed002 = simulate(draw_truth(get_scenario("seed002", 10.0), 1)[0], seed=1)
    assert set(calibration_truth(seed002)) == {"k_v", "k_w"}  # no IMU there


def test_the_calibration_summary_leaves_out_runs_that_failed():
    a = _fake_seed(0, {0: 1.0}, rmse=0.2, dr=2.0)
    b = _fake_seed(1, {0: 3.0}, rmse=0.4, dr=1.0)
    a["estimators"]["ekf"]["calibration"] = {"k_w": {"error": 0.01, "z": 1.0}}
    b["estimators"]["ekf"]["calibration"] = {"k_w": {"error": -9e20, "z": -3e21}}
    b["estimators"]["ekf"]["error"] = "numerical breakdown at t=209.9"
    c = aggregate(_seeds(a, b))["ekf"].calibration["k_w"]
    assert c.n == 1 and c.error_mean == pytest.approx(0.01) and c.z_rms == 1.0


def _fake_mc(fixed_truth=False, lag_s=None, error=None) -> MonteCarloRun:
    """A two-seed run as monte_carlo returns it, without running anything."""
    a = _fake_seed(0, {0: 1.0}, rmse=0.2, dr=2.0)
    b = _fake_seed(1, {0: 3.0}, rmse=0.4, dr=1.0)
    for r in (a, b):
        r["estimators"]["ekf"]["calibration"] = {"bg": {"error": 1e-4, "z": 1.0},
                                                 "hoff": {"error": 1e-3, "z": 0.5}}
    b["estimators"]["ekf"]["error"] = error
    seeds = _seeds(a, b)
    return MonteCarloRun("husky", [0, 1], 1.0, None, fixed_truth, lag_s,
                         [r.lean() for r in seeds], aggregate(seeds), "x")


def test_markdown_records_fixed_truth_and_lag():
    """Two runs that differ only in --fixed-truth or --lag wrote the same header before."""
    from ddfuse.evaluation.montecarlo import to_markdown

    drawn, fixed = to_markdown(_fake_mc()), to_markdown(_fake_mc(fixed_truth=True))
    head = drawn.splitlines()[0]
    assert "drawn per seed" in head and "--fixed-truth" not in head
    assert "Truth fixed (--fixed-truth)" in fixed.splitlines()[0]
    assert "Smoother lag 10 s (the simulated config's)" in head
    assert "Smoother lag 5 s (--lag)" in to_markdown(_fake_mc(lag_s=5.0)).splitlines()[0]


def test_markdown_calibration_text_follows_fixed_truth_and_names_the_labels():
    """Under --fixed-truth nothing is drawn, so the calibration text must not say so; the
    table's state labels bg and hoff are explained with their units."""
    from ddfuse.evaluation.montecarlo import to_markdown

    def cal_text(md):
        return next(line for line in md.splitlines() if line.startswith("Calibration states"))

    fixed = cal_text(to_markdown(_fake_mc(fixed_truth=True)))
    assert "drawn" not in fixed and "the scenario's true geometry" in fixed
    assert "the geometry drawn for each seed" in cal_text(to_markdown(_fake_mc()))
    assert "hoff, the IMU's heading offset (rad)" in fixed
    assert "bg, the gyro bias (rad/s)" in fixed


def test_markdown_errors_go_below_the_table_not_into_it():
    """Every table row has the header's 12 cells; the error is listed after the table with its
    seed, on one line, and its estimator's row is marked."""
    from ddfuse.evaluation.montecarlo import to_markdown

    md = to_markdown(_fake_mc(error="numerical breakdown at t=209.9:\npose (1e9, 2e9, 0.1)"))
    lines = md.splitlines()
    start = lines.index(next(x for x in lines if x.startswith("| estimator | runs")))
    table = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        table.append(line)
    assert all(line.count("|") == 13 for line in table), table
    assert any(line.startswith("| ekf * |") for line in table)
    assert "- ekf, seed 1: numerical breakdown at t=209.9: pose (1e9, 2e9, 0.1)" in lines
    assert "errors:" not in md and "*" not in to_markdown(_fake_mc()).split("Calibration")[0]


def test_run_seed_reads_a_string_of_estimator_names_as_the_cli_does():
    from ddfuse.evaluation.montecarlo import run_seed

    r = run_seed("seed002", 1, "ekf_landmark", duration=20.0)
    assert set(r.estimators) == {"ekf_landmark", "dr"}
