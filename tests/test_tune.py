"""``ddfuse tune``: maximum likelihood of the EKF's innovations on a simulated bag whose config
states the true noise, started 3x off; the written config; the command line."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config, parse_config_text
from ddfuse.evaluation.cli import main
from ddfuse.evaluation.tune import tune
from ddfuse.evaluation.tune_params import Applier, parameters
from ddfuse.evaluation.tune_result import Tuned, TuneResult
from ddfuse.evaluation.tune_scoring import (
    STOP_NLL,
    STOP_STEP,
    correlated_pairs,
    information,
    scoring,
)
from ddfuse.evaluation.tune_yaml import tuned_text

# The values the unicycle EKF's innovations inform on a simulated Husky drive (GPS 2.5 Hz,
# compass and gyro 30 Hz, odometry 10 Hz): the GPS's horizontal noise, the compass's, the
# odometry's yaw rate, and the gyro's once the twist's random walk (robot.twist_walk) is tuned
# with it (docs/design/tuning.md has every value's figures); the odometry's speed once the
# sensors' noise is fitted with the twist's rates (the drive ramps its speed from and to rest).
INFORMED = ("sensors.gps[0].noise.horizontal", "sensors.imu[0].noise.yaw",
            "sensors.odometry[0].noise.yaw_rate", "sensors.imu[0].noise.yaw_rate",
            "sensors.odometry[0].noise.v")
# Bound on |log(tuned / true)|: the fewest-sampled of them is the GPS, N = 2.5 Hz x 40 s = 100
# fixes; a standard deviation estimated from N Gaussian samples has a relative standard error
# of 1 / sqrt(2 N) = 0.071, and 4 of those (0.28) leaves a chance of 6e-5 of failing. The gyro
# shares its innovations' S with the twist walk: its standard error in the fit is 0.06 (the
# fit's own +-), so 4 of those is inside the same bound.
BOUND = 4.0 / math.sqrt(2 * 100)


@pytest.fixture(scope="module")
def sim_bag(tmp_path_factory):
    bag = tmp_path_factory.mktemp("tune") / "husky.bag"
    assert main(["simulate", "husky", "--seed", "3", "--duration", "40", "-o", str(bag)]) == 0
    return bag, bag.with_suffix(".yaml")


# 4x under, not 3x: the search first scales the measurement noise by 1, 3 or 9
# (tune.START_SCALES), and from exactly 1/3 the scan alone would land on the truth
@pytest.fixture(scope="module", params=[3.0, 0.25], ids=["3x_over", "4x_under"])
def tuned_sim(request, sim_bag):
    bag, yaml = sim_bag
    cfg = load_config(yaml)
    stream = read_stream(bag, cfg)
    truth = {p.key: p.before for p in parameters(cfg, stream)}
    start = {k: v * request.param for k, v in truth.items() if v}
    return truth, tune(cfg, stream, start=start, jobs=1, twist_rates=True), cfg, stream


@pytest.mark.slow
def test_tune_recovers_the_true_noise_from_3x_off(tuned_sim):
    truth, result, _, _ = tuned_sim
    got = {t.param.key: t for t in result.tuned}
    for key in INFORMED:
        assert got[key].status == "tuned", (key, got[key].reason)
        assert abs(math.log(got[key].value / truth[key])) < BOUND, (key, got[key].value,
                                                                   truth[key])


@pytest.mark.slow
def test_the_rates_fit_the_sensors_noise_and_stay_out_of_the_result(tuned_sim):
    _, result, cfg, _ = tuned_sim
    assert "the sensors' noise fitted with the twist's rates (speed_rate" in result.message
    assert not any("rate_rate" in t.param.key or t.param.key.endswith("speed_rate")
                   for t in result.tuned)
    assert cfg.robot.twist_walk == {}  # the first stage's rates put back with the rest


@pytest.mark.slow
def test_a_value_the_data_do_not_inform_stays_and_says_why(tuned_sim):
    # the simulated robot does not slip (slip 0 in its config) and the unicycle EKF does not
    # fuse the accelerometer: nothing in the innovations depends on either
    truth, result, _, _ = tuned_sim
    got = {t.param.key: t for t in result.tuned}
    for key in ("sensors.imu[0].noise.accel", "robot.slip.lateral"):
        assert got[key].status == "not informed"
        assert got[key].value == truth[key]
        assert "do not inform" in got[key].reason


@pytest.mark.slow
def test_tune_leaves_the_config_and_stream_as_read(tuned_sim):
    _, _, cfg, stream = tuned_sim
    assert cfg.sensor("/fix").noise == {"horizontal": 1.0, "vertical": 2.0}
    fix = next(m for m in stream.measurements if m.sensor == "/fix")
    assert fix.cov[0, 0] == 1.0


def test_applier_sets_and_restores_the_measurement_variances(sample_husky):
    cfg, stream = sample_husky
    params = parameters(cfg, stream)
    ap = Applier(cfg, stream, params)
    gyro = next(m for m in stream.measurements if type(m).__name__ == "GyroYawRate")
    was, slip = gyro.var, dict(cfg.robot.slip)
    vals = [None] * len(params)
    i = next(k for k, p in enumerate(params) if p.key == "sensors.imu[0].noise.yaw_rate")
    j = next(k for k, p in enumerate(params) if p.key == "robot.slip.heading")
    vals[i], vals[j] = 0.5, 0.25
    ap.apply(vals)
    assert gyro.var == 0.25 and cfg.robot.slip["heading"] == 0.25
    assert cfg.of_kind("imu")[0].noise["yaw_rate"] == 0.5
    ap.apply([None] * len(params))
    assert gyro.var == was and cfg.robot.slip == slip


def _result(cfg, stream) -> TuneResult:
    params = parameters(cfg, stream)
    tuned = []
    for p in params:
        if p.key == "sensors.imu[0].noise.yaw":
            tuned.append(Tuned(p, 0.0123456, "tuned"))
        elif p.key == "robot.slip.longitudinal":
            tuned.append(Tuned(p, 0.2, "at upper bound"))
        else:
            tuned.append(Tuned(p, p.before, "not informed", "no data"))
    return TuneResult("ekf", tuned)


def raw_sensor(text: str, kind: str) -> dict:
    import yaml

    return yaml.safe_load(text)["sensors"][kind][0]


def test_the_tuned_config_loads_keeps_the_original_keys_and_marks_the_values(tmp_path):
    from importlib.resources import files

    from ddfuse.data import configs

    src = files(configs) / "rl_husky_gps.yaml"
    text = src.read_text()
    cfg = load_config(src)
    from ddfuse.estimation.measurements import Stream

    out = tuned_text(text, _result(cfg, Stream([])), "rl_husky_gps.bag", "2026-12-02")
    path = tmp_path / "tuned.yaml"
    path.write_text(out)
    new = load_config(path)
    # the values not informed are not written: their keys stay as they were
    assert new.sensor("/imu/data").noise == {"yaw": 0.0123, "yaw_rate": 0.02}
    assert "noise" not in raw_sensor(out, "gps")
    assert new.robot.slip == {"longitudinal": 0.2}
    assert (new.robot.max_speed, new.robot.max_yaw_rate) == (1.5, 3.0)
    assert new.smoother.lag == 10.0 and new.sensor("/imu/data").heading_offset == "estimate"
    # the original's comments are kept, the tuned values are marked
    assert "The IMU is mounted with its y axis up" in out
    assert "What a Clearpath Husky can do" in out
    assert out.count("ddfuse tune, rl_husky_gps.bag, 2026-12-02") == 2
    import yaml

    raw = yaml.safe_load(text)
    assert set(yaml.safe_load(out)) == set(raw)


def _check(rmse: float | None, scale: float, held: float | None = None):
    """A ``Check`` of two sensors whose NIS is ``scale`` times chi-square(1) (0.01: Fail), with
    a hold-out NEES of ``held`` times chi-square(2) over 150 fixes where given."""
    from ddfuse.evaluation.consistency import SensorNis, summarize
    from ddfuse.evaluation.tune import Check

    rng = np.random.default_rng(0)
    v = scale * rng.chisquare(1, 2000)
    nis = {f"/s{i} v": SensorNis(f"/s{i}", "v", 2000, 0, summarize(v, 1)) for i in range(2)}
    nees = None if held is None else summarize(held * rng.chisquare(2, 150), 2)
    return Check(nis, rmse, holdout_nees=nees)


def test_a_tuned_config_that_predicts_the_holdout_worse_is_said_to():
    from ddfuse.evaluation.tune import holdout_worse

    said = holdout_worse(_check(3.606, 0.01), _check(5.825, 1.0), "window:150:210", "ekf")
    assert "window:150:210" in said and "3.606 -> 5.825 m" in said and "+62 %" in said
    assert "hold-out NEES" not in said  # none measured
    b, a = _check(3.606, 0.01, 3.4), _check(5.825, 1.0, 1.0)
    said = holdout_worse(b, a, "window:150:210", "ekf")
    assert (f"+62 %; its hold-out NEES {b.holdout_nees.mean:.2f} Fail -> "
            f"{a.holdout_nees.mean:.2f} Pass, expected 2") in said
    # within the 5 %, or under a centimetre, or with nothing to compare: nothing said
    assert holdout_worse(_check(3.606, 1), _check(3.78, 1), "every:5", "ekf") is None
    assert holdout_worse(_check(0.1, 1), _check(0.109, 1), "every:5", "ekf") is None
    assert holdout_worse(_check(3.606, 1), _check(2.0, 1), "every:5", "ekf") is None
    assert holdout_worse(_check(None, 1), _check(5.0, 1), "every:5", "ekf") is None
    assert holdout_worse(_check(3.0, 1), _check(5.0, 1), None, "ekf") is None
    assert holdout_worse(_check(math.nan, 1), _check(5.0, 1), "every:5", "ekf") is None


def test_the_tuned_configs_header_says_how_it_compares_and_a_retune_replaces_it(tmp_path):
    from importlib.resources import files

    from ddfuse.data import configs
    from ddfuse.estimation.measurements import Stream

    src = files(configs) / "rl_husky_gps.yaml"
    cfg = load_config(src)
    result = _result(cfg, Stream([]))
    before, after = _check(3.606, 0.01, 3.4), _check(5.825, 1.0, 1.0)
    out = tuned_text(src.read_text(), result, "rl_husky_gps.bag", "2026-12-02", before, after,
                     "window:150:210")
    head = out[:out.index("\n\n")]
    flat = " ".join(line[2:] for line in head.splitlines())
    assert "Fail on 2 -> 0 of 2 sensors" in flat
    assert (f"3.606 m with the config's values, 5.825 m tuned; NEES "
            f"{before.holdout_nees.mean:.2f} Fail -> {after.holdout_nees.mean:.2f} Pass") in flat
    assert "WORSE by 62 % on that hold-out" in flat
    assert all(line.startswith("# ") and len(line) <= 100 for line in head.splitlines())
    again = tuned_text(out, result, "other.bag", "2026-12-03")
    assert again.count("estimated by `ddfuse tune`") == 1 and "other.bag (2026-12-03)" in again
    assert "WORSE" not in again and "The IMU is mounted with its y axis up" in again
    path = tmp_path / "t.yaml"
    path.write_text(again)
    assert load_config(path).sensor("/imu/data").noise["yaw"] == 0.0123
    # a header as tuned configs had it before (two lines, no blank line) is replaced too
    old = ("# Noise values marked 'tuned' were estimated by `ddfuse tune` on a.bag (2026-12-01):"
           "\n# maximum likelihood of the ekf EKF's innovations (docs/design/tuning.md).\n"
           + src.read_text())
    assert tuned_text(old, result, "b.bag", "2026-12-03").count("by `ddfuse tune`") == 1


@pytest.mark.slow
def test_cli_prints_the_table_and_writes_the_tuned_config(sim_bag, tmp_path, capsys):
    bag, _ = sim_bag
    out = tmp_path / "tuned.yaml"
    assert main(["tune", str(bag), "-o", str(out), "--gps-holdout", "every:5",
                 "--jobs", "1"]) == 0
    text = capsys.readouterr().out
    for row in ("sensors.gps[0].noise.horizontal [m]", "NIS mean / expected", "/fix gps",
                "GPS hold-out RMSE (every:5), m", "GPS hold-out NEES (expected 2)",
                "not informed"):
        assert row in text
    cfg = load_config(out)
    assert np.isfinite(cfg.sensor("/fix").noise["horizontal"])
    assert "ddfuse tune" in out.read_text()


def test_cli_refuses_a_holdout_without_gps(tmp_path, capsys):
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    cfg = tmp_path / "c.yaml"
    cfg.write_text("sensors:\n  odometry:\n    - topic: /odom\n      use: [v, yaw_rate]\n")
    code = main(["tune", str(root / "data" / "sample_husky.bag"), "-c", str(cfg),
                 "--gps-holdout", "every:5"])
    assert code == 2
    assert "has no gps sensor" in capsys.readouterr().err


def test_cli_refuses_twist_rates_for_a_landmark_config(capsys):
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "data"
    code = main(["tune", str(root / "sample_seed002.bag"), "-c",
                 str(root / "sample_seed002.yaml"), "--twist-rates"])
    assert code == 2
    err = capsys.readouterr().err
    assert "--twist-rates" in err and "ekf_landmark tunes it" in err and len(err.splitlines()) == 1


def test_two_values_with_the_same_effect_are_reported_as_a_pair():
    # per-innovation scores (J) where gyro noise and slip move the innovations alike (gyro
    # noise vs heading slip, both widening the yaw-rate innovations): J'J's inverse correlates
    # them; the GPS, with its own innovations, stays apart
    rng = np.random.default_rng(1)
    n = 400
    gyro = rng.normal(size=n)
    gps = np.zeros(n)
    gps[::4] = rng.normal(size=n // 4)
    slip = 0.9 * gyro + 0.05 * rng.normal(size=n)
    base = rng.normal(size=n)
    step = 0.02
    bumped = [base + step * col for col in (gyro, slip, gps)]
    info = information(base, bumped, step)
    np.testing.assert_allclose(info[0, 0], gyro @ gyro, rtol=1e-9)
    pairs = correlated_pairs(np.linalg.inv(info), ["gyro", "slip", "gps"])
    assert [(a, b) for a, b, _ in pairs] == [("gyro", "slip")]
    assert pairs[0][2] < -0.9  # their estimates trade off: one up, the other down


def test_runs_of_different_lengths_give_no_information():
    assert information(np.zeros(5), [np.zeros(5), np.zeros(4)], 0.02) is None


def test_the_log_keeps_each_innovations_log_det_for_the_likelihood():
    from ddfuse.estimation.estimator import InnovationLog

    log = InnovationLog(keep=1 << 20)
    S2 = np.array([[2.0, 0.3], [0.3, 0.5]])
    log.add(0.0, "/fix", "gps", np.array([1.0, -1.0]), S2, 3.0)
    log.add(0.1, "/imu", "gyro", (0.2,), ((0.04,),), 1.0, accepted=False)
    h = log.held_log_det()
    np.testing.assert_allclose(h["log_det"], [np.log(np.linalg.det(S2)), np.log(0.04)],
                               rtol=1e-12)
    assert h["accepted"].tolist() == [True, False] and h["nis"].tolist() == [3.0, 1.0]
    assert [h["groups"][g] for g in h["group"]] == [("/fix", "gps", 2), ("/imu", "gyro", 1)]


def test_scoring_finds_the_maximum_likelihood_of_a_variance_from_far_off():
    # N samples of N(0, sigma^2): L(log s) = sum 0.5 (log s^2 + y^2 / s^2); its minimum is the
    # sample RMS. Per sample d/dlog s is 1 - y^2 / s^2 (J), and the Fisher factor's
    # d(sqrt(1/2) log s^2)/dlog s = sqrt(2) (F): scoring from 30x too large or too small, and
    # BHHH alone from 1.5x off (far off, the misfit inflates J'J and BHHH creeps: why the
    # search takes the scoring step too), reach it to within the stopping rule's reach
    rng = np.random.default_rng(3)
    y = 0.2 * rng.normal(size=500)
    rms = math.sqrt(float(np.mean(y * y)))

    def values_at(xs):
        return [float(np.sum(0.5 * (2 * x[0] + y * y * np.exp(-2 * x[0])))) for x in xs]

    def derivs_at(x, fisher=True):
        J = (1.0 - y * y * np.exp(-2 * x[0]))[:, None]
        return J, (np.full((len(y), 1), math.sqrt(2.0)) if fisher else None)

    for start, fisher in ((30.0 * rms, True), (rms / 30.0, True), (1.5 * rms, False)):
        x0 = np.array([math.log(start)])
        J, F = derivs_at(x0, fisher)
        x, f, _, its, why = scoring(values_at, lambda x, k=fisher: derivs_at(x, k), x0,
                                     values_at([x0])[0], J, F, x0 - math.log(100.0),
                                     x0 + math.log(100.0), lambda *a: None)
        # the search stops when a step would gain under STOP_NLL: L's curvature in log s is
        # the information 2 N, so that leaves x within sqrt(2 STOP_NLL / (2 N)) (+ a last step)
        bound = math.sqrt(2.0 * STOP_NLL / (2.0 * len(y))) + STOP_STEP
        assert abs(x[0] - math.log(rms)) < bound, (start, fisher, math.exp(x[0]), why)
        # (the predicted gain is the quadratic model's, BHHH's J'J off by the misfit: 2x)
        assert f <= values_at([np.array([math.log(rms)])])[0] + 2.0 * STOP_NLL


def test_the_twist_walk_is_a_parameter_starting_where_the_ekf_is(sim_bag):
    # the simulated config states the acceleration limits, no twist walk: the EKF's densities
    # are then a_max sqrt(T), T the sample period of what measures v (odometry, 10 Hz) and w
    # (the gyro, 30 Hz); the search starts there, and the config's value is "none"
    bag, yaml = sim_bag
    cfg = load_config(yaml)
    params = {p.key: p for p in parameters(cfg, read_stream(bag, cfg))}
    speed, yaw = params["robot.twist_walk.speed"], params["robot.twist_walk.yaw_rate"]
    assert speed.before is None and speed.source == "max_accel"
    assert speed.start == pytest.approx(cfg.robot.max_accel * math.sqrt(0.1), rel=0.01)
    assert yaw.start == pytest.approx(cfg.robot.max_yaw_accel * math.sqrt(1 / 30), rel=0.01)
    assert yaw.unit == "rad/s/sqrt(s)"


@pytest.mark.slow
def test_a_value_the_data_drive_to_nothing_is_kept_small_not_put_back(sim_bag):
    # the simulated robot does not slip: a heading slip of 0.05 rad/sqrt(s) widens the compass's
    # S (0.05^2 / 30 Hz against its 0.02^2) and is informed at the start; the likelihood drives
    # it down until it no longer shows. Putting the 0.05 back would undo the fit.
    bag, yaml = sim_bag
    cfg = load_config(yaml)
    stream = read_stream(bag, cfg)
    cfg.robot.slip = {**cfg.robot.slip, "heading": 0.05}
    result = tune(cfg, stream, jobs=1)
    got = {t.param.key: t for t in result.tuned}["robot.slip.heading"]
    assert got.status == "negligible", (got.status, got.value, got.reason)
    assert got.value < 0.005 and "no longer affects" in got.reason



@pytest.mark.parametrize("tau", [0.0, 30.0])
def test_a_gps_sigma_tuned_under_a_stated_correlation_time_says_what_it_is(tmp_path, tau):
    from ddfuse.evaluation.tune_params import Param
    from ddfuse.evaluation.tune_rules import correlated_gps_caveat

    cfg_file = tmp_path / "c.yaml"
    cfg_file.write_text("sensors:\n  gps:\n    - topic: /fix\n"
                        f"      correlation_time: {tau}\n      noise: {{horizontal: 1.0}}\n")
    cfg = load_config(cfg_file)
    p = Param("sensors.gps[0].noise.horizontal", "/fix horizontal", 1.0, 1.0, "config", "m",
              "/fix", "gps", "horizontal")
    result = TuneResult("ekf", [Tuned(p, 0.49, "tuned")])
    correlated_gps_caveat(cfg, result)
    said = result.tuned[0].reason
    assert ("correlated over 30 s" in said) == (tau > 0.0)
    assert result.tuned[0].value == 0.49  # said, not changed


@pytest.mark.parametrize("gps_key", ["", "gps: {model: default}\n", "gps:\n  model: cauchy\n"])
def test_a_gps_model_from_the_command_line_goes_into_the_tuned_config(tmp_path, gps_key):
    """``ddfuse run --tune --gps-model dcs``: the values were tuned under dcs, so the tuned
    config says dcs with why, whatever the original's gps key looked like."""
    from ddfuse.estimation.measurements import Stream

    text = "sensors:\n  imu: [{topic: /imu, use: [yaw, yaw_rate]}]\n" + gps_key
    cfg = parse_config_text(text)
    out = tuned_text(text, _result(cfg, Stream([])), "u.bag", "2026-12-04", gps_model="dcs")
    path = tmp_path / "tuned.yaml"
    path.write_text(out)
    assert load_config(path).gps.model == "dcs"
    assert "tuned under --gps-model dcs (ddfuse tune, u.bag, 2026-12-04)" in out
    plain = tuned_text(text, _result(cfg, Stream([])), "u.bag", "2026-12-04")
    assert "--gps-model" not in plain
