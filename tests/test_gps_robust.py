"""The robust GPS models of ``gps.model`` (estimation/smoother/gps_models.py) and the max-mixture
factor (factors/gps_mixture.py): Jacobians, the component choice, the learned scale, the config
key, and a GPS that is wrong for minutes (a wrong datum)."""

import math

import gtsam
import numpy as np
import pytest
from ddfuse.estimation.config import (
    Config,
    GpsModelConfig,
    RobotConfig,
    SensorConfig,
    parse_config_text,
)
from ddfuse.estimation.errors import ConfigError
from ddfuse.estimation.smoother.fixed_lag import FixedLagSmoother
from ddfuse.estimation.smoother.gps import DISAGREE_S
from ddfuse.estimation.smoother.gps_models import (
    CHI2_2_QUANTILE,
    GpsScale,
    RobustGps,
    kernel_weight,
)
from ddfuse.factors.gps import gps_predict
from ddfuse.factors.gps_mixture import MixtureModel, gps_maxmix_factor, mixture_component
from drives import straight_drive
from jacobian_checks import analytic_jacobians, numerical_jacobians

KEY = 7
STATE = np.array([3.0, -2.0, 2.9, 1.7, 0.3, 0.01, 0.2, 1.0, 1.0])
INLIER = np.array([[2.0, 0.3], [0.3, 1.5]])
OUTLIER = INLIER + 900.0 * np.eye(2)


def _values(x=STATE):
    v = gtsam.Values()
    v.insert(KEY, np.asarray(x, float))
    return v


@pytest.mark.parametrize("lever,dt", [((0.0, 0.0), 0.0), ((0.4, -0.2), 0.0),
                                      ((0.4, -0.2), 0.13), ((0.0, 0.0), -0.07)])
@pytest.mark.parametrize("offset", [0.5, 40.0])  # the inlier's side, the outlier's
def test_maxmix_jacobian_matches_central_differences(lever, dt, offset):
    e, n = gps_predict(STATE, lever, dt)
    model = MixtureModel(INLIER, OUTLIER, 0.1)
    f = gps_maxmix_factor(KEY, e + offset, n - 0.3 * offset, model, lever, dt)
    an = analytic_jacobians(f, _values())[0]
    nu = numerical_jacobians(f, _values())[0]
    assert np.max(np.abs(an - nu)) < 1e-6
    assert np.any(np.abs(an[:2, :5]) > 0.01)  # not trivially zero


@pytest.mark.parametrize("offset,component", [(0.5, 0), (3.0, 0), (40.0, 1)])
def test_maxmix_error_is_the_better_components_negative_log_likelihood(offset, component):
    """0.5 |error|^2 = min over components of their negative log-likelihood, less the smaller
    constant: the optimiser minimises the mixture's max-component likelihood."""
    e, n = gps_predict(STATE)
    model = MixtureModel(INLIER, OUTLIER, 0.1)
    z = np.array((e + offset, n))
    err = gps_maxmix_factor(KEY, *z, model).unwhitenedError(_values())
    r = np.array((e, n)) - z
    nll = []
    for cov, w in ((INLIER, 0.9), (OUTLIER, 0.1)):
        nll.append(0.5 * r @ np.linalg.solve(cov, r) + 0.5 * math.log(np.linalg.det(cov))
                   - math.log(w))
    c_min = min(0.5 * math.log(np.linalg.det(c)) - math.log(w)
                for c, w in ((INLIER, 0.9), (OUTLIER, 0.1)))
    assert 0.5 * float(err @ err) == pytest.approx(min(nll) - c_min, rel=1e-9)
    assert mixture_component(model, STATE, *z) == component


def test_mixture_refuses_a_weight_outside_zero_one():
    with pytest.raises(ValueError, match="outlier weight"):
        MixtureModel(INLIER, OUTLIER, 1.0)


def test_scale_learns_the_stated_covariances_optimism_despite_outliers():
    """Fixes 2.5 times worse than stated (NIS = 6.25 chi2(2)), 30 % of them outliers: the lower
    quartile gives s^2 of 6.25 within x0.8-x2 (the outliers push it up x1.5 on average, 300
    fixes in the window); stated honestly, 1 (never below)."""
    rng = np.random.default_rng(3)
    worse, honest = GpsScale(60.0), GpsScale(60.0)
    for k in range(600):
        t = 0.2 * k
        nis = 6.25 * rng.chisquare(2)
        if rng.uniform() < 0.3:
            nis = 1e4 * (1.0 + rng.uniform())
        worse.add(t, nis)
        honest.add(t, 0.5 * rng.chisquare(2))
    assert 0.8 * 6.25 <= worse.factor <= 2.0 * 6.25
    assert honest.factor == 1.0
    assert GpsScale(60.0).factor == 1.0  # nothing learned yet
    worse.add(1e3, 1.0)  # the window moved on: one fix, under MIN_SAMPLES
    assert worse.factor == 1.0


def test_kernel_weights_fall_with_the_residual():
    for model, k in (("cauchy", 2.3849), ("geman_mcclure", 2.5), ("dcs", 5.99)):
        w = [kernel_weight(model, k, r) for r in (0.0, 1.0, 3.0, 10.0, 100.0)]
        assert w[0] == 1.0 and w[-1] < 0.01
        assert all(a >= b for a, b in zip(w[:-1], w[1:], strict=True))


