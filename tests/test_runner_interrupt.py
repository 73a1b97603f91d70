"""Ctrl-C in the middle of a run keeps what was estimated (runner.run(interruptible=True)), and
`ddfuse run` writes it before it stops."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation.config import load_config
from ddfuse.estimation.dead_reckoning import DeadReckoning
from ddfuse.estimation.errors import RunInterrupted
from ddfuse.estimation.runner import run
from ddfuse.evaluation import pipeline

ROOT = Path(__file__).resolve().parents[1]


def _interrupt(kind: str, ki: type = KeyboardInterrupt) -> None:
    """Raise the interrupt ``ki`` as Python raises it: plain, or (``kind`` 'in C') as a C call
    (numba's dispatcher) that returned a result while its handler's exception was pending
    reports it: SystemError from it."""
    if kind == "plain":
        raise ki
    try:
        raise ki
    except KeyboardInterrupt as e:
        raise SystemError("CPUDispatcher(<function apply_update>) returned a result with an "
                          "exception set") from e


class _CtrlC(DeadReckoning):
    """Dead reckoning that receives Ctrl-C inside its ``at``-th update, or in ``finish``
    (``kind``: how it reaches Python, ``_interrupt``)."""

    def __init__(self, cfg, at: int | None = None, in_finish: bool = False,
                 kind: str = "plain", ki: type = KeyboardInterrupt, **kw) -> None:
        super().__init__(cfg, **kw)
        self.calls, self.at, self.in_finish, self.kind, self.ki = 0, at, in_finish, kind, ki

    def process(self, m) -> None:
        self.calls += 1
        if self.calls == self.at:
            _interrupt(self.kind, self.ki)
        super().process(m)

    def finish(self) -> None:
        if self.in_finish:
            _interrupt(self.kind, self.ki)
        super().finish()


def _pose(stream):
    g = stream.ground_truth[0]
    return (g.x, g.y, g.yaw)


@pytest.mark.parametrize("kind", ["plain", "in C"])
def test_ctrl_c_inside_an_update_ends_the_feed_and_keeps_every_track(sample_husky, kind):
    """Also when the Ctrl-C came inside a compiled call and reached Python as SystemError from
    it ('in C'): an interrupt, not that estimator's failure, or the run would go on without
    it (found in the side process, its ekf_igvc stopped by 'CPUDispatcher(<function
    apply_update>) returned a result with an exception set')."""
    cfg, stream = sample_husky
    n = len(stream.measurements)
    ests = {"a": DeadReckoning(cfg, initial_pose=_pose(stream)),
            "b": _CtrlC(cfg, at=n // 2, kind=kind, initial_pose=_pose(stream))}
    res = run(stream, ests, interruptible=True)
    t_stop = stream.measurements[n // 2 - 1].t
    at = f"{t_stop - stream.measurements[0].t:.3f} s after the first measurement"
    assert res.interrupted == f"interrupted (Ctrl-C) after {n // 2 - 1} measurements, {at}"
    assert res.messages == n // 2 - 1
    a, b = res.runs["a"], res.runs["b"]
    assert b.error == f"interrupted (Ctrl-C) inside an update, {at}"
    assert a.error is None  # it had finished that message
    # both tracks up to the stop, the same dead reckoning
    assert len(a.trajectory) > 100 and a.trajectory.t[-1] <= t_stop
    k = len(b.trajectory)
    assert np.allclose(a.trajectory.pose[:k], b.trajectory.pose)
    # without interruptible, Ctrl-C stops the caller (mc, bench...) as it always did
    with pytest.raises(KeyboardInterrupt):
        run(stream, {"b": _CtrlC(cfg, at=10, kind=kind, initial_pose=_pose(stream))})


@pytest.mark.parametrize("kind", ["plain", "in C"])
def test_ctrl_c_in_one_finish_keeps_the_others(sample_husky, kind):
    cfg, stream = sample_husky
    ests = {"slow": _CtrlC(cfg, in_finish=True, kind=kind, initial_pose=_pose(stream)),
            "dr": DeadReckoning(cfg, initial_pose=_pose(stream))}
    res = run(stream, ests, interruptible=True)
    assert res.interrupted == "slow interrupted in finish"
    assert res.runs["slow"].error == "interrupted (Ctrl-C) in finish"
    assert res.runs["dr"].error is None
    assert res.runs["dr"].trajectory.t[-1] > stream.measurements[-1].t - 0.2  # to the end
    with pytest.raises(KeyboardInterrupt):
        run(stream, {"slow": _CtrlC(cfg, in_finish=True, kind=kind,
                                    initial_pose=_pose(stream))})


def test_sigterm_inside_a_compiled_call_is_named_as_sigterm(sample_husky):
    from ddfuse.estimation.interrupts import Terminated

    cfg, stream = sample_husky
    res = run(stream, {"b": _CtrlC(cfg, at=50, kind="in C", ki=Terminated,
                                   initial_pose=_pose(stream))}, interruptible=True)
    assert res.interrupted.startswith("interrupted (SIGTERM) after 49 measurements")
    assert res.runs["b"].error.startswith("interrupted (SIGTERM) inside an update")


def test_an_estimators_own_system_error_is_its_failure_not_an_interrupt(sample_husky):
    cfg, stream = sample_husky

    class Broken(DeadReckoning):
        def process(self, m):
            raise SystemError("a C extension's own bug")

    res = run(stream, {"x": Broken(cfg, initial_pose=_pose(stream)),
                       "dr": DeadReckoning(cfg, initial_pose=_pose(stream))}, interruptible=True)
    assert res.interrupted is None
    assert res.runs["x"].error.startswith("SystemError at t=")
    assert res.runs["dr"].error is None


@pytest.mark.slow
def test_run_bag_writes_the_results_then_says_it_was_interrupted(tmp_path, monkeypatch, capsys):
    from ddfuse.evaluation import estimators as registry

    monkeypatch.setitem(registry.SPECS, "dr", replace(
        registry.SPECS["dr"], make=lambda cfg, stream, pose, lag, _: _CtrlC(
            cfg, at=3000, initial_pose=pose)))
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    with pytest.raises(RunInterrupted) as e:
        pipeline.run_bag(ROOT / "data" / "sample_husky.bag", cfg, tmp_path,
                         names=["ekf", "dr"])
    assert str(tmp_path) in str(e.value) and "after 2999 measurements" in str(e.value)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["interrupted"].startswith("interrupted (Ctrl-C) after 2999 measurements")
    assert m["estimators"]["ekf"]["ate_rmse_m"] < 0.5  # scored over what it processed
    assert (tmp_path / "ekf.tum").is_file()
    # the command line: the report of what was processed, one line, Ctrl-C's exit code
    from ddfuse.evaluation import cli

    out = tmp_path / "cli"
    assert cli.main(["run", "-o", str(out), "--estimators", "ekf,dr"]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("ddfuse: interrupted (Ctrl-C) after 2999 measurements")
    assert (out / "report.html").is_file() and (out / "metrics.json").is_file()


def test_online_on_ctrl_c_prints_the_final_estimates_and_the_latency_so_far(
        monkeypatch, capsys):
    from ddfuse.evaluation import cli, online

    push = online.OnlineSession.push
    calls = []

    def push_until_ctrl_c(self, m):
        calls.append(1)
        if len(calls) == 2000:
            raise KeyboardInterrupt
        push(self, m)

    monkeypatch.setattr(online.OnlineSession, "push", push_until_ctrl_c)
    bag = ROOT / "data" / "sample_husky.bag"
    assert cli.main(["online", str(bag), "--estimators", "ekf", "--every", "50"]) == 130
    out, err = capsys.readouterr()
    assert "(at the interrupt)" in out and "update latency (ms):" in out and "(1999 updates)" in out
    assert err.strip().splitlines()[-1].startswith(
        "ddfuse: interrupted (Ctrl-C) after 1999 measurements, ")
    calls.clear()
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    with pytest.raises(KeyboardInterrupt):  # the library call stops as Ctrl-C always did
        online.replay(bag, cfg, names=["ekf"])
