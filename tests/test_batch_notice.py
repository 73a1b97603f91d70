"""On a long bag the batch's whole-run solve is most of the run: the default set leaves it out
of a bag spanning more than DEFAULT_MAX_SPAN_S, saying so; asked for, it says on stderr before
its solve that it is the slow part and about how long it takes (evaluation.batch_cost)."""

from __future__ import annotations

import json

from ddfuse.evaluation import batch_cost, pipeline
from ddfuse.evaluation.batch_cost import solve_notice, solve_seconds
from ddfuse.evaluation.cli import main


def test_the_solve_estimate_follows_the_measured_figures():
    # docs/design/outputs.md: 1500 keyframes 16.5 s, 4500 keyframes 224 s
    assert abs(solve_seconds(1500) - 16.5) < 1.0 and abs(solve_seconds(4500) - 224) < 10
    assert solve_notice(300) is None  # the sample bag's: nothing said
    text = solve_notice(18000)  # a 2 h bag
    assert text.startswith("batch: now solving the whole run at once (18000 keyframes), the "
                           "slow part of this run: about ")
    assert " h (a model" in text and "Ctrl-C skips it" in text


def test_run_says_so_before_the_batch_solves(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(batch_cost, "NOTICE_ABOVE_S", 0.0)  # the sample's solve is short
    assert main(["run", "-o", str(tmp_path / "out"), "--estimators", "batch",
                 "--no-report"]) == 0
    err = capsys.readouterr().err
    notes = [ln for ln in err.splitlines() if ln.startswith("ddfuse: batch: ")]
    assert len(notes) == 1 and "whole run at once (300 keyframes)" in notes[0], err


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
