"""What the runner does with an estimator whose numbers break down: stop it there, keep its
track up to the last sound estimate, say why, and let the others go on."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.dead_reckoning import DeadReckoning
from ddfuse.estimation.runner import broken, run

ROOT = Path(__file__).resolve().parents[1]


class _Diverging(DeadReckoning):
    """Dead reckoning whose estimates from ``t_break`` s on carry ``fault`` ('negative': a
    negative x variance, as a filter whose covariance lost positive definiteness; 'huge': an x
    variance of 1e21 m^2, as one inflated past meaning, yaw 3e21 rad^2 on the way to that in
    the unicycle EKF with IMU sigmas of 1e-9; 'nan': a NaN position)."""

    def __init__(self, cfg, t_break: float, fault: str, **kw) -> None:
        super().__init__(cfg, **kw)
        self.t_break, self.fault, self.t0 = t_break, fault, None

    def estimate(self):
        e = super().estimate()
        if e is None:
            return None
        self.t0 = e.t if self.t0 is None else self.t0
        if e.t - self.t0 < self.t_break:
            return e
        if self.fault == "nan":
            return replace(e, pose=(math.nan, e.pose[1], e.pose[2]))
        cov = e.pose_cov.copy()
        cov[0, 0] = -1e120 if self.fault == "negative" else 1e21
        return replace(e, pose_cov=cov)


@pytest.fixture(scope="module")
def sample():
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    return cfg, read_stream(ROOT / "data" / "sample_husky.bag", cfg)


@pytest.mark.parametrize("fault", ["negative", "nan", "huge"])
def test_an_estimator_whose_estimate_breaks_down_is_stopped_and_keeps_its_track(sample, fault):
    """Before, a unicycle EKF with the IMU noise at 1e-9 ended 3e29 m away with pose variances
    of -5e121 in its CSV, error None."""
    cfg, stream = sample
    r = run(stream, {"bad": _Diverging(cfg, 30.0, fault), "good": DeadReckoning(cfg)}).runs
    bad, good = r["bad"], r["good"]
    assert bad.error.startswith("numerical breakdown at t=")
    assert "lost positive definiteness" in bad.error
    assert bad.trajectory.t[-1] - bad.trajectory.t[0] < 30.0  # nothing after the breakdown
    assert np.isfinite(bad.trajectory.pose).all()
    assert not (np.diagonal(bad.trajectory.cov, axis1=1, axis2=2) < 0).any()
    assert good.error is None and good.trajectory.t[-1] - good.trajectory.t[0] > 119.0
    assert any("stopped: numerical breakdown" in n for n in bad.log.messages)


def test_broken_names_what_is_wrong(sample):
    cfg, stream = sample
    e = run(stream, {"dr": DeadReckoning(cfg)}).runs["dr"]
    assert e.error is None
    good = _Diverging(cfg, 1e9, "nan")
    for m in stream.measurements[:200]:
        good.process(m)
    est = good.estimate()
    assert broken(est) is None  # dead reckoning's NaN covariance is 'none', not broken
    est = replace(est, pose_cov=np.diag([0.1, 0.1, 0.01]))
    assert broken(est) is None
    cov = est.pose_cov.copy()
    cov[2, 2] = -1.0
    assert "pose variances" in broken(replace(est, pose_cov=cov))
    assert broken(replace(est, pose=(1.0, math.inf, 0.0))).startswith("pose (1, inf, 0)")


def test_run_refuses_a_finished_estimator_and_a_zero_output_rate(sample):
    cfg, stream = sample
    est = DeadReckoning(cfg)
    with pytest.raises(ValueError, match="output_rate: expected Hz > 0, got 0"):
        run(stream, {"dr": est}, output_rate=0)
    ok = replace(stream, measurements=stream.measurements[:200])
    assert len(run(ok, {"dr": est}).runs["dr"].trajectory)
    with pytest.raises(ValueError, match="'dr' was already run to its end"):
        run(ok, {"dr": est})


def test_a_gps_innovation_with_a_singular_covariance_has_infinite_nis_without_a_warning():
    """An absurd config (a slip of 1e20) can leave the fix's innovation covariance with a
    determinant that is not positive: its NIS is infinite (the fix cannot be judged), and numpy's
    divide-by-zero warning no longer reaches the user's terminal."""
    import types
    import warnings

    from ddfuse.estimation.estimator import EstimatorLog
    from ddfuse.estimation.measurements import GpsFix
    from ddfuse.estimation.smoother.gps import GpsFusion

    fusion = types.SimpleNamespace(log=EstimatorLog())
    fix = GpsFix(t=1.0, lat=0.0, lon=0.0, alt=0.0, cov=np.eye(3), enu=(3.0, 4.0, 0.0))
    st = np.zeros(9)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        singular = GpsFusion.innovation(fusion, fix, (0.0, 0.0), 0.0, np.zeros((2, 2)), st,
                                        np.zeros((9, 9)))
        regular = GpsFusion.innovation(fusion, fix, (0.0, 0.0), 0.0, np.eye(2), st,
                                       np.zeros((9, 9)))
    assert singular == float("inf")
    assert regular == pytest.approx(25.0)
    assert len(fusion.log.innovations) == 2


