"""SIGTERM stops a run as Ctrl-C does (results of what was seen written, exit 143), and an
interrupt wherever it lands in the run (inside an innovation log's compaction, while the results
are written, during the report) takes the interrupt path, never a traceback."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation.config import load_config
from ddfuse.estimation.dead_reckoning import DeadReckoning
from ddfuse.estimation.estimator import Innovation, InnovationLog
from ddfuse.estimation.interrupts import held_signals
from ddfuse.estimation.runner import run
from ddfuse.evaluation import pipeline
from ddfuse.evaluation.run_files import INCOMPLETE

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / "data" / "sample_husky.bag"


pytestmark = pytest.mark.usefixtures("ctrl_c_raises")


class _Sigint(float):
    """A residual value whose conversion sends this process SIGINT: Ctrl-C landing inside
    ``InnovationLog.compact``, between its columns' updates."""

    def __float__(self):
        signal.raise_signal(signal.SIGINT)
        return 1.0


def _inn(t: float, signal_in_it: bool = False) -> Innovation:
    return Innovation(t, "odom", "v", [_Sigint(1.0) if signal_in_it else 1.0, 2.0], np.eye(2),
                      1.0)


def test_ctrl_c_inside_compact_is_raised_once_the_columns_agree():
    """Before: the KeyboardInterrupt cut compact in two, the columns had different lengths
    (1499 codes, 1000 stamps) and scoring ended in an IndexError traceback."""
    log = InnovationLog()
    for k in range(100):
        log.append(_inn(k * 0.1, signal_in_it=k == 50))
    with pytest.raises(KeyboardInterrupt):
        log.compact()
    assert len(log._t) == len(log._g) == len(log._roff) == len(log._acc) == len(log) == 100
    assert not log._pending and len(log.columns()["t"]) == 100


class _LoggingDr(DeadReckoning):
    """Dead reckoning that logs one innovation per message, the 1500th holding a SIGINT."""

    def process(self, m) -> None:
        super().process(m)
        self.n = getattr(self, "n", 0) + 1
        self.log.innovations.append(_inn(m.t, signal_in_it=self.n == 1500))


def test_ctrl_c_landing_in_the_runners_compaction_takes_the_interrupt_path(sample_husky):
    cfg, stream = sample_husky
    g = stream.ground_truth[0]
    res = run(stream, {"dr": _LoggingDr(cfg, initial_pose=(g.x, g.y, g.yaw))},
              interruptible=True)
    # the runner compacts every 1000 messages: the one holding the signal is compacted at 2000
    assert res.interrupted.startswith("interrupted (Ctrl-C) after 2000 measurements, ")
    nis = pipeline.score(res).estimators["dr"].nis["odom v"]
    assert nis.accepted == 2000 and nis.nis.n == 2000


def test_a_signal_while_results_are_written_is_held_until_they_are_complete(tmp_path,
                                                                            monkeypatch):
    """Ctrl-C (or SIGTERM) after the estimators finished, while the results are scored and
    written: they are written whole, then the run says it was interrupted."""
    from ddfuse.estimation.errors import RunInterrupted
    from ddfuse.evaluation import run_files

    real = run_files.write_metrics

    def write_metrics_after_ctrl_c(outdir, d):
        signal.raise_signal(signal.SIGINT)
        real(outdir, d)

    monkeypatch.setattr(pipeline, "write_metrics", write_metrics_after_ctrl_c)
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    with pytest.raises(RunInterrupted, match=r"^interrupted \(Ctrl-C\) while the results were "
                       r"written; they are complete, in "):
        pipeline.run_bag(BAG, cfg, tmp_path, names=["dr"])
    assert json.loads((tmp_path / "metrics.json").read_text())["interrupted"] is None
    assert not (tmp_path / INCOMPLETE).exists()


def test_a_second_signal_in_a_held_block_acts_at_once():
    with pytest.raises(KeyboardInterrupt), held_signals() as held:
        signal.raise_signal(signal.SIGINT)
        assert held == [signal.SIGINT]
        signal.raise_signal(signal.SIGINT)
        pytest.fail("the second Ctrl-C was held too")
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_run_sent_sigterm_writes_what_it_had_and_exits_143(tmp_path):
    """A real process sent SIGTERM mid-run (as `timeout` or `docker stop` do). Before: killed
    at once, exit 143 from the shell (-15 here), nothing written."""
    out, started = tmp_path / "out", tmp_path / "started"
    script = textwrap.dedent(f"""
        import sys, time
        from pathlib import Path
        from ddfuse.estimation.dead_reckoning import DeadReckoning
        from ddfuse.evaluation.cli.dispatch import entry
        process, calls = DeadReckoning.process, []
        def slow(self, m):  # a long bag: the signal comes mid-run
            calls.append(1)
            if len(calls) == 2000:
                Path({str(started)!r}).touch()
            if len(calls) >= 2000:
                time.sleep(0.002)
            process(self, m)
        DeadReckoning.process = slow
        sys.argv = ["ddfuse", "run", "-o", {str(out)!r}, "--estimators", "dr", "--no-report"]
        entry()
    """)
    p = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while not started.exists() and p.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        p.send_signal(signal.SIGTERM)
        stdout, stderr = p.communicate(timeout=240)
    finally:
        p.kill()
    assert p.returncode == 143, stderr
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("ddfuse: interrupted (SIGTERM) after ") and str(out) in last, stderr
    assert "Traceback" not in stderr and "wall time" in stdout  # the table of what it had
    m = json.loads((out / "metrics.json").read_text())
    assert m["interrupted"].startswith("interrupted (SIGTERM) after ")
    # the signal can land while the 2000th message is in hand: 1999 counted (clean-clone CI)
    assert 1999 <= m["messages"] < 12000 and m["estimators"]["dr"]["samples"] > 100
    assert not (out / INCOMPLETE).exists()


def test_ctrl_c_during_the_report_says_how_to_render_it_later(tmp_path, monkeypatch, capsys):
    from ddfuse.evaluation import report
    from ddfuse.evaluation.cli import main

    def ctrl_c(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(report, "make_figures", ctrl_c)
    out = tmp_path / "out"
    assert main(["run", "-o", str(out), "--estimators", "dr"]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (f"ddfuse: interrupted (Ctrl-C) while the report was rendered: the "
                       f"results in {out}/ are complete; 'ddfuse report {out}' renders it")
    assert (out / "metrics.json").is_file() and not (out / "report.html").exists()



def test_sigterm_is_held_only_where_it_would_raise(monkeypatch):
    """Taken as an interrupt (the command line's handler), SIGTERM is held like Ctrl-C and
    sets the exit code's flag; left to the system (a library caller), it is not touched."""
    from ddfuse.estimation import interrupts

    monkeypatch.setattr(interrupts, "_received", [])
    before = signal.getsignal(signal.SIGTERM)
    try:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        with held_signals():
            assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
        interrupts.terminate_as_interrupt()
        with held_signals() as held:
            signal.raise_signal(signal.SIGTERM)
        assert held == [signal.SIGTERM] and interrupts.sigterm_received()
        with pytest.raises(interrupts.Terminated):
            interrupts.deliver(held)
    finally:
        signal.signal(signal.SIGTERM, before)
