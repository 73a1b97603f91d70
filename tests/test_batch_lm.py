"""The batch's Levenberg-Marquardt iterated from Python (estimation.smoother.batch_lm) is
gtsam's LevenbergMarquardtOptimizer: the same steps, lambdas and result, on a graph that needs
the lambda schedule (rejected steps) and on the sample bag's whole-run graph."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from ddfuse.estimation.smoother.batch_lm import levenberg_marquardt


def _params(max_iter: int = 20, rel: float = 1e-6) -> gtsam.LevenbergMarquardtParams:
    p = gtsam.LevenbergMarquardtParams()
    p.setMaxIterations(max_iter)
    p.setRelativeErrorTol(rel)
    return p


def _gtsam_lm(graph, values, params):
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = opt.optimize()
    return result, opt.iterations(), opt.error(), opt.lambda_()


def _max_diff(a: gtsam.Values, b: gtsam.Values) -> float:
    return max(float(np.max(np.abs(a.atVector(k) - b.atVector(k)))) for k in a.keys())  # noqa: SIM118


def _range_factor(ka: int, kb: int, r: float, sigma: float, robust: bool) -> gtsam.CustomFactor:
    """Distance between two 2-D points (Vector keys): strongly nonlinear from a poor start."""

    def error(this, values, H):
        d = values.atVector(kb) - values.atVector(ka)
        n = math.hypot(d[0], d[1])
        if H is not None:
            u = (d / n).reshape(1, 2)
            H[0], H[1] = -u, u
        return np.array([n - r])

    model = gtsam.noiseModel.Isotropic.Sigma(1, sigma)
    if robust:
        model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.0),
                                               model)
    return gtsam.CustomFactor(model, [ka, kb], error)


def _saturating_factor(k: int, c: float) -> gtsam.CustomFactor:
    """Residual tanh(x - c) of a 1-vector key: from |x - c| = 2.5 the Gauss-Newton step
    overshoots far beyond c, which LM must reject (raise lambda) before it converges."""

    def error(this, values, H):
        x = float(values.atVector(k)[0])
        if H is not None:
            H[0] = np.array([[1.0 / math.cosh(x - c) ** 2]])
        return np.array([math.tanh(x - c)])

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, 0.1), [k], error)


def _trilateration(robust: bool):
    """Three anchors held by priors, two unknown points seen by ranges (one outlying), started
    far off."""
    rng = np.random.default_rng(7)
    anchors = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    points = np.array([[4.0, 3.0], [7.0, 6.0]])
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for i, a in enumerate(anchors):
        graph.add(gtsam.PriorFactorVector(i, a, gtsam.noiseModel.Isotropic.Sigma(2, 0.01)))
        values.insert(i, a + rng.normal(0, 0.01, 2))
    for j, p in enumerate(points):
        values.insert(10 + j, np.array([-30.0, 25.0]) * (j + 1))
        for i, a in enumerate(anchors):
            r = float(np.linalg.norm(p - a)) + (3.0 if (i, j) == (1, 1) else rng.normal(0, 0.05))
            graph.add(_range_factor(i, 10 + j, r, 0.05, robust))
    graph.add(_range_factor(10, 11, float(np.linalg.norm(points[1] - points[0])), 0.05, robust))
    return graph, values


def _saturating():
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(_saturating_factor(20, 1.0))
    values.insert(20, np.array([3.5]))
    return graph, values


@pytest.mark.parametrize("problem", ["ranges", "robust ranges", "saturating"])
def test_same_steps_and_result_as_gtsams_optimizer(problem):
    graph, values = _saturating() if problem == "saturating" else _trilateration(
        problem == "robust ranges")
    for params in (_params(), _params(max_iter=3), _params(rel=1e-12)):
        ref, iters, err, lam = _gtsam_lm(graph, values, params)
        got = levenberg_marquardt(graph, values, params)
        assert got.iterations == iters and got.lam == pytest.approx(lam, rel=1e-12)
        assert got.error == pytest.approx(err, rel=1e-9, abs=1e-12)
        assert _max_diff(ref, got.values) < 1e-9
        # gtsam's final lambda, equal to ours, is lambdaInitial * 10 ** (rejected - iterations)
        assert got.lam == pytest.approx(1e-5 * 10.0 ** (got.rejected - got.iterations), rel=1e-9)
        if problem == "saturating":  # its Gauss-Newton steps overshoot: the schedule mattered
            assert got.rejected > 0 and abs(got.values.atVector(20)[0] - 1.0) < 1e-3


def test_the_sample_bags_batch_graph(sample_batch):
    batch = sample_batch
    w = batch.window
    ref, iters, err, _ = _gtsam_lm(w.all_graph, w.all_values, _params())
    got = levenberg_marquardt(w.all_graph, w.all_values, _params())
    assert iters >= 2 and got.iterations == iters
    assert got.error == pytest.approx(err, rel=1e-9)
    assert _max_diff(ref, got.values) < 1e-9
    # and the batch's output is that solution
    final = batch.final_estimates()
    last = max(w.all_kf_t, key=w.all_kf_t.get)
    assert np.max(np.abs(final.last.state - ref.atVector(w.key(last)))) < 1e-9
    # ../shared/bench/batch_compare.py reads the run's keyframes and graph off the estimator
    assert batch.all_kf_t is w.all_kf_t and batch.all_graph is w.all_graph
    assert len(batch.all_kf_t) == len(final) and batch.all_graph.size() > len(final)


@pytest.mark.parametrize("change", ["setDiagonalDamping", "setUseFixedLambdaFactor",
                                    "setLinearSolverType", "setOrderingType"])
def test_other_params_are_refused(change):
    graph, values = _trilateration(False)
    p = _params()
    arg = {"setDiagonalDamping": True, "setUseFixedLambdaFactor": False,
           "setLinearSolverType": "MULTIFRONTAL_QR", "setOrderingType": "METIS"}[change]
    getattr(p, change)(arg)
    with pytest.raises(ValueError, match="levenberg_marquardt"):
        levenberg_marquardt(graph, values, p)
