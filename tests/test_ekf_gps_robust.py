"""The EKFs' robust GPS model (ekf_baseline/gps_robust.py, ``gps.model`` robust): the sliding-
window chi-square test declares a faulty stretch and re-admits the GPS, the hold before the
filter takes itself for lost is bounded and doubles, the factor on R is bounded and grows with
the innovation, and on a multipath burst both EKFs do better with the model than without."""

import math

import numpy as np
import pytest
from ddfuse.ekf_baseline.gps_robust import (
    EXCLUDE,
    FUSE,
    MAX_FACTOR,
    RECOVER,
    EkfRobustGps,
)
from ddfuse.ekf_baseline.igvc import IgvcEkf
from ddfuse.ekf_baseline.unicycle import UnicycleEkf
from ddfuse.estimation.config import (
    GpsModelConfig,
    parse_config_text,
)
from ddfuse.estimation.errors import ConfigError
from drives import straight_drive
from test_gps_robust import _cfg  # the smoother's robust-GPS tests' config: one drive for both

S = [[4.0, 0.0], [0.0, 4.0]]  # innovation covariance (m^2) with the stated R
R = [[2.25, 0.0], [0.0, 2.25]]
R_WHEEL, TRACK, DATUM = 0.165, 0.555, (47.4, 8.5, 400.0)


def _model(**kw) -> EkfRobustGps:
    return EkfRobustGps("gps", GpsModelConfig(model="cauchy", **kw), None)


def _feed(model, t0, t1, rate, rng, offset=0.0):
    """Fixes at ``rate`` Hz over [t0, t1) whose innovation is N(0, S) plus ``offset`` m east;
    the verdicts."""
    out = []
    for t in np.arange(t0, t1, 1.0 / rate):
        y = rng.multivariate_normal([offset, 0.0], S)
        out.append((float(t), model.judge(float(t), [float(y[0]), float(y[1])], S, R)))
    return out


def test_window_declares_a_faulty_stretch_and_readmits_the_gps():
    """Consistent fixes are fused; a 6 s stretch of fixes 25 m off is declared faulty within
    the window and none of its fixes fused (beyond the gate); once the stretch has left the
    window the GPS is re-admitted, and the fault is said both ways."""
    rng = np.random.default_rng(4)
    m = _model(fault_window=5.0)
    before = _feed(m, 0.0, 60.0, 2.0, rng)
    assert all(v[0] == FUSE for _, v in before)
    burst = _feed(m, 60.0, 66.0, 2.0, rng, offset=25.0)
    after = _feed(m, 66.0, 100.0, 2.0, rng)
    tripped = [t for t, v in burst if v[0] == EXCLUDE]
    assert tripped and tripped[0] < 60.0 + 5.0
    assert all(v[0] == EXCLUDE and v[2] for _, v in burst)  # every burst fix an outlier
    readmit = next(t for t, v in after if v[0] == FUSE)
    assert readmit <= 66.0 + 5.0 + 1.0
    assert all(v[0] == FUSE for t, v in after if t > readmit)
    assert len(m.faults) == 1 and m.faults[0][3] == "consistent"
    assert 60.0 <= m.faults[0][0] < 65.0 and m.faults[0][1] == readmit
    assert any("disagree" in n and "following the odometry" in n for _, n in m.notes)
    assert any("agrees" in n and "following the GPS" in n for _, n in m.notes)


def test_a_gps_wrong_for_good_is_followed_after_a_bounded_hold_that_doubles():
    """Fixes off by 60 m for minutes (a wrong datum, against a filter that never widens): the
    GPS is declared faulty, and ``fault_hold`` s later the model asks for a recovery; if it
    recurs, the next hold is twice as long -- never a lock-out for good."""
    rng = np.random.default_rng(5)
    m = _model(fault_window=5.0, fault_hold=20.0)
    _feed(m, 0.0, 30.0, 2.0, rng)
    wrong = _feed(m, 30.0, 200.0, 2.0, rng, offset=60.0)
    rec = [t for t, v in wrong if v[0] == RECOVER]
    first_ex = next(t for t, v in wrong if v[0] == EXCLUDE)
    assert rec and 20.0 <= rec[0] - first_ex <= 21.0
    second_ex = next(t for t, v in wrong if v[0] == EXCLUDE and t > rec[0])
    assert len(rec) >= 2 and 40.0 <= rec[1] - second_ex <= 41.0
    assert all(how == "recovered" for *_, how in m.faults)


