"""The heavy-tailed speed walk (``robot.twist_walk.speed_burst``, ``burst_share``;
``estimation.twist_tails``): the mixture's equations, the unicycle EKF's choice of the burst
from the speed innovation, the smoothers' ageing of a held sample with the mixture's mean
density, the config keys, and ``ddfuse tune``'s criterion for turning it on."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.ekf_baseline.igvc import IgvcEkf
from ddfuse.ekf_baseline.unicycle import UnicycleEkf
from ddfuse.estimation.config import ConfigError, parse_config
from ddfuse.estimation.measurements import GyroYawRate, Stream, WheelOdometry
from ddfuse.estimation.twist_tails import SpeedTails, held_speed_walk
from ddfuse.evaluation.tune_params import HEAVY_KURTOSIS, parameters, speed_tails

STEADY, BURST, SHARE = 0.02, 1.0, 0.05
R_V = 1e-4  # (m/s)^2, the odometry speed's variance
DT = 0.02  # s, 50 Hz


def _cfg(tails: bool = True, smoother: bool = False, bias: bool = False, rate="event", **walk):
    tw = {"speed": STEADY, "yaw_rate": 0.3}
    if tails:
        tw.update(speed_burst=BURST, burst_share=SHARE)
    tw.update(walk)
    imu = {"topic": "/imu", "use": ["yaw_rate"]}
    if bias:
        imu["gyro_bias"] = "estimate"
    raw = {"sensors": {"odometry": [{"topic": "/odom", "use": ["v"]}], "imu": [imu]},
           "robot": {"twist_walk": tw}, "initial_pose": [0.0, 0.0, 0.0],
           "ekf": {"rate": rate}}
    if smoother:
        raw["smoother"] = {"lag": 5.0, "keyframe": "rate", "keyframe_rate": 5.0}
    return parse_config(raw)


def _normal(x: float, var: float) -> float:
    return math.exp(-0.5 * x * x / var) / math.sqrt(2.0 * math.pi * var)


def test_the_burst_weight_is_the_mixtures_posterior_and_nll_its_density():
    t = SpeedTails(STEADY, BURST, SHARE)
    s, e = 3e-5, t.extra(DT)
    assert e == pytest.approx((BURST ** 2 - STEADY ** 2) * DT)
    for nu in (0.0, 0.005, 0.02, 0.05, 0.3):
        pb, ps = SHARE * _normal(nu, s + e), (1.0 - SHARE) * _normal(nu, s)
        assert t.weight(nu, s, e) == pytest.approx(pb / (pb + ps), rel=1e-9, abs=1e-300)
        # less 0.5 log(2 pi): the Gaussian terms of ddfuse tune are 0.5 (log S + NIS)
        assert t.nll(nu, s, e) == pytest.approx(-math.log(pb + ps) - 0.5 * math.log(
            2.0 * math.pi), rel=1e-9)
    # the clip: beyond it the innovation costs what one at clip x the burst's variance does
    assert t.nll(5.0, s, e, clip=15.0) == pytest.approx(t.nll(math.sqrt(15.0 * (s + e)), s, e))
    assert t.mean_density() == pytest.approx((1 - SHARE) * STEADY ** 2 + SHARE * BURST ** 2)


def _steps(n: int, speed, t0: float = 0.0) -> list:
    return [WheelOdometry(t0 + k * DT, speed(k), None, R_V, 0.0, "/odom") for k in range(n)]


def test_a_burst_gets_the_burst_variance_a_steady_stretch_the_steady_walk_alone():
    ekf = UnicycleEkf(_cfg(), reference=True)
    stream = _steps(150, lambda k: 1.0 if k < 100 else 1.3)
    for m in stream:
        ekf.process(m)
    h = ekf.log.innovations.held_log_det()
    S = np.exp(h["log_det"])
    kept = np.array(ekf.bursts.terms["/odom"])
    assert len(kept) == len(S) == 150
    nu, s, extra = kept.T
    # the steady stretch: the logged S is the steady one, and it has settled where a random
    # walk of q = STEADY^2 dt measured with R_V does (P_prior^2 - q P_prior - q R_V = 0)
    q = STEADY ** 2 * DT
    p_prior = 0.5 * (q + math.sqrt(q * q + 4.0 * q * R_V))
    np.testing.assert_allclose(S[50:100], s[50:100], rtol=1e-12)
    np.testing.assert_allclose(s[90:100], p_prior + R_V, rtol=1e-3)
    # the step: the burst's variance added, so the gate takes it; then steady again
    assert S[100] == pytest.approx(s[100] + extra[100], rel=1e-12)
    assert extra[100] == pytest.approx((BURST ** 2 - STEADY ** 2) * DT, rel=1e-9)
    assert h["accepted"][100]
    np.testing.assert_allclose(S[120:], s[120:], rtol=1e-12)
    assert abs(ekf.kf.x[3] - 1.3) < 0.01
    # the Gaussian walk at the steady density: the gate rejects the step (the speed is lost)
    gauss = UnicycleEkf(_cfg(tails=False), reference=True)
    for m in stream[:101]:
        gauss.process(m)
    assert not gauss.log.innovations.held_log_det()["accepted"][100]


def test_ekf_igvc_widens_its_speeds_alike_at_a_burst_only():
    """ekf_igvc's speed is driven by jerk on an acceleration state; the burst adds its extra
    variance to v and the rim speeds alike, where the burst is the more probable."""
    ekf = IgvcEkf(_cfg(), reference=True)
    stream = _steps(150, lambda k: 1.0 if k < 100 else 1.3)
    for m in stream[:100]:
        ekf.process(m)
    P0 = ekf.kf.P.copy()
    ekf.process(stream[100])
    h = ekf.log.innovations.held_log_det()
    S = np.exp(h["log_det"])
    nu, s, extra = np.array(ekf.bursts.terms["/odom"]).T
    assert len(S) == len(s) == 101
    np.testing.assert_allclose(S[:100], s[:100], rtol=1e-12)  # steady: nothing added
    assert extra[100] == pytest.approx((BURST ** 2 - STEADY ** 2) * DT, rel=1e-9)
    assert S[100] == pytest.approx(s[100] + extra[100], rel=1e-9)
    assert h["accepted"][100]
    assert ekf.kf.x[6] > 1.2  # v followed the step
    assert P0[6, 6] < 1e-3  # (the prior was tight: the step's acceptance is the widening's)
    gauss = IgvcEkf(_cfg(tails=False), reference=True)
    for m in stream[:101]:
        gauss.process(m)
    assert not gauss.log.innovations.held_log_det()["accepted"][100]


@pytest.mark.parametrize(("make", "rate"), [(UnicycleEkf, "event"), (UnicycleEkf, 20.0),
                                            (IgvcEkf, "event")])
@pytest.mark.parametrize("bias", [False, True])
def test_compiled_and_reference_filters_agree_under_the_heavy_tailed_walk(make, rate, bias):
    from test_ekf_compiled import _run_both

    rng = np.random.default_rng(3)
    stream = _drive(rng, 10.0)
    _run_both(lambda reference: make(_cfg(bias=bias, rate=rate), reference=reference), stream)


def _drive(rng, duration: float) -> list:
    """50 Hz odometry speed (sigma 0.01 m/s) and gyro (0.01 rad/s): 0.5 m/s, the speed
    stepping by +-0.3 m/s every 3 s, the yaw rate 0.3 sin(0.3 t)."""
    out = []
    for k in range(int(duration / DT)):
        t = k * DT
        v = 0.5 + 0.3 * (int(t / 3.0) % 2)
        out.append(GyroYawRate(t, 0.3 * math.sin(0.3 * t) + rng.normal(0.0, 0.01), 1e-4, "/imu"))
        out.append(WheelOdometry(t + 0.001, v + rng.normal(0.0, 0.01), None, R_V, 0.0, "/odom"))
    return out


def _track(est, stream) -> np.ndarray:
    xy = []
    for m in stream:
        est.process(m)
        e = est.estimate()
        if e is not None:
            xy.append((e.t, *e.pose[:2]))
    est.finish()
    return np.array(xy)


def test_the_ekf_follows_the_bursts_as_the_smoother_does():
    """The smoother takes the twist from the held samples (no walk between fresh ones), so it
    follows a step at once; the EKF does with the heavy-tailed walk, and with a Gaussian walk
    at the steady density it rejects the steps and drifts off."""
    from ddfuse.estimation.smoother.fixed_lag import FixedLagSmoother

    stream = _drive(np.random.default_rng(1), 20.0)
    ref = _track(FixedLagSmoother(_cfg(smoother=True)), stream)

    def off(est) -> float:
        tr = _track(est, stream)
        at = {round(t, 6): (x, y) for t, x, y in ref.tolist()}
        d = [math.hypot(x - at[round(t, 6)][0], y - at[round(t, 6)][1])
             for t, x, y in tr.tolist() if round(t, 6) in at]
        return max(d)

    tails, gauss = off(UnicycleEkf(_cfg(), reference=True)), off(
        UnicycleEkf(_cfg(tails=False), reference=True))
    assert tails < 0.03
    assert gauss > 10.0 * tails


def test_the_smoother_ages_a_held_speed_with_the_mixtures_mean_density():
    from ddfuse.estimation.smoother.held_twist import HeldTwist
    from ddfuse.estimation.smoother.noise import SmootherNoise
    from ddfuse.factors.preintegration import WheelGyroPreintegration

    robot = _cfg().robot
    assert held_speed_walk(robot) == pytest.approx(math.sqrt(
        (1 - SHARE) * STEADY ** 2 + SHARE * BURST ** 2))
    assert held_speed_walk(_cfg(tails=False).robot) == STEADY
    ht = HeldTwist(robot, SmootherNoise(), WheelGyroPreintegration, 0.0)
    # held 1 s past its span: var tau^2 + q tau^3 / 3 over the step, q the mean density
    q, var = ht.stale(R_V, DT, None, 1.0, (0.0, 1.0), 1.0, 2.0, held_speed_walk(robot))
    assert var == pytest.approx(R_V + held_speed_walk(robot) ** 2)
    assert q == pytest.approx(R_V + held_speed_walk(robot) ** 2 / 3.0)


@pytest.mark.parametrize(("walk", "key"), [
    ({"speed_burst": 0.01}, "robot.twist_walk.speed_burst"),  # not above speed
    ({"speed_burst": "fast"}, "robot.twist_walk.speed_burst"),
    ({"burst_share": 1.0}, "robot.twist_walk.burst_share"),
    ({"burst_share": 0.0}, "robot.twist_walk.burst_share"),
    ({"burst_share": -0.1}, "robot.twist_walk.burst_share"),
])
def test_a_bad_heavy_tailed_walk_is_refused_in_one_line_naming_the_key(walk, key):
    with pytest.raises(ConfigError) as e:
        _cfg(**walk)
    msg = str(e.value)
    assert key in msg and "\n" not in msg


@pytest.mark.parametrize(("walk", "key", "needs"), [
    ({"speed_burst": 1.0}, "robot.twist_walk.speed_burst", "robot.twist_walk.speed"),
    ({"burst_share": 0.1}, "robot.twist_walk.burst_share", "robot.twist_walk.speed_burst"),
])
def test_a_heavy_tailed_key_without_what_it_needs_is_refused(walk, key, needs):
    with pytest.raises(ConfigError) as e:
        parse_config({"sensors": {"odometry": [{"topic": "/odom"}]},
                      "robot": {"twist_walk": walk}})
    msg = str(e.value)
    assert key in msg and needs in msg.split(key, 1)[1] and "\n" not in msg


def test_the_keys_parse_and_absent_the_walk_is_gaussian():
    cfg = _cfg()
    assert SpeedTails.from_robot(cfg.robot) == SpeedTails(STEADY, BURST, SHARE)
    assert SpeedTails.from_robot(_cfg(tails=False).robot) is None
    assert UnicycleEkf(_cfg(tails=False), reference=True).bursts is None
    default = _cfg(tails=False, speed_burst=BURST).robot
    assert SpeedTails.from_robot(default).share == 0.05


def _odometry_stream(rng, heavy: bool) -> Stream:
    v, out = 0.5, []
    for k in range(3000):
        dv = rng.normal(0.0, 0.005)
        if heavy and rng.random() < 0.03:
            dv += rng.normal(0.0, 0.15)
        v += dv
        out.append(WheelOdometry(k * DT, v, None, R_V, 0.0, "/odom"))
    return Stream(out, t0=0.0, t1=out[-1].t)


def test_tune_turns_the_heavy_tailed_walk_on_only_where_the_speed_changes_are_heavy_tailed():
    cfg = parse_config({"sensors": {"odometry": [{"topic": "/odom", "use": ["v"]}]}})
    rng = np.random.default_rng(7)
    gauss = parameters(cfg, _odometry_stream(rng, heavy=False))
    assert [p.key for p in gauss if "twist_walk" in p.key] == ["robot.twist_walk.speed"]
    assert gauss[-1].start == 1.0  # the EKF's default density, as before
    heavy = {p.key: p for p in parameters(cfg, _odometry_stream(rng, heavy=True))}
    share, burst = heavy["robot.twist_walk.burst_share"], heavy["robot.twist_walk.speed_burst"]
    assert share.kind == "corr" and 0.02 < share.start < 0.04
    # started from the data: the changes' robust sigma and the bursts' RMS over sqrt(period)
    assert heavy["robot.twist_walk.speed"].start == pytest.approx(0.005 / math.sqrt(DT),
                                                                  rel=0.15)
    assert burst.start == pytest.approx(0.15 / math.sqrt(DT), rel=0.25)
    dv = np.diff([m.v for m in _odometry_stream(np.random.default_rng(8), heavy=False)
                  .measurements])
    assert speed_tails(dv, DT)[0] < HEAVY_KURTOSIS


def test_tunes_likelihood_of_a_speed_innovation_is_the_mixtures():
    from ddfuse.estimation import chi2
    from ddfuse.evaluation.tune import GATE_P, Problem

    cfg = _cfg()
    stream = Stream(_drive(np.random.default_rng(2), 12.0), t0=0.0, t1=12.0)
    params = parameters(cfg, stream)
    problem = Problem(cfg, stream, params, "ekf")
    terms = problem.terms([None] * len(params))[0]
    est, _ = problem.run([None] * len(params))
    h = est.log.innovations.held_log_det()
    code = next(i for i, (_, kind, _) in enumerate(h["groups"]) if kind == "v")
    rows = h["group"] == code
    clip = chi2.ppf(GATE_P, 1)
    want = [est.bursts.tails.nll(nu, s, e, clip) for nu, s, e in est.bursts.terms["/odom"]]
    np.testing.assert_allclose(terms[rows], want, rtol=1e-9)
    # not the Gaussian term of the widened S the log holds
    gauss = 0.5 * (h["log_det"][rows] + np.minimum(h["nis"][rows], clip))
    assert np.abs(terms[rows] - gauss).max() > 0.1
    # the gyro's terms stay Gaussian
    g = h["group"] != code
    np.testing.assert_allclose(terms[g], 0.5 * (h["log_det"][g] + np.minimum(h["nis"][g], clip)))
