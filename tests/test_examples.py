"""Smoke test of the maintained examples under examples/: each runs on the shipped sample data
(or a short simulation) and prints its table."""

from __future__ import annotations

import runpy
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _main(name: str):
    return runpy.run_path(str(EXAMPLES / name), run_name="example")["main"]


def test_compare_estimators_on_the_sample_bag(capsys):
    _main("compare_estimators.py")(["--estimators", "ekf,smoother"])
    head, *rows = capsys.readouterr().out.strip().splitlines()
    assert head.split()[:3] == ["estimator", "ATE", "m"]
    ate = {r.split()[0]: float(r.split()[1]) for r in rows}
    # metrics.json's figures of ``ddfuse run`` on the sample bag (the smoother gives its lagged
    # output too)
    assert ate == {"ekf": pytest.approx(0.114, abs=6e-4),
                   "smoother": pytest.approx(0.101, abs=6e-4),
                   "smoother_lagged": pytest.approx(0.088, abs=6e-4)}


def test_monte_carlo_of_a_short_scenario(capsys):
    pytest.importorskip("gtsam")
    _main("monte_carlo.py")(["husky", "--seeds", "1-2", "--duration", "20"])
    out = capsys.readouterr().out
    assert "husky" in out and "ekf" in out and "ANEES" in out


@pytest.mark.slow
def test_urban_study_of_one_short_seed(tmp_path, capsys):
    """The urban GPS study (docs/results/urban.md) on one 60 s seed: it writes a result per
    seed and model, and the table prints a row for it."""
    pytest.importorskip("gtsam")
    out = tmp_path / "urban.json"
    main = _main("urban_study.py")
    assert main(["--seeds", "3", "--models", "default,cauchy", "--duration", "60",
                 "--json", str(out)]) == 0
    assert main(["--json", str(out), "--table"]) == 0
    text = capsys.readouterr().out
    assert "3" in text and "cauchy" in text


def test_tune_recovery_cuts_both_ends_of_the_stream():
    """``--trim S`` (docs/design/tuning.md, the odometry v's bias): what is within S s of
    either end goes, measurements and ground truth alike; the rest stays, in order."""
    from types import SimpleNamespace

    from ddfuse.estimation.measurements import Stream

    cut = runpy.run_path(str(EXAMPLES / "tune_recovery.py"), run_name="example")["cut_ends"]
    ts = [0.0, 1.0, 5.9, 6.0, 50.0, 114.0, 114.1, 120.0]
    s = Stream([SimpleNamespace(t=t) for t in ts], ground_truth=[SimpleNamespace(t=t) for t in ts],
               t0=0.0, t1=120.0)
    cut(s, 0.0)
    assert [m.t for m in s.measurements] == ts
    cut(s, 6.0)
    assert [m.t for m in s.measurements] == [6.0, 50.0, 114.0]
    assert [g.t for g in s.ground_truth] == [6.0, 50.0, 114.0]


def test_landmark_residuals_tells_a_frame_common_bearing_error_from_an_own_one():
    """``examples/landmark_residuals.py residuals`` (docs/design/tuning.md, session 21): two
    landmarks seen in every frame, the bearings err by a rotation common to the frame
    (sigma 0.02 rad) plus their own (0.005 rad): the pairs' correlation is near
    0.02^2 / (0.02^2 + 0.005^2) = 0.94, half their difference's sigma near 0.005 rad; the ranges
    err independently (+0.03 m +- 0.01 m): uncorrelated, that median and sigma in every band."""
    import math

    import numpy as np
    from ddfuse.estimation.measurements import GroundTruthPose, LandmarkObservation, Stream

    residuals = runpy.run_path(str(EXAMPLES / "landmark_residuals.py"),
                               run_name="example")["residuals"]
    rng = np.random.default_rng(1)
    marks = {"a": (3.0, 1.0), "b": (2.0, -2.0)}
    truth = [GroundTruthPose(0.1 * k, 0.001 * k, 0.0, 0.3 * math.sin(0.01 * k))
             for k in range(2001)]
    sightings = []
    for p in truth[:-1]:
        common = rng.normal(0.0, 0.02)
        for lid, (lx, ly) in marks.items():
            r = math.hypot(lx - p.x, ly - p.y)
            b = math.atan2(ly - p.y, lx - p.x) - p.yaw + common + rng.normal(0.0, 0.005)
            sightings.append(LandmarkObservation(p.t, lid, r + 0.03 + rng.normal(0.0, 0.01), b,
                                                 0.01, 0.0025))
    out = residuals(Stream(sightings, ground_truth=truth, landmarks=marks))
    line = next(x for x in out.splitlines() if x.startswith("sightings of different"))
    corr = float(line.split("bearing errors correlated ")[1].split(",")[0])
    half = float(line.split("half the bearing difference ")[1].split(" ")[0])
    assert corr == pytest.approx(0.94, abs=0.02)
    assert half == pytest.approx(0.005, rel=0.1)
    assert abs(float(line.split("range errors ")[1].split(";")[0])) < 0.1
    bands = [x.split("|")[2:4] for x in out.splitlines() if x.startswith("| ")
             and " m | " in x[:12]]
    assert sum(int(n) for n, _ in bands) == 4000
    for _, cell in bands:
        med, sig = (float(v) for v in cell.split(","))
        assert med == pytest.approx(0.03, abs=0.004) and sig == pytest.approx(0.01, rel=0.25)