def test_a_moderate_outlier_is_fused_down_weighted_a_gross_one_not_at_all():
    m = _model()
    verdict, f, outlier = m.judge(0.0, [6.0, 0.0], S, R)  # NIS 9: inside the gate
    assert verdict == FUSE and f > 1.5 and not outlier
    verdict, f, outlier = m.judge(0.5, [12.0, 0.0], S, R)  # NIS 36: beyond it
    assert verdict == EXCLUDE and outlier


def test_correlated_fixes_need_a_larger_window_sum_to_be_faulty():
    """With a stated correlation time the window holds fewer independent fixes: a run of
    moderately inconsistent fixes that trips the white sensor's test does not trip it."""
    verdicts = {}
    for tau in (0.0, 10.0):
        m = EkfRobustGps("gps", GpsModelConfig(model="cauchy", fault_window=5.0), None, tau)
        for t in np.arange(-20.0, 0.0, 0.5):  # agreeing first: a disagreement is the GPS's
            m.judge(t, [0.0, 0.0], S, R)
        verdicts[tau] = [m.judge(t, [5.0, 0.0], S, R)[0] for t in np.arange(0.0, 5.0, 0.5)]
    assert EXCLUDE in verdicts[0.0] and EXCLUDE not in verdicts[10.0]


def test_fixes_that_never_agreed_since_the_start_are_followed_after_start_hold():
    """A faulty stretch before AGREE_FIXES inliers in a row blames the start (a wrong
    initial_pose), not the GPS: RECOVER START_HOLD s after the verdict, not fault_hold (30),
    the fix fused at the learned scale (1 here); after agreement the same stretch is the
    GPS's fault and waits fault_hold."""
    from ddfuse.ekf_baseline.gps_robust import START_HOLD

    def first_recovery(m, t0):
        out = [(t, m.judge(t, [60.0, 0.0], S, R)) for t in np.arange(t0, t0 + 40.0, 0.5)]
        first_ex = next(t for t, v in out if v[0] == EXCLUDE)
        t_rec, v = next((t, v) for t, v in out if v[0] == RECOVER)
        return t_rec - first_ex, v

    m = _model(fault_window=5.0)
    wait, v = first_recovery(m, 0.0)
    assert START_HOLD <= wait <= START_HOLD + 1.0 and v[1] == pytest.approx(1.0)
    assert any("no fix has agreed with the estimate since the start" in n for _, n in m.notes)
    m = _model(fault_window=5.0)
    for t in np.arange(-10.0, 0.0, 0.5):
        m.judge(t, [0.0, 0.0], S, R)
    wait, _ = first_recovery(m, 0.0)
    assert 30.0 <= wait <= 31.0 and any("takes itself for lost" in n for _, n in m.notes)
    assert not any("since the start" in n for _, n in m.notes)


@pytest.mark.parametrize("model", ["cauchy", "geman_mcclure", "dcs", "maxmix"])
def test_the_factor_on_r_is_bounded_and_grows_with_the_innovation(model):
    m = EkfRobustGps("gps", GpsModelConfig(model=model, fault_window=1e-3), None)
    fs = [m.judge(float(i), [d, 0.0], S, R)[1] for i, d in
          enumerate(np.geomspace(0.01, 1e6, 60))]
    assert all(1.0 <= f <= MAX_FACTOR for f in fs)
    assert all(np.diff(fs) >= 0.0)
    assert fs[0] < 1.01 and fs[-1] == MAX_FACTOR


