"""The batch smoother: every factor of the run, solved at the end with Levenberg-Marquardt, the
offline optimum the fixed-lag outputs are compared with. Its trajectory is at the keyframes
(poses in local ENU, marginal covariances from ``gtsam.Marginals``)."""

from __future__ import annotations

import gtsam
from ddfuse.estimation.config import Config
from ddfuse.estimation.errors import error_line
from ddfuse.estimation.estimator import Estimate, wrap_angle
from ddfuse.estimation.runner import TrackBuilder
from ddfuse.estimation.smoother.batch_banded import BandedSystem
from ddfuse.estimation.smoother.batch_factors import VectorisedGraph
from ddfuse.estimation.smoother.batch_lm import levenberg_marquardt
from ddfuse.estimation.smoother.fixed_lag import FixedLagSmoother
from ddfuse.factors.state import NAMES
from threadpoolctl import threadpool_limits


def _solve(window, system: VectorisedGraph, params: gtsam.LevenbergMarquardtParams):
    """The whole run's LM solution and a function from a key to its marginal covariance (9, 9);
    RuntimeError where the system cannot be solved."""
    banded = BandedSystem.build(system, window.all_values)
    if banded is None:
        result = levenberg_marquardt(window.all_graph, window.all_values, params, system).values
        return result, gtsam.Marginals(system.linearize(result), result).marginalCovariance
    result = levenberg_marquardt(window.all_graph, window.all_values, params, banded).values
    covs = dict(zip(banded.keys, banded.marginals(result), strict=True))
    return result, covs.__getitem__


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
        if not self.initialised:
            return
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(20)
        params.setRelativeErrorTol(1e-6)
        window = self.window
        try:
            # gtsam's LM iterated from Python (its own optimizer would hand every CustomFactor
            # callback a copy of the whole run's Values), with the preintegrated and
            # bias-difference factors evaluated together with numpy (batch_lm, batch_factors),
            # the normal equations solved as one banded matrix where they are one
            # (batch_banded); BLAS's threads only cost more on these small blocks
            with threadpool_limits(1, user_api="blas"):
                result, covs = _solve(window, VectorisedGraph(window.all_graph,
                                                              self.factor_record), params)
        except RuntimeError as e:
            self.log.note(self.twist.last_t, f"batch optimisation failed: {error_line(str(e))}"
                          ": the whole run's system is ill-conditioned; check the config's noise "
                          "values, priors and delays")
            return
        for j, t in sorted(window.all_kf_t.items(), key=lambda jt: jt[1]):
            key = int(window.key(j))
            x = result.atVector(key)
            cov = window.with_gauge(j, covs(key))
            self._final.append(Estimate(t, (float(x[0]), float(x[1]), wrap_angle(float(x[2]))),
                                        cov[:3, :3].copy(), x.copy(), cov.copy(), NAMES))

    def lagged_estimates(self):  # the batch has no lagged output of its own
        return None

    def final_estimates(self) -> TrackBuilder:
        return self._final

    def final_state(self) -> Estimate | None:
        return self._estimated_only(self._final.last)