def test_every_track_has_increasing_stamps_when_an_estimator_has_nothing_newer(tmp_path):
    """At the first 10 Hz tick of a simulated drive from rest the smoother has had no odometry
    sample since it started, so its estimate still has the start's stamp: recorded again it
    gave its track two samples with one stamp (loop-stops, gps-outage and husky-multipath,
    seed 7). A track's stamps only increase."""
    from ddfuse.evaluation.estimators import build
    from ddfuse.evaluation.simulate import simulate, write_bag

    bag, cfg_path, _ = write_bag(simulate("loop-stops", seed=7, duration=20.0),
                                 tmp_path / "ls.bag")
    cfg = load_config(cfg_path)
    stream = read_stream(bag, cfg)
    result = run(stream, build(cfg, stream, ["ekf", "smoother"]))
    for name, r in result.runs.items():
        t = r.trajectory.t
        assert r.error is None and len(t) > (40 if name == "smoother_lagged" else 150), name
        assert np.all(np.diff(t) > 0.0), (name, t[:3])


class _Raising(DeadReckoning):
    """Dead reckoning that raises gtsam's kind of message (a paragraph: a blank first line,
    the reason, the variable on the next line, advice) at its 500th update, or in finish."""

    TEXT = ("\nIndeterminate linear system detected while working near variable\n"
            "8646911284551352381 (Symbol: x61).\n\nThrown when a linear system is ill-posed.\n")

    def __init__(self, cfg, where: str) -> None:
        super().__init__(cfg)
        self.where, self.n = where, 0

    def process(self, m):
        self.n += 1
        if self.where == "update" and self.n == 500:
            raise RuntimeError(self.TEXT)
        return super().process(m)

    def finish(self):
        if self.where == "finish":
            raise RuntimeError(self.TEXT)
        return super().finish()


@pytest.mark.parametrize("where", ["update", "finish"])
def test_a_multi_line_exception_is_one_line_in_the_error_row(sample, where):
    """gtsam's messages are paragraphs; the run's error row (metrics.json, the table, the
    report) takes the reason and the variable it names, on one line."""
    cfg, stream = sample
    err = run(stream, {"bad": _Raising(cfg, where)}).runs["bad"].error
    assert "\n" not in err
    assert err.endswith("Indeterminate linear system detected while working near variable x61")


def test_gtsams_own_exception_text_becomes_one_line_naming_the_variable():
    import gtsam
    from ddfuse.estimation.errors import error_line

    x0, x1 = gtsam.symbol("x", 0), gtsam.symbol("x", 1)
    graph = gtsam.NonlinearFactorGraph()  # x1 tied to x0 only: no prior, indeterminate
    graph.add(gtsam.BetweenFactorPose2(x0, x1, gtsam.Pose2(), gtsam.noiseModel.Unit.Create(3)))
    values = gtsam.Values()
    values.insert(x0, gtsam.Pose2())
    values.insert(x1, gtsam.Pose2())
    with pytest.raises(RuntimeError) as e:
        gtsam.Marginals(graph, values)
    line = error_line(str(e.value))
    assert "\n" not in line and line.startswith("Indeterminate linear system")
    assert line.endswith(" x0") or line.endswith(" x1")
    assert "\n" in str(e.value)  # what it was made from