def test_gps_model_config_key():
    base = "sensors: {gps: [{topic: /fix}]}\n"
    cfg = parse_config_text(base + "gps: {model: maxmix, outlier_std: 20, outlier_weight: 0.2}")
    assert (cfg.gps.model, cfg.gps.outlier_std, cfg.gps.outlier_weight) == ("maxmix", 20.0, 0.2)
    assert parse_config_text(base).gps == GpsModelConfig()  # today's model unless asked
    with pytest.raises(ConfigError, match="gps.model"):
        parse_config_text(base + "gps: {model: tukey}")
    with pytest.raises(ConfigError, match="gps.outlier_weight"):
        parse_config_text(base + "gps: {model: maxmix, outlier_weight: 1.5}")


def test_robust_factor_scales_the_stated_part_only():
    rg = RobustGps(GpsModelConfig(model="cauchy"))
    for k in range(50):
        rg.scale.add(0.2 * k, 4.0 * CHI2_2_QUANTILE)  # the NIS's quartile 4x chi2(2)'s
    r = np.diag([1.0, 1.0])
    carry = np.diag([0.5, 0.0])
    f, outlier = rg.factor(KEY, 0.0, 0.0, r + carry, r, 1.0, (0.0, 0.0), 0.0,
                           np.array((1.0, 0.0)), r, 18.4)
    cov = np.linalg.inv(f.noiseModel().noise().R().T @ f.noiseModel().noise().R())
    np.testing.assert_allclose(cov, 4.0 * r + carry)
    assert not outlier
    _, outlier = rg.factor(KEY, 0.0, 0.0, r, r, 1.0, (0.0, 0.0), 0.0, np.array((30.0, 0.0)), r,
                           18.4)  # NIS 225 / 4 against the gate's 18.4
    assert outlier


R_WHEEL, TRACK, DATUM = 0.165, 0.555, (47.4, 8.5, 400.0)


def _cfg(model: str) -> Config:
    cfg = Config(sensors=[
        SensorConfig(kind="imu", topic="/imu", name="imu", use=("yaw_rate",)),
        SensorConfig(kind="gps", topic="/fix", name="gps", use=("position",)),
        SensorConfig(kind="wheels", topic="/joint_states", name="wheels", use=("speeds",),
                     joints=("l", "r"))],
        robot=RobotConfig(wheel_radius=R_WHEEL, track_width=TRACK), datum=DATUM)
    cfg.gps = GpsModelConfig(model=model)
    return cfg


@pytest.mark.slow
@pytest.mark.parametrize("model", ["maxmix", "cauchy"])
def test_a_gps_wrong_for_minutes_is_said_and_the_odometry_followed(model):
    """From 40 s on every fix is 60 m north (a wrong datum): DISAGREE_S (10 s) later the
    smoother says GPS and odometry disagree and that it follows the odometry, and its estimate
    stays with the odometry (the outliers fused before that turned its heading by under 0.1
    rad: within 15 m of the truth after 60 s, against the fixes' 60 m) -- the fixes are neither
    silently trusted nor silently dropped."""
    rng = np.random.default_rng(11)
    v = 2.0
    sm = FixedLagSmoother(_cfg(model), initial_pose=(0.0, 0.0, 0.0), lag=10.0)

    def wrong_datum(t, e, n):
        return (e, n + 60.0) if t >= 40.0 else (e, n)

    for m in straight_drive(DATUM, 0.0, v, 100.0, rng, r_wheel=R_WHEEL, sig_wheel=0.1,
                            sig_gyro=0.01, sig_gps=1.0, fix_hook=wrong_datum):
        sm.process(m)
    sm.finish()
    said = [n for n in sm.log.messages if "disagree" in n]
    assert len(said) == 1 and "following the odometry" in said[0]
    t_said = float(said[0].split(":")[0][2:])
    assert 40.0 + DISAGREE_S <= t_said <= 40.0 + DISAGREE_S + 1.0
    est = sm.estimate()
    assert abs(est.pose[1]) < 15.0 and abs(est.pose[0] - v * 100.0) < 5.0
    assert sm.log.rejected[("gps", "outlier")] >= 250  # 60 s of 5 Hz fixes, taken for outliers


def test_the_trajectory_figure_marks_the_fixes_taken_for_outliers():
    """Fixes 2-3 s of a straight drive moved 40 m east (a multipath burst): the smoother under
    the Cauchy model takes them for outliers, and ``plots.gps_outliers`` finds exactly those
    fixes among the run's for the trajectory figure."""
    from ddfuse.estimation.measurements import Stream
    from ddfuse.estimation.runner import run
    from ddfuse.evaluation.plots import gps_outliers
    from ddfuse.evaluation.results import SavedRun

    rng = np.random.default_rng(2)

    def burst(t, e, n):
        return (e + 40.0, n) if 12.0 <= t < 14.0 else (e, n)

    ms = list(straight_drive(DATUM, 0.0, 2.0, 20.0, rng, r_wheel=R_WHEEL, sig_wheel=0.1,
                             sig_gyro=0.01, sig_gps=1.0, fix_hook=burst))
    sm = FixedLagSmoother(_cfg("cauchy"), initial_pose=(0.0, 0.0, 0.0), lag=5.0)
    result = run(Stream(ms, datum=DATUM, t0=0.0, t1=20.0), {"smoother": sm})
    saved = SavedRun.from_result(result)
    mask, who = gps_outliers(saved)
    assert who == "smoother"
    moved = (saved.gps_t >= 12.0) & (saved.gps_t < 14.0)
    assert moved.sum() == 10
    np.testing.assert_array_equal(mask, moved)
