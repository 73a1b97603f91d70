"""With the smoother and the batch in one run, the batch solves the graph of the smoother's own
online run (``SharedBatch``) instead of running the smoother a second time: every output, log
and score as with a batch of its own, in either order; and where the smoother stops, the batch
stops with it and says why."""

from __future__ import annotations

import numpy as np
import pytest
from ddfuse.estimation.runner import run
from ddfuse.estimation.smoother import BatchSmoother, FixedLagSmoother, SharedBatch
from ddfuse.evaluation import estimators as registry
from ddfuse.evaluation.consistency import InnovationTable


def _tracks(result, name):
    tr = result.runs[name].trajectory
    return tr.t, tr.pose, tr.cov


def _same_run(a, b, name):
    for x, y in zip(_tracks(a, name), _tracks(b, name), strict=True):
        np.testing.assert_array_equal(x, y)
    la, lb = a.runs[name].log, b.runs[name].log
    assert la.rejected == lb.rejected
    ta, tb = (InnovationTable.from_innovations(x.innovations) for x in (la, lb))
    assert len(ta.nis) > 100
    np.testing.assert_array_equal(ta.nis, tb.nis)
    np.testing.assert_array_equal(ta.t, tb.t)


@pytest.fixture(scope="module")
def apart(sample_husky):
    """The sample bag run with each estimator built on its own (no sharing)."""
    cfg, stream = sample_husky
    ests = {n: registry.build(cfg, stream, [n])[n] for n in ("smoother", "batch")}
    assert isinstance(ests["batch"], BatchSmoother)
    return run(stream, ests)


@pytest.mark.parametrize("order", [["smoother", "batch"], ["batch", "smoother"]])
def test_the_shared_batch_is_the_batch_and_the_smoother_unchanged(sample_husky, apart, order):
    cfg, stream = sample_husky
    ests = registry.build(cfg, stream, order)
    assert list(ests) == order and isinstance(ests["batch"], SharedBatch)
    assert ests["batch"].source is ests["smoother"] and ests["smoother"].keep_all
    together = run(stream, ests)
    for name in ("smoother", "smoother_lagged", "batch"):
        _same_run(apart, together, name)
    assert together.runs["batch"].error is None
    # its own note first, then the smoother's
    notes = together.runs["batch"].log.messages
    assert "shares the smoother's online run" in notes[0]
    assert notes[1:] == together.runs["smoother"].log.messages
    # the final state: the solve's last keyframe, whole
    fa, fb = apart.runs["batch"].final_state, together.runs["batch"].final_state
    np.testing.assert_array_equal(fa.state, fb.state)
    np.testing.assert_array_equal(fa.state_cov, fb.state_cov)


@pytest.mark.parametrize("fault", ["error", "interrupt"])
def test_the_batch_stops_where_its_smoother_stops(sample_husky, monkeypatch, fault):
    """An error in the smoother's update, or Ctrl-C inside it (its state half-updated): the
    batch does not solve what that run left, and says why."""
    cfg, stream = sample_husky
    ests = registry.build(cfg, stream, ["smoother", "batch"])
    t_fail = stream.measurements[0].t + 30.0
    real = FixedLagSmoother.process

    def failing(self, m):
        if m.t >= t_fail:
            raise ArithmeticError("injected") if fault == "error" else KeyboardInterrupt
        return real(self, m)

    monkeypatch.setattr(FixedLagSmoother, "process", failing)
    result = run(stream, ests, interruptible=True)
    smoother, batch = result.runs["smoother"], result.runs["batch"]
    said = "ArithmeticError at t=" if fault == "error" else "interrupted (Ctrl-C) inside an update"
    assert said in smoother.error
    assert batch.error == f"stopped with smoother, whose online run it solves: {smoother.error}"
    assert "stopped: stopped with smoother" in batch.log.messages[-1]
    assert len(batch.trajectory.t) == 0  # no whole-run solve of a run cut short


def test_it_needs_a_smoother_that_keeps_every_factor(sample_husky):
    cfg, _ = sample_husky
    with pytest.raises(ValueError, match="keep_all"):
        SharedBatch(FixedLagSmoother(cfg))
