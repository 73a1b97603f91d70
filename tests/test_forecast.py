"""Carrying an estimate forward on the odometry since it (ddfuse.estimation.forecast), and an online
session's estimate "now" (OnlineSession.estimate(name, at=...))."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation.config import load_config
from ddfuse.estimation.estimator import Estimate
from ddfuse.estimation.forecast import MAX_CARRY_S, OdometryTwist, TwistSample, carry
from ddfuse.estimation.measurements import GyroYawRate, WheelOdometry
from ddfuse.evaluation.online import OnlineSession
from ddfuse.factors.kinematics import se2_step

ROOT = Path(__file__).resolve().parents[1]


def _samples(n: int = 6, dt: float = 0.1, v_var: float = 0.02 ** 2, w_var: float = 0.05 ** 2):
    return [TwistSample(10.0 + dt * (k + 1), 1.0 + 0.1 * k, 0.3 - 0.05 * k, v_var, w_var)
            for k in range(n)]


def _start(cov=None) -> Estimate:
    return Estimate(10.0, (2.0, -1.0, 0.4), np.diag((0.01, 0.02, 0.003)) if cov is None else cov)


def test_the_pose_is_the_odometry_integrated_as_dead_reckoning_does():
    twists = _samples()
    t = twists[-1].t + 0.25  # the newest held for 0.25 s beyond its interval
    out = carry(_start(), twists, t, (0.0, 0.0))
    x, y, psi = _start().pose
    now = 10.0
    for s in twists:
        x, y, psi = se2_step(x, y, psi, s.v, s.w, s.t - now)
        now = s.t
    x, y, psi = se2_step(x, y, psi, twists[-1].v, twists[-1].w, t - now)
    assert out.t == t and out.state is None and out.pose_error == "world"
    np.testing.assert_allclose(out.pose[:2], (x, y), atol=1e-12)
    assert abs(out.pose[2] - psi) < 1e-12
    # inside a sample's interval, the sample that measures it moves the pose
    mid = carry(_start(), twists, 10.05, (0.0, 0.0))
    np.testing.assert_allclose(mid.pose, se2_step(*_start().pose, twists[0].v, twists[0].w,
                                                  0.05), atol=1e-12)


def test_nothing_to_carry_gives_the_estimate_itself():
    e = _start()
    assert carry(e, _samples(), 9.0, (1.0, 1.0)) is e  # not after the estimate
    assert carry(e, _samples(), 10.0, (1.0, 1.0)) is e
    assert carry(e, [], 11.0, (1.0, 1.0)) is e  # no odometry known


@pytest.mark.slow
def test_the_covariance_is_the_spread_of_the_integrated_odometry_errors():
    """Monte Carlo: per-sample twist errors, one scale error per run, and a held twist that
    walks away from its sample (density q) over the last 0.4 s, integrated exactly; the
    first-order covariance must match the sample covariance within its sampling error."""
    rng = np.random.default_rng(7)
    twists = _samples()
    q = (0.3, 0.2)
    scale = np.array([[0.08 ** 2, 0.5 * 0.08 * 0.1], [0.5 * 0.08 * 0.1, 0.1 ** 2]])
    e0 = _start(np.diag((0.001, 0.002, 0.0004)))
    hold, sub = 0.4, 40
    t = twists[-1].t + hold
    out = carry(e0, twists, t, q, scale)
    n = 4000
    L = np.linalg.cholesky(scale)
    ends = np.empty((n, 3))
    for i in range(n):
        x, y, psi = rng.multivariate_normal(e0.pose, e0.pose_cov)
        kv, kw = 1.0 + L @ rng.standard_normal(2)
        now = e0.t
        for s in twists:
            v = kv * (s.v + math.sqrt(s.v_var) * rng.standard_normal())
            w = kw * (s.w + math.sqrt(s.w_var) * rng.standard_normal())
            x, y, psi = se2_step(x, y, psi, v, w, s.t - now)
            now = s.t
        h = hold / sub
        dv, dw = v - kv * s.v, w - kw * s.w  # the held sample's error stays...
        for _ in range(sub):  # ...and the twist walks away from it
            dv += math.sqrt(q[0] * h) * rng.standard_normal()
            dw += math.sqrt(q[1] * h) * rng.standard_normal()
            x, y, psi = se2_step(x, y, psi, kv * s.v + dv, kw * s.w + dw, h)
        ends[i] = x, y, psi
    C = np.cov(ends.T)
    assert np.all(np.abs(ends.mean(axis=0) - out.pose) < 4 * np.sqrt(np.diag(C) / n))
    # each variance within ~5 sigma of its sampling error (sqrt(2/n) relative), plus the
    # first-order linearisation's share
    for k in range(3):
        assert abs(C[k, k] / out.pose_cov[k, k] - 1.0) < 5 * math.sqrt(2.0 / n) + 0.03, k
    corr = C[0, 1] / math.sqrt(C[0, 0] * C[1, 1])
    corr_c = out.pose_cov[0, 1] / math.sqrt(out.pose_cov[0, 0] * out.pose_cov[1, 1])
    assert abs(corr - corr_c) < 0.08
    # without the scale term the carried covariance is visibly too small (the test can fail)
    small = carry(e0, twists, t, q)
    assert np.trace(small.pose_cov[:2, :2]) < 0.95 * np.trace(C[:2, :2])


def test_the_yaw_rate_comes_from_the_gyro_when_the_odometry_gives_speed_only():
    cfg = load_config(ROOT / "data" / "configs" / "rl_jackal.yaml")
    tw = OdometryTwist(cfg)
    odo, imu = tw.v_sensor, tw.w_sensor
    assert odo != imu and tw.usable
    tw.push(WheelOdometry(1.0, 0.8, None, 0.01, math.nan, sensor=odo))
    assert tw.samples == []  # no yaw rate yet
    tw.push(GyroYawRate(1.02, 0.25, 1e-4, sensor=imu))
    tw.push(WheelOdometry(1.05, 0.9, None, 0.01, math.nan, sensor=odo))
    assert [(s.t, s.v, s.w) for s in tw.samples] == [(1.02, 0.8, 0.25), (1.05, 0.9, 0.25)]
    assert tw.scale_cov is None  # the Jackal config states no geometry uncertainty


def test_an_online_estimate_carried_to_the_newest_stamp_is_where_the_robot_is(sample_husky):
    """With the config's 0.5 s reorder window the estimators lag the newest message; carried
    to it, the estimate is as close to the truth there as the estimate is at its own stamp,
    and as consistent."""
    cfg, stream = sample_husky
    truth = stream.ground_truth
    tt = np.array([g.t for g in truth])
    tp = np.array([(g.x, g.y) for g in truth])
    tyaw = np.unwrap([g.yaw for g in truth])

    def err(e, t):
        p = np.array([np.interp(t, tt, tp[:, 0]), np.interp(t, tt, tp[:, 1]),
                      np.interp(t, tt, tyaw)])
        d = np.array(e.pose) - p
        d[2] = (d[2] + math.pi) % (2 * math.pi) - math.pi
        return d

    session = OnlineSession.from_config(cfg, ["ekf", "smoother"], stream=stream,
                                        reorder_window=0.5)
    rows = {"ekf": [], "smoother": []}
    nxt = stream.measurements[0].t + 10.0
    for m in stream.measurements:
        session.push(m)
        if m.t < nxt:
            continue
        nxt = m.t + 0.37
        now = session.newest
        for name, r in rows.items():
            e = session.estimate(name)
            c = session.estimate(name, at=now)
            assert c.t == now and e.t < now
            d0, d1, d2 = err(e, now), err(c, now), err(e, e.t)
            r.append((d0[:2] @ d0[:2], d1[:2] @ d1[:2], d2[:2] @ d2[:2],
                      d1 @ np.linalg.solve(c.pose_cov, d1), d2 @ np.linalg.solve(e.pose_cov, d2)))
    for name, r in rows.items():
        a = np.array(r)
        stale, carried, own = np.sqrt(a[:, :3].mean(axis=0))
        assert stale > 0.4  # ~0.5 s behind at ~1 m/s
        assert carried < 1.2 * own, name
        assert 0.8 < a[:, 3].mean() / a[:, 4].mean() < 1.25, name
    # a stopped estimator's estimate is not carried
    session._stop("ekf", session.released_t, RuntimeError("test"))
    assert session.estimate("ekf", at=session.newest).t < session.newest


@pytest.mark.parametrize("twist", [None])
def test_a_session_without_odometry_gives_the_estimate_uncarried(sample_husky, twist):
    cfg, stream = sample_husky
    s = OnlineSession.from_config(cfg, ["ekf"], stream=stream)
    s = OnlineSession(s.estimators, reorder_window=0.5, twist=twist)
    for m in stream.measurements[:3000]:
        s.push(m)
    e = s.estimate("ekf", at=s.newest)
    assert e is not None and e.t < s.newest and e.state is not None


def test_a_carry_beyond_its_horizon_is_refused():
    """1e6 s ahead gave a pose 1e6 m away with variances of 1e16-1e27 and no word."""
    e, twists = _start(), _samples()
    out = carry(e, twists, e.t + MAX_CARRY_S, (0.1, 0.1))  # at the horizon: carried
    assert out.t == e.t + MAX_CARRY_S
    with pytest.raises(ValueError, match=r"^at = 15\.100 s is 5\.1 s after the estimate "
                                         r"\(t = 10\.000 s\), beyond the carry's horizon of 5 s"):
        carry(e, twists, e.t + 5.1, (0.1, 0.1))
    with pytest.raises(ValueError, match=r"horizon of 2 s"):
        carry(e, twists, e.t + 2.5, (0.1, 0.1), horizon=2.0)
    with pytest.raises(ValueError, match=r"^at = nan: expected a time in seconds"):
        carry(e, twists, math.nan, (0.1, 0.1))
    with pytest.raises(ValueError, match=r"^at = inf s is inf s after the estimate"):
        carry(e, twists, math.inf, (0.1, 0.1))
    assert carry(e, twists, -math.inf, (0.1, 0.1)) is e  # not after it: nothing to carry


def test_a_session_carries_over_its_window_plus_the_horizon_only(sample_husky):
    cfg, stream = sample_husky
    s = OnlineSession.from_config(cfg, ["ekf"], stream=stream, reorder_window=0.5)
    assert s.carry_horizon == 0.5 + MAX_CARRY_S
    assert s.estimate("ekf", at=s.newest) is None  # before any push newest is -inf: no error
    for m in stream.measurements[:3000]:
        s.push(m)
    e = s.estimate("ekf")
    assert s.estimate("ekf", at=e.t + 5.4).t == e.t + 5.4
    with pytest.raises(ValueError, match=r"^estimate\('ekf', at=\.\.\.\): at = .* is 1e\+06 s "
                                         r"after the estimate .* beyond the carry's horizon of "
                                         r"5\.5 s: .* \(carry_horizon: reorder_window 0\.5 s "
                                         r"\+ 5 s of latency\)$"):
        s.estimate("ekf", at=e.t + 1e6)
    for bad in (math.inf, math.nan, "soon", [1.0]):
        with pytest.raises(ValueError, match=r"^estimate\('ekf', at=.*\): expected a time in "
                                             r"seconds on the stamps' clock"):
            s.estimate("ekf", at=bad)
    # a long window: the twist keeps the samples its carry needs
    long = OnlineSession.from_config(cfg, ["ekf"], stream=stream, reorder_window=8.0)
    assert long.carry_horizon == 13.0 and long._twist.keep == 13.0
