"""On a long bag the batch's whole-run solve is most of the run: before it starts, `ddfuse run`
says on stderr that it is the slow part and about how long it takes (evaluation.batch_cost)."""

from __future__ import annotations

from ddfuse.evaluation import batch_cost
from ddfuse.evaluation.batch_cost import solve_notice, solve_seconds
from ddfuse.evaluation.cli import main


def test_the_solve_estimate_follows_the_measured_figures():
    # docs/design/outputs.md: 300 keyframes 4.9 s, 1500 keyframes 97.7 s
    assert abs(solve_seconds(300) - 4.9) < 0.5 and abs(solve_seconds(1500) - 97.7) < 5
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
