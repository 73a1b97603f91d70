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
