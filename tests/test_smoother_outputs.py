"""The smoother computes its lagged output only when a caller uses it: the filtered output and
the final state are the same either way, and every path that builds estimators by track name
(run, online, bench) turns the lagged output on exactly when its track is asked for."""

from __future__ import annotations

import numpy as np
import pytest
from ddfuse.estimation.runner import run
from ddfuse.estimation.smoother import BatchSmoother, FixedLagSmoother
from ddfuse.evaluation import estimators as registry
from ddfuse.evaluation.online import OnlineSession


def _pose0(stream):
    g = stream.ground_truth[0]
    return (g.x, g.y, g.yaw)


def test_without_the_lagged_output_the_filtered_output_and_final_state_are_unchanged(
        sample_husky):
    cfg, stream = sample_husky
    both = FixedLagSmoother(cfg, initial_pose=_pose0(stream))
    filtered = FixedLagSmoother(cfg, initial_pose=_pose0(stream), lagged=False)
    res = run(stream, {"a": both, "b": filtered})
    assert set(res.runs) == {"a", "a_lagged", "b"}
    assert filtered.lagged_estimates() is None
    ta, tb = res.runs["a"].trajectory, res.runs["b"].trajectory
    np.testing.assert_array_equal(ta.t, tb.t)
    np.testing.assert_array_equal(ta.pose, tb.pose)
    np.testing.assert_array_equal(ta.cov, tb.cov)
    fa, fb = both.final_state(), filtered.final_state()
    assert fa.t == fb.t
    np.testing.assert_array_equal(fa.state, fb.state)
    np.testing.assert_array_equal(fa.state_cov, fb.state_cov)
    # the lagged track's own entries are many (one per keyframe), not just the final one
    assert len(res.runs["a_lagged"].trajectory.t) > 100


@pytest.mark.parametrize("tracks, lagged", [
    (None, True), (["smoother"], False), (["smoother_lagged"], True),
    (["ekf", "smoother", "smoother_lagged"], True), (["ekf", "smoother"], False)])
def test_build_turns_the_lagged_output_on_only_when_its_track_is_wanted(sample_husky, tracks,
                                                                        lagged):
    cfg, stream = sample_husky
    names = [n for n in tracks or ["ekf", "smoother"]]
    ests = registry.build(cfg, stream, names, tracks=tracks)
    assert ests["smoother"].lagged is lagged


def test_the_batch_and_an_online_session_never_compute_a_lagged_track(sample_husky):
    cfg, stream = sample_husky
    assert BatchSmoother(cfg).lagged is False
    session = OnlineSession.from_config(cfg, ["ekf", "smoother"], stream=stream)
    assert session.estimators["smoother"].lagged is False
    session = OnlineSession.from_config(cfg, stream=stream)
    assert session.estimators["smoother"].lagged is False
