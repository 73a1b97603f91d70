"""The batch smoother: every factor of the run, solved at the end with Levenberg-Marquardt, the
offline optimum the fixed-lag outputs are compared with. Its trajectory is at the keyframes
(poses in local ENU, marginal covariances from ``gtsam.Marginals``)."""

from __future__ import annotations

import math

import gtsam
import numpy as np
from ddfuse.estimation.config import Config
from ddfuse.estimation.errors import error_line
from ddfuse.estimation.estimator import Estimate, Estimator, EstimatorLog
from ddfuse.estimation.runner import TrackBuilder
from ddfuse.estimation.smoother.batch_banded import BandedSystem
from ddfuse.estimation.smoother.batch_factors import VectorisedGraph
from ddfuse.estimation.smoother.batch_lm import levenberg_marquardt
from ddfuse.estimation.smoother.fixed_lag import FixedLagSmoother
from ddfuse.factors.state import NAMES
from threadpoolctl import ThreadpoolController

_controller: list[ThreadpoolController] = []


def _blas() -> ThreadpoolController:
    """The process's BLAS libraries (found once: the search reads every loaded library)."""
    if not _controller:
        _controller.append(ThreadpoolController())
    return _controller[0]


def _solve(window, system: VectorisedGraph, params: gtsam.LevenbergMarquardtParams
           ) -> tuple[list[int], np.ndarray, np.ndarray]:
    """The whole run's LM solution: its keys, their states (n, 9) and marginal covariances
    (n, 9, 9) in that order; RuntimeError where the system cannot be solved."""
    banded = BandedSystem.build(system, window.all_values)
    if banded is not None:
        result = levenberg_marquardt(window.all_graph, window.all_values, params, banded).values
        return banded.keys, banded.states(result), banded.marginals(result)
    result = levenberg_marquardt(window.all_graph, window.all_values, params, system).values
    marg = gtsam.Marginals(system.linearize(result), result)
    keys = sorted(int(k) for k in result.keys())  # noqa: SIM118 (Values: no __iter__)
    return (keys, np.array([result.atVector(k) for k in keys]),
            np.array([marg.marginalCovariance(k) for k in keys]))


