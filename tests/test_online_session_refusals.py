"""``OnlineSession`` refuses what it cannot do, with an error that says what was wrong: a
truth-started config with no truth, pushes after finish()."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.measurements import Stream
from ddfuse.evaluation.online import OnlineSession

ROOT = Path(__file__).resolve().parents[1]
BAG, CFG = ROOT / "data" / "sample_husky.bag", ROOT / "data" / "sample_husky.yaml"


@pytest.fixture(scope="module")
def stream():
    return read_stream(BAG, load_config(CFG))


def test_ground_truth_start_without_truth_is_refused(stream):
    """sample_husky.yaml says initial_pose: ground_truth. Without stream= the EKFs waited for
    a truth pose never pushed: after the whole bag, estimate None and errors None."""
    cfg = load_config(CFG)
    with pytest.raises(ValueError, match=r"sample_husky.yaml: initial_pose: ground_truth, but "
                                         r"no truth pose to start from \(no stream= given\); "
                                         r"give initial_pose as \[x, y, yaw\]"):
        OnlineSession.from_config(cfg, ["ekf", "smoother"])
    with pytest.raises(ValueError, match=r"\(the stream given has no ground truth\)"):
        OnlineSession.from_config(cfg, ["ekf"], stream=Stream(measurements=[]))
    # with the truth, the EKFs start at its first pose; without the setting, from the GPS
    for s in (OnlineSession.from_config(cfg, ["ekf", "ekf_igvc"], stream=stream),
              OnlineSession.from_config(replace(cfg, initial_pose=None), ["ekf", "ekf_igvc"])):
        for m in stream.measurements:
            if m.t - stream.t0 > 20.0:
                break
            s.push(m)
        s.flush()
        for name in s.estimators:
            assert s.errors[name] is None and s.estimate(name) is not None, name


def test_push_after_finish_is_refused(stream):
    """After finish() the EKFs took further pushes silently and the smoother was stopped with
    "KeyError at t=104.000: 6"."""
    cfg = replace(load_config(CFG), initial_pose=None)
    s = OnlineSession.from_config(cfg, ["ekf", "smoother"])
    meas = [m for m in stream.measurements if m.t - stream.t0 <= 10.0]
    for m in meas[:-50]:
        s.push(m)
    s.finish()
    before = {n: s.estimate(n) for n in s.estimators}
    late = meas[-1]
    with pytest.raises(RuntimeError, match=rf"^OnlineSession \(ekf, smoother\) is finished: "
                                           rf"push\({type(late).__name__} at t={late.t!r}\) "
                                           r"after finish\(\) is refused; build a new session"):
        s.push(late)
    s.finish()  # a second finish does nothing: the estimators are not ended twice
    assert s.errors == {"ekf": None, "smoother": None}
    for n, e in before.items():
        assert s.estimate(n).t == e.t, n