def test_gps_fault_keys_are_read_and_checked():
    base = "sensors: {gps: [{topic: /fix}]}\n"
    cfg = parse_config_text(base + "gps: {model: cauchy, fault_window: 8, fault_hold: 40}")
    assert (cfg.gps.fault_window, cfg.gps.fault_hold) == (8.0, 40.0)
    with pytest.raises(ConfigError, match="gps.fault_hold"):
        parse_config_text(base + "gps: {model: cauchy, fault_hold: -1}")




@pytest.mark.parametrize("cls", [UnicycleEkf, IgvcEkf])
@pytest.mark.parametrize("reference", [False, True])
def test_on_a_burst_an_ekf_with_the_model_beats_itself_without(cls, reference):
    """A straight drive whose fixes move 30 m north for 8 s (a multipath burst longer than the
    gate's lock-out time): the gated EKF recovers onto the burst and follows it; with the
    model it dead-reckons through it. Its largest error over the run is smaller with the
    model, under half the burst's offset, and the fixes of the burst are counted outliers."""
    v, t0, t1, off = 2.0, 40.0, 48.0, 30.0

    def burst(t, e, n):
        return (e, n + off) if t0 <= t < t1 else (e, n)

    worst = {}
    for model in ("default", "cauchy"):
        rng = np.random.default_rng(3)
        kw = {"reference": True} if reference and cls is UnicycleEkf else {}
        ekf = cls(_cfg(model), initial_pose=(0.0, 0.0, 0.0), **kw)
        err = []
        for m in straight_drive(DATUM, 0.0, v, 80.0, rng, r_wheel=R_WHEEL, sig_wheel=0.1,
                                sig_gyro=0.01, sig_gps=1.0, fix_hook=burst):
            ekf.process(m)
            est = ekf.estimate()
            if est is not None and m.t > 1.0:
                err.append(math.hypot(est.pose[0] - v * m.t, est.pose[1]))
        ekf.finish()
        worst[model] = max(err)
        if model == "cauchy":
            assert ekf.log.rejected[("gps", "outlier")] >= 0.5 * (t1 - t0) * 5
            assert any("following the odometry" in n for n in ekf.log.messages)
    assert worst["cauchy"] < worst["default"]
    assert worst["cauchy"] < 0.5 * off


def test_the_trajectory_figure_marks_the_ekfs_outliers_beside_the_smoothers():
    """Fixes 12-14 s of a straight drive moved 40 m east: the EKF under the Cauchy model takes
    each of them for an outlier (and none before the burst), ``plots.gps_outliers`` finds them
    for it, and the trajectory figure draws its marks beside the smoother's."""
    from ddfuse.estimation.measurements import Stream
    from ddfuse.estimation.runner import run
    from ddfuse.estimation.smoother.fixed_lag import FixedLagSmoother
    from ddfuse.evaluation.plots import gps_outliers, trajectories
    from ddfuse.evaluation.results import SavedRun

    rng = np.random.default_rng(2)

    def burst(t, e, n):
        return (e + 40.0, n) if 12.0 <= t < 14.0 else (e, n)

    ms = list(straight_drive(DATUM, 0.0, 2.0, 20.0, rng, r_wheel=R_WHEEL, sig_wheel=0.1,
                             sig_gyro=0.01, sig_gps=1.0, fix_hook=burst))
    cfg = _cfg("cauchy")
    result = run(Stream(ms, datum=DATUM, t0=0.0, t1=20.0), {
        "smoother": FixedLagSmoother(cfg, initial_pose=(0.0, 0.0, 0.0), lag=5.0),
        "ekf": UnicycleEkf(cfg, initial_pose=(0.0, 0.0, 0.0))})
    saved = SavedRun.from_result(result)
    mask, who = gps_outliers(saved, only="ekf")
    assert who == "ekf"
    moved = (saved.gps_t >= 12.0) & (saved.gps_t < 14.0)
    assert mask[moved].all() and not mask[saved.gps_t < 12.0].any()
    fig = trajectories(saved)
    labels = [h.get_label() for h in fig.axes[0].get_lines()]
    assert any(lb.startswith("GPS fixes rejected or taken for outliers by ekf") for lb in labels)
    assert any("by smoother" in lb for lb in labels)