def whole_run(smoother: FixedLagSmoother, log: EstimatorLog) -> TrackBuilder:
    """The Levenberg-Marquardt solve of every factor ``smoother`` (a finished one built with
    ``keep_all``) kept, at its keyframes: poses in local ENU, marginal covariances; empty, with a
    note in ``log``, where the whole run's system cannot be solved."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(20)
    params.setRelativeErrorTol(1e-6)
    window, final = smoother.window, TrackBuilder()
    try:
        # gtsam's LM iterated from Python (its own optimizer would hand every CustomFactor
        # callback a copy of the whole run's Values), with the preintegrated and
        # bias-difference factors evaluated together with numpy (batch_lm, batch_factors),
        # the normal equations solved as one banded matrix where they are one
        # (batch_banded); BLAS's threads only cost more on these small blocks
        with _blas().limit(limits=1, user_api="blas"):
            keys, states, covs = _solve(window, VectorisedGraph(window.all_graph,
                                                                smoother.factor_record), params)
    except RuntimeError as e:
        log.note(smoother.twist.last_t, f"batch optimisation failed: {error_line(str(e))}"
                 ": the whole run's system is ill-conditioned; check the config's noise "
                 "values, priors and delays")
        return final
    index = {k: i for i, k in enumerate(keys)}
    order = sorted(window.all_kf_t.items(), key=lambda jt: jt[1])
    rows = np.array([index[int(window.key(j))] for j, _ in order], dtype=int)
    x, cov = states[rows], covs[rows]
    gauge = window.gauge_vars(np.array([j for j, _ in order]))
    cov[:, 0, 0] += gauge
    cov[:, 1, 1] += gauge
    pose = np.column_stack((x[:, 0], x[:, 1], np.remainder(x[:, 2] + math.pi, 2.0 * math.pi)
                            - math.pi))
    last = Estimate(order[-1][1], tuple(pose[-1].tolist()), cov[-1, :3, :3].copy(),
                    x[-1].copy(), cov[-1].copy(), NAMES)
    final.extend_columns(np.array([t for _, t in order]), pose, cov[:, :3, :3], last)
    return final


class BatchSmoother(FixedLagSmoother):
    """Every factor of the run, solved at the end with Levenberg-Marquardt: the offline optimum
    the fixed-lag outputs are compared with. Its trajectory is at the keyframes. The factors are
    the ones the online run builds, so a time-correlated GPS fix is inflated by the f the
    smoother gave it (for the time since the previous fused fix; a late one's nearest): batch
    and smoother model the data alike."""

    name = "batch"
    keep_all = True

    def __init__(self, cfg: Config, **kw) -> None:
        kw.setdefault("lagged", False)  # its output is the final solve's, not a lagged one
        super().__init__(cfg, **kw)
        self._final = TrackBuilder()
        self._finished = False

    def estimate(self) -> Estimate | None:
        """None until ``finish``: the batch's output is the final solve's trajectory
        (``final_estimates``), and the online run's filtered estimates, which it builds its
        graph with, are nobody's output (the runner asks at every output tick). After
        ``finish``, the online run's last filtered estimate, as the smoother's."""
        return super().estimate() if self._finished else None

    def online_estimate(self) -> Estimate | None:
        """The online run's filtered estimate now (the smoother's ``estimate``): what the
        batch's gating sees, for diagnostics."""
        return super().estimate()

    @property
    def all_kf_t(self) -> dict[int, float]:
        """Every keyframe of the run: index -> stamp (s). Read-only view of the window's."""
        return self.window.all_kf_t

    @property
    def all_graph(self) -> gtsam.NonlinearFactorGraph:
        """Every factor of the run, the graph ``finish`` solves."""
        return self.window.all_graph

    def finish(self) -> None:
        super().finish()
        self._finished = True
        if self.initialised:
            self._final = whole_run(self, self.log)

    def lagged_estimates(self):  # the batch has no lagged output of its own
        return None

    def final_estimates(self) -> TrackBuilder:
        return self._final

    def final_state(self) -> Estimate | None:
        return self._estimated_only(self._final.last)



class SharedBatch(Estimator):
    """The batch over the online run of a smoother that runs beside it: ``source``, a
    ``FixedLagSmoother`` built with ``keep_all``, builds the graph a ``BatchSmoother`` would
    (the same factors: one online run with one config makes the same gating decisions), and
    ``finish`` solves it, instead of a second online run of the same smoother. Its log shares
    the source's innovations and rejections (the same as a batch's own would be), its notes are
    the source's and its own. ``runner.run`` stops it where it stops the source (an error, a
    broken output, an interrupt inside an update: ``source``)."""

    name = "batch"

    def __init__(self, source: FixedLagSmoother) -> None:
        if not source.keep_all:
            raise ValueError("SharedBatch: the smoother must keep every factor (keep_all=True)")
        super().__init__()
        self.source, self.cfg = source, source.cfg
        self.pose_error = source.pose_error
        self.log = EstimatorLog(innovations=source.log.innovations,
                                rejected=source.log.rejected)
        self._final = TrackBuilder()
        self._finished = False

    def late_horizon(self, m) -> float:
        return self.source.late_horizon(m)

    def process(self, m) -> None:
        """Nothing of its own: the source processes ``m``."""

    def estimate(self) -> Estimate | None:
        """None until ``finish`` (as ``BatchSmoother.estimate``), then the source's."""
        return self.source.estimate() if self._finished else None

    def finish(self) -> None:
        source = self.source
        source.finish()  # once: the runner's own call of it returns at once
        own = self.log.messages
        # first, so that metrics.json's first events always say it
        self.log.messages = []
        self.log.note(source.twist.last_t, "shares the smoother's online run (the factors it "
                      "built): this batch's runtime is its whole-run solve alone")
        self.log.messages += source.log.messages + own
        self._finished = True
        if source.initialised:
            self._final = whole_run(source, self.log)

    def lagged_estimates(self):
        return None

    def final_estimates(self) -> TrackBuilder:
        return self._final

    def final_state(self) -> Estimate | None:
        return self.source._estimated_only(self._final.last)
