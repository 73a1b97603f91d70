"""The smoother with a GPS sensor's ``correlation_time`` (time-correlated fix errors,
``ddfuse.estimation.gps_correlation``): each fused fix's factor takes the fix's covariance times
f = inflation(dt, tau), dt since the previous fused fix of that sensor, its robust threshold
scaled by 1/sqrt(f); the gate and the logged innovation keep the fix's own covariance; the
batch solves the same factors; tau = 0 changes nothing."""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import gtsam
import numpy as np
import pytest
from ddfuse.estimation import chi2
from ddfuse.estimation.config import DEFAULT_GATE, parse_config_text
from ddfuse.estimation.gps_correlation import inflation
from ddfuse.estimation.measurements import GpsFix, WheelOdometry
from ddfuse.estimation.runner import run
from ddfuse.estimation.smoother import BatchSmoother, FixedLagSmoother

ROOT = Path(__file__).resolve().parents[1]
SIGMA = 1.0  # m, the hand-built fixes' horizontal sigma
GATE_RADIUS = math.sqrt(chi2.ppf(DEFAULT_GATE, 2))

CFG = """
sensors:
  odometry: [{topic: /odom, use: [v, yaw_rate], noise: {v: 0.05, yaw_rate: 0.02}}]
  gps: [{topic: /fix, noise: {horizontal: 1.0}%s}]
initial_pose: [0.0, 0.0, 0.0]
smoother: {lag: 10.0, keyframe: gps, robust: huber%s}
"""


def _cfg(tau: float | None = None, robust_k: float | None = None):
    return parse_config_text(CFG % (f", correlation_time: {tau}" if tau is not None else "",
                                    f", robust_k: {robust_k}" if robust_k is not None else ""))


def _drive(fix_t, duration: float, moved: dict | None = None, late: dict | None = None):
    """A straight drive east at 1 m/s from the origin: odometry at 10 Hz (exact), a fix at
    each stamp of ``fix_t`` on the true position (``moved``: stamp -> (de, dn) m added;
    ``late``: stamp -> seconds it is delivered after its stamp), in order of delivery."""
    moved, late = moved or {}, late or {}
    out = [(0.1 * i, 0, WheelOdometry(0.1 * i, 1.0, 0.0, 0.05 ** 2, 0.02 ** 2, "/odom"))
           for i in range(int(round(duration * 10)) + 1)]
    for t in fix_t:
        de, dn = moved.get(t, (0.0, 0.0))
        fix = GpsFix(t, 0.0, 0.0, 0.0, np.diag([SIGMA ** 2, SIGMA ** 2, 4.0]), 0, "/fix",
                     (t + de, dn, 0.0))
        out.append((t + late.get(t, 0.0), 1, fix))
    out.sort(key=lambda p: (p[0], p[1]))
    return [m for _, _, m in out]


def _feed(sm, ms):
    """Run ``sm`` over ``ms``, capturing every factor it builds: (smoother, [factors])."""
    built, add = [], sm.window.add
    sm.window.add = lambda f: (built.append(f), add(f))[1]
    for m in ms:
        sm.process(m)
    sm.finish()
    return sm, built


def _gps_factors(built) -> list[tuple[np.ndarray, float]]:
    """The GPS factors among ``built``, in build order: (the factor's east/north variances, its
    Huber threshold). On a keyframe a robust prior on the position; off one (a late fix) the
    motion-compensated ``ddfuse.factors.gps`` CustomFactor (one key, two rows)."""
    out = []
    for f in built:
        if isinstance(f, gtsam.PriorFactorVector):
            model = f.noiseModel()
            if not isinstance(model, gtsam.noiseModel.Robust):
                continue  # the first keyframe's prior
            prec = model.noise().precisions()
            assert np.all(prec[2:] == 0.0)
            var = 1.0 / prec[:2]
        elif isinstance(f, gtsam.CustomFactor) and len(f.keys()) == 1 and f.dim() == 2:
            model = f.noiseModel()
            assert isinstance(model, gtsam.noiseModel.Robust)
            var = np.diag(model.noise().covariance())
        else:
            continue
        k = model.robust().weight(1e3) * 1e3  # Huber: weight k/|e| beyond k
        out.append((var, k))
    return out


