"""The batch's cost grows with the bag: the default set leaves it out of a bag spanning more
than DEFAULT_MAX_SPAN_S, saying so; asked for, it says on stderr before a long solve about how
long it takes (evaluation.batch_cost)."""

from __future__ import annotations

import json

import pytest
from ddfuse.evaluation import batch_cost, pipeline
from ddfuse.evaluation.batch_cost import batch_seconds, solve_notice, solve_seconds
from ddfuse.evaluation.cli import main


def test_the_estimates_follow_the_measured_figures():
    # docs/design/outputs.md "Long bags": CPU s of the solve and of the whole batch
    for keyframes, solve, whole in ((1500, 0.66, 4.55), (4500, 1.61, 11.80),
                                    (9000, 4.37, 24.46), (18000, 8.61, 49.82)):
        assert solve_seconds(keyframes) == pytest.approx(solve, rel=0.25)
        assert batch_seconds(keyframes) == pytest.approx(whole, rel=0.25)
    assert solve_notice(300) is None and solve_notice(18000) is None  # a 2 h bag: seconds
    assert batch_cost.DEFAULT_MAX_SPAN_S > 7200.0  # the default set keeps it on a 2 h bag
    text = solve_notice(1_000_000)  # a model for a run far longer than any measured
    assert text.startswith("batch: now solving the whole run at once (1000000 keyframes): about ")
    assert "(a model" in text and "Ctrl-C skips it" in text
    left = batch_cost.leave_out_notice(86400.0, ["ekf", "smoother"])
    assert "spans 24.0 h" in left and left.endswith("--estimators ekf,smoother,batch")


def test_run_says_so_before_the_batch_solves(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(batch_cost, "NOTICE_ABOVE_S", 0.0)  # the sample's solve is short
    assert main(["run", "-o", str(tmp_path / "out"), "--estimators", "batch",
                 "--no-report"]) == 0
    err = capsys.readouterr().err
    notes = [ln for ln in err.splitlines() if ln.startswith("ddfuse: batch: ")]
    assert len(notes) == 1 and "whole run at once (300 keyframes)" in notes[0], err


@pytest.mark.slow
def test_the_default_set_leaves_the_batch_out_of_a_long_bag(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(pipeline, "DEFAULT_MAX_SPAN_S", 60.0)  # the 120 s sample is "long"
    out = tmp_path / "out"
    assert main(["run", "-o", str(out), "--no-report"]) == 0
    err = capsys.readouterr().err
    notes = [ln for ln in err.splitlines() if ln.startswith("ddfuse: batch: left out")]
    assert len(notes) == 1 and "--estimators ekf," in notes[0] and notes[0].endswith(",batch")
    run = json.loads((out / "metrics.json").read_text())
    assert "batch" not in run["estimators"] and "ekf" in run["estimators"]
    assert not (out / "batch.tum").exists()
    # asked for by name it runs, however long the bag
    assert main(["run", "-o", str(tmp_path / "named"), "--estimators", "ekf,batch",
                 "--no-report"]) == 0
    assert "left out" not in capsys.readouterr().err
    assert (tmp_path / "named" / "batch.tum").exists()
