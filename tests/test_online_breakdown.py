"""An online session stops an estimator whose estimate breaks down, as ``run`` does."""

from __future__ import annotations

from pathlib import Path

from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.dead_reckoning import DeadReckoning
from ddfuse.evaluation.online import OnlineSession
from test_runner_guards import _Diverging

ROOT = Path(__file__).resolve().parents[1]


def test_a_session_stops_an_estimator_whose_estimate_breaks_down():
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    stream = read_stream(ROOT / "data" / "sample_husky.bag", cfg)
    s = OnlineSession({"bad": _Diverging(cfg, 30.0, "negative"), "good": DeadReckoning(cfg)})
    for m in stream.measurements:
        s.push(m)
        s.estimate("bad")
    s.finish()
    assert s.errors["bad"].startswith("FloatingPointError at t=")
    assert "numerical breakdown: pose" in s.errors["bad"]
    last = s.estimate("bad")
    assert not last.pose_cov[0, 0] < 0 and last.t - stream.measurements[0].t < 30.0
    assert s.errors["good"] is None


def test_a_ctrl_c_inside_a_compiled_update_stops_the_session_not_the_estimator():
    """A Ctrl-C that came inside a compiled call reaches Python as SystemError from it; the
    session raises it as the interrupt (as a plain one), its estimator marked interrupted,
    instead of stopping that estimator for a failure and going on."""
    import pytest
    from test_runner_interrupt import _CtrlC

    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    stream = read_stream(ROOT / "data" / "sample_husky.bag", cfg)
    s = OnlineSession({"c": _CtrlC(cfg, at=40, kind="in C"), "good": DeadReckoning(cfg)})
    with pytest.raises(KeyboardInterrupt):
        for m in stream.measurements:
            s.push(m)
    assert s.errors["c"].startswith("interrupted (Ctrl-C) inside an update")
    assert s.errors["good"] is None