def test_the_factor_is_the_fix_inflated_for_the_time_since_the_previous_fused_one():
    """Fixes at 1, 2, 3, 5 and 9.5 s (1, 1, 2, 4.5 s apart), tau 20 s: each factor's variance
    is f SIGMA^2 with f = inflation(dt, 20), the first f = 1, and its Huber threshold the
    gate radius over sqrt(f); the innovation logged for the NIS has the fix's own covariance
    (1 m^2 plus the prediction's, not f m^2); the batch builds exactly the same factors."""
    fix_t = [1.0, 2.0, 3.0, 5.0, 9.5]
    sm, built = _feed(BatchSmoother(_cfg(20.0)), _drive(fix_t, 12.0))
    gps = _gps_factors(built)
    dts = [math.inf] + list(np.diff(fix_t))
    for (var, k), dt in zip(gps, dts, strict=True):
        f = inflation(dt, 20.0)
        np.testing.assert_allclose(var, [f * SIGMA ** 2] * 2, rtol=1e-12)
        np.testing.assert_allclose(k, GATE_RADIUS / math.sqrt(f), rtol=1e-9)
    assert inflation(1.0, 20.0) > 39.0  # so the checks above tell f R from R
    inn = [i for i in sm.log.innovations if i.kind == "gps"]
    assert len(inn) == len(fix_t) and all(i.accepted for i in inn)
    for i in inn:
        s = i.cov
        assert SIGMA ** 2 <= s[0, 0] < SIGMA ** 2 + 0.5 and SIGMA ** 2 <= s[1, 1] < 1.5, s
        np.testing.assert_allclose(i.nis, i.residual @ np.linalg.solve(s, i.residual))
    # the online smoother builds the same GPS factors (the batch is that run, all kept)
    online, built_online = _feed(FixedLagSmoother(_cfg(20.0)), _drive(fix_t, 12.0))
    same = _gps_factors(built_online)
    for (va, ka), (vb, kb) in zip(gps, same, strict=True):
        assert np.array_equal(va, vb) and ka == kb


def test_a_user_robust_k_is_scaled_alike():
    sm, built = _feed(BatchSmoother(_cfg(20.0, robust_k=2.0)), _drive([1.0, 2.0], 3.0))
    (_, k0), (_, k1) = _gps_factors(built)
    assert k0 == pytest.approx(2.0) and k1 == pytest.approx(2.0 / math.sqrt(inflation(1.0, 20.0)))


def test_a_rejected_fix_does_not_count_as_fused_and_a_late_one_takes_its_nearest():
    """Fixes every 0.4 s (tau 30 s: f = 150 for the next one). The one at 4.0 s is 30 m off
    (sigma 1 m): the gate rejects it as with white fixes, judged with its own covariance (NIS
    in the hundreds, not 900 / 150), and the fix after it is 0.8 s from the previous FUSED
    one (f = 75). The fix at 6.0 s is delivered 0.5 s late, after the 6.4 s one: its f is for
    0.4 s, its nearer neighbour on either side."""
    fix_t = [round(0.4 * i, 1) for i in range(1, 26)]
    for tau in (0.0, 30.0):
        sm, built = _feed(BatchSmoother(_cfg(tau)), _drive(fix_t, 11.0, moved={4.0: (21.2, 21.2)},
                                                           late={6.0: 0.5}))
        assert sm.log.rejected[("/fix", "gate")] == 1, (tau, sm.log.rejected)
        bad = [i for i in sm.log.innovations if i.kind == "gps" and i.t == 4.0]
        assert len(bad) == 1 and not bad[0].accepted and bad[0].nis > 400.0, bad
        assert math.hypot(*sm.window.kf_state[:2] - (11.0, 0.0)) < 0.5
    # the fused fixes in order of delivery: the late one after 6.4 s
    order = [t for t in fix_t if t not in (4.0, 6.0)]
    order.insert(order.index(6.4) + 1, 6.0)
    gps = dict(zip(order, _gps_factors(built), strict=True))
    f = {dt: inflation(dt, 30.0) for dt in (0.4, 0.8)}
    assert f[0.4] == pytest.approx(150.0, rel=1e-3)
    np.testing.assert_allclose(gps[3.6][0], f[0.4], rtol=1e-12)
    np.testing.assert_allclose(gps[4.4][0], f[0.8], rtol=1e-12)  # from 3.6 s, not 4.0
    np.testing.assert_allclose(gps[6.4][0], f[0.8], rtol=1e-12)  # 5.6 -> 6.4
    np.testing.assert_allclose(gps[6.8][0], f[0.4], rtol=1e-12)
    # late: off its keyframe, so the motion carry's few mm^2 add to f R
    assert np.all(gps[6.0][0] >= f[0.4]) and np.all(gps[6.0][0] < f[0.4] + 0.05), gps[6.0]
    assert gps[1.2][1] == pytest.approx(GATE_RADIUS / math.sqrt(f[0.4]))


def test_the_fused_stamps_kept_are_bounded_by_the_lag():
    fix_t = [round(0.4 * i, 1) for i in range(1, 200)]
    sm, _ = _feed(FixedLagSmoother(_cfg(30.0)), _drive(fix_t, 80.0))
    kept = sm.gps.fused_t["/fix"]
    assert kept[-1] == fix_t[-1] and len(kept) <= 10.0 / 0.4 + 3, len(kept)


def test_a_late_fix_finds_its_neighbour_from_before_the_lag():
    """Fixes every 0.4 s up to 20 s, none until 31 s (lag 10 s), then one stamped 21.5 s
    delivered after it: inside the window (31 - 10 = 21 s), its nearest fused fix is the one
    at 20 s, older than the lag, which the bounded memory keeps: f for 1.5 s, not 9.5 s."""
    fix_t = [round(0.4 * i, 1) for i in range(1, 51)] + [31.0, 21.5]
    sm, built = _feed(FixedLagSmoother(_cfg(30.0)), _drive(fix_t, 33.0, late={21.5: 9.8}))
    gps = _gps_factors(built)
    assert len(gps) == len(fix_t) and sm.log.rejected.get(("/fix", "gate"), 0) == 0
    np.testing.assert_allclose(gps[-2][0], inflation(11.0, 30.0), rtol=1e-12)  # 20 -> 31 s
    np.testing.assert_allclose(gps[-1][0], inflation(1.5, 30.0), rtol=1e-12)


def _tracks(cfg, stream, pose0):
    ests = {"smoother": FixedLagSmoother(cfg, initial_pose=pose0),
            "batch": BatchSmoother(cfg, initial_pose=pose0)}
    r = run(stream, ests)
    return {n: r.runs[n].trajectory for n in ("smoother", "smoother_lagged", "batch")}


def test_tau_zero_is_bit_identical_to_no_correlation_time(sample_husky):
    """correlation_time: 0 (white) against a config without the key: the filtered, lagged and
    batch tracks equal to the bit, on the sample's first 40 s (fixes 0.2 s delayed: the GPS
    factor with motion compensation). The same comparison with tau 30 differs (it can see a
    change), and with tau 0 the factors are the fixes' own, their threshold the gate radius."""
    cfg, stream = sample_husky
    short = replace(stream, measurements=[m for m in stream.measurements
                                          if m.t < stream.t0 + 40.0])
    g = short.ground_truth[0]
    pose0 = (g.x, g.y, g.yaw)
    text = cfg.text
    assert "correlation_time" not in text and "    delay: 0.2\n" in text
    zero = parse_config_text(text.replace("    delay: 0.2\n",
                                          "    delay: 0.2\n    correlation_time: 0\n"))
    thirty = parse_config_text(text.replace("    delay: 0.2\n",
                                            "    delay: 0.2\n    correlation_time: 30\n"))
    plain = parse_config_text(text)
    a, b, c = _tracks(plain, short, pose0), _tracks(zero, short, pose0), \
        _tracks(thirty, short, pose0)
    for name in a:
        assert len(a[name].t) > 50
        for field in ("t", "pose", "cov"):
            assert np.array_equal(getattr(a[name], field), getattr(b[name], field),
                                  equal_nan=True), (name, field)
        assert not np.array_equal(a[name].pose, c[name].pose), name
    # the factors themselves: the fix's own noise and the gate radius with tau 0
    sm, built = _feed(BatchSmoother(_cfg(0.0)), _drive([1.0, 2.0, 3.0], 4.0))
    for var, k in _gps_factors(built):
        assert np.array_equal(var, [SIGMA ** 2] * 2) and k == pytest.approx(GATE_RADIUS)


@pytest.fixture(scope="module")
def multipath(tmp_path_factory):
    """husky-multipath seed 1 cut to 200 s (GPS errors Gauss-Markov, tau 30 s, sigma 1 m;
    its config states that correlation time; the test sets 0 and 30 itself)."""
    d = tmp_path_factory.mktemp("hm")
    bag = d / "hm.bag"
    subprocess.run([sys.executable, "-m", "ddfuse.evaluation.cli", "simulate", "husky-multipath",
                    "--seed", "1", "--duration", "200", "-o", str(bag)], check=True, cwd=ROOT,
                   capture_output=True)
    return bag, d / "hm.yaml"


@pytest.mark.slow
def test_correlated_fixes_end_to_end(multipath, tmp_path):
    """Told the fixes' correlation time, the smoother stops following the GPS's wander and
    its covariance becomes honest. Measured (seed 1, 200 s; tau 0 -> 30): filtered ATE 0.468
    -> 0.098 m, NEES 55 -> 1.55; lagged 0.510 -> 0.094 m, NEES 67 -> 1.40 (seeds 2, 3: ATE
    0.71 / 0.88 -> 0.15 / 0.12 m, NEES 109 / 149 -> 1.4 / 1.6)."""
    from ddfuse.estimation.config import load_config
    from ddfuse.evaluation.pipeline import run_bag

    bag, yaml = multipath
    cfg = load_config(yaml)
    out = {}
    for tau in (0.0, 30.0):
        c = replace(cfg, sensors=[replace(s, correlation_time=tau) if s.kind == "gps" else s
                                  for s in cfg.sensors])
        m = run_bag(bag, c, tmp_path / f"tau{tau:g}", names=["smoother", "smoother_lagged"])
        out[tau] = {n: (e.ate_rmse_m, e.nees_mean) for n, e in m.estimators.items()}
    for name in ("smoother", "smoother_lagged"):
        (ate0, nees0), (ate30, nees30) = out[0.0][name], out[30.0][name]
        assert ate0 > 0.3 and nees0 > 20.0, (name, out)  # white: follows the wander
        assert ate30 < 0.4 * ate0 and ate30 < 0.15, (name, out)
        assert nees30 < 3.0 and nees30 < 0.1 * nees0, (name, out)
