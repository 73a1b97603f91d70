"""The batch's banded normal equations (estimation.smoother.batch_banded) are gtsam's: the same
information matrix and gradient as gtsam's linearisation (robust factors, bias rows, factors
that tie keyframes two apart), the same LM steps and result as gtsam's elimination, the same
marginal covariances as ``gtsam.Marginals``; where the band does not apply it says so, and a
system without a solution is refused as gtsam refuses it."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from ddfuse.estimation.estimator import wrap_angle
from ddfuse.estimation.smoother.batch_banded import MAX_KEY_SPAN, BandedSystem, IndefiniteSystem
from ddfuse.estimation.smoother.batch_factors import VectorisedGraph
from ddfuse.estimation.smoother.batch_lm import levenberg_marquardt
from ddfuse.factors.gyro import bias_difference_factor
from ddfuse.factors.preintegration import WheelGyroPreintegration, preintegrated_factor
from ddfuse.factors.state import DIM


def _params() -> gtsam.LevenbergMarquardtParams:
    p = gtsam.LevenbergMarquardtParams()
    p.setMaxIterations(20)
    p.setRelativeErrorTol(1e-6)
    return p


def _chain(n_keys: int = 8, tie: tuple[int, int] | None = None, robust: bool = True,
           seed: int = 3):
    """Preintegrated intervals with bias rows, a lone bias row, position fixes (one robust) and
    a heading prior per key, initial values off the truth; ``tie``: a between factor on two
    keys that far apart."""
    rng = np.random.default_rng(seed)
    graph, values, record = gtsam.NonlinearFactorGraph(), gtsam.Values(), []
    truth = []
    for k in range(n_keys):
        x = np.array([1.0 * k, 0.2 * k, 0.1 * k, 1.0, 0.1, 0.01, 0.05, 1.0, 1.0])
        truth.append(x)
        values.insert(k, x + rng.normal(0, [0.3, 0.3, 0.05, 0.1, 0.02, 0.005, 0.02, 0.02,
                                            0.02]))
        model = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.5, 0.5, 0.2, 0.5, 0.2, 0.05, 0.2,
                                                           0.1, 0.1]))
        if robust and k == 3:
            model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(
                1.345), model)
        graph.add(gtsam.PriorFactorVector(k, x + rng.normal(0, 0.3, DIM), model))
    graph.add(gtsam.PriorFactorVector(0, truth[0], gtsam.noiseModel.Isotropic.Sigma(DIM, 0.1)))
    for k in range(1, n_keys):
        p = WheelGyroPreintegration(0.01)
        for _ in range(10):
            p.integrate(0.1, 1.0 + rng.normal(0, 0.05), 0.1 + rng.normal(0, 0.01), 1e-3, 1e-4,
                        gain=0.6, w_odo=0.1 + rng.normal(0, 0.01))
        graph.add(preintegrated_factor(k - 1, k, p, gyro_bias_rw=2e-3, heading_offset_rw=1e-3,
                                       record=record))
        graph.add(bias_difference_factor(k, 0.11, 0.1, 0.01, 0.02, record=record))
    graph.add(bias_difference_factor(0, 0.11, 0.1, 0.02, 0.01, record=record))
    if tie is not None:
        graph.add(gtsam.BetweenFactorVector(tie[0], tie[1], truth[tie[1]] - truth[tie[0]],
                                            gtsam.noiseModel.Isotropic.Sigma(DIM, 0.5)))
    return graph, values, VectorisedGraph(graph, record)


class _DenseStep:
    def __init__(self, h, g, old_error):
        self.h, self.g, self.old_error = h, g, old_error

    def solve(self, lam):
        try:
            c = np.linalg.cholesky(self.h + lam * np.eye(len(self.h)))
        except np.linalg.LinAlgError:
            return None
        return np.linalg.solve(c.T, np.linalg.solve(c, self.g))

    def change(self, delta):
        return float(self.g @ delta) - 0.5 * float(delta @ self.h @ delta)


class _DenseSystem:
    """The LM system contract with dense numpy normal equations: the reference for the band."""

    def __init__(self, graph, keys):
        self.graph, self.keys = graph, keys

    def error(self, values):
        return self.graph.error(values)

    def linearize(self, values):
        linear = self.graph.linearize(values)
        h, eta = linear.hessian()
        return _DenseStep(h, eta, linear.error(values.zeroVectors()))

    def retract(self, values, delta):
        vv = gtsam.VectorValues()
        for i, k in enumerate(self.keys):
            vv.insert(k, delta[i * DIM:(i + 1) * DIM])
        return values.retract(vv)


def _dense(band: np.ndarray, u: int) -> np.ndarray:
    n = band.shape[1]
    h = np.zeros((n, n))
    for d in range(u + 1):
        i = np.arange(n - d)
        h[i, i + d] = h[i + d, i] = band[u - d, d:]
    return h


@pytest.mark.parametrize("tie", [None, (2, 4)])
def test_same_normal_equations_as_gtsams_linearisation(tie):
    graph, values, system = _chain(tie=tie)
    banded = BandedSystem.build(system, values)
    assert banded is not None and banded.u == DIM * (2 if tie else 1) + DIM - 1
    for at in (values, banded.retract(values, np.random.default_rng(1).normal(0, 0.2,
                                                                          banded.n))):
        step = banded.linearize(at)
        h_ref, eta_ref = graph.linearize(at).hessian()  # keys in key order, as the band's
        h = _dense(step.band, banded.u)
        assert np.abs(h - h_ref).max() <= 1e-12 * np.abs(h_ref).max()
        assert np.abs(step.g - eta_ref).max() <= 1e-12 * np.abs(eta_ref).max()
        assert step.old_error == pytest.approx(graph.linearize(at).error(
            at.zeroVectors()), rel=1e-12)
        assert banded.error(at) == pytest.approx(graph.error(at), rel=1e-12)
        delta = np.random.default_rng(2).normal(0, 0.1, banded.n)
        linear = graph.linearize(at)
        vv = gtsam.VectorValues()
        for i, k in enumerate(banded.keys):
            vv.insert(k, delta[i * DIM:(i + 1) * DIM])
        assert step.change(delta) == pytest.approx(step.old_error - linear.error(vv), rel=1e-9)


def test_same_steps_result_and_marginals_as_gtsam():
    graph, values, system = _chain()
    ref = levenberg_marquardt(graph, values, _params(), system)
    banded = BandedSystem.build(system, values)
    got = levenberg_marquardt(graph, values, _params(), banded)
    assert got.iterations == ref.iterations >= 2 and got.lam == ref.lam
    assert got.error == pytest.approx(ref.error, rel=1e-10)
    for k in banded.keys:
        assert np.abs(got.values.atVector(k) - ref.values.atVector(k)).max() < 1e-10
    marg = gtsam.Marginals(graph, ref.values)
    covs = banded.marginals(got.values)
    for k, cov in zip(banded.keys, covs, strict=True):
        want = marg.marginalCovariance(k)
        assert np.abs(cov - want).max() <= 1e-8 * np.abs(want).max()
        assert np.array_equal(cov, cov.T)


def test_keys_two_apart_where_gtsams_elimination_gives_up():
    """A factor on keyframes 2 and 4 (two keys per block in the marginals' recursion). With the
    intervals' tight walks (information up to 2e10) gtsam's elimination calls the system
    indeterminate at the small lambdas and its LM stops at the iteration limit, higher; the
    band solves it: each damped step is the dense solve's, the result a minimum, the marginals
    the dense inverse's blocks."""
    graph, values, system = _chain(tie=(2, 4))
    banded = BandedSystem.build(system, values)
    step = banded.linearize(values)
    h, eta = graph.linearize(values).hessian()
    for lam in (1e-5, 1.0):
        want = np.linalg.solve(h + lam * np.eye(len(h)), eta)
        assert np.abs(step.solve(lam) - want).max() <= 1e-7 * np.abs(want).max()
    with pytest.raises(RuntimeError, match="Indeterminate"):
        graph.linearize(values).optimize()
    gave_up = levenberg_marquardt(graph, values, _params(), system)
    ref = levenberg_marquardt(graph, values, _params(), _DenseSystem(graph, banded.keys))
    got = levenberg_marquardt(graph, values, _params(), banded)
    assert gave_up.iterations == 20 and gave_up.error > got.error
    assert got.iterations == ref.iterations < 10
    assert got.error == pytest.approx(ref.error, rel=1e-10)
    for k in banded.keys:
        assert np.abs(got.values.atVector(k) - ref.values.atVector(k)).max() < 1e-9
    h, eta = graph.linearize(got.values).hessian()
    assert np.abs(eta).max() <= 1e-6 * np.abs(h).max() ** 0.5  # the gradient is ~0: a minimum
    dense = np.linalg.inv(h)
    for i, cov in enumerate(banded.marginals(got.values)):
        want = dense[i * DIM:(i + 1) * DIM, i * DIM:(i + 1) * DIM]
        assert np.abs(cov - want).max() <= 1e-6 * np.abs(want).max()


def test_where_the_band_does_not_apply():
    _, values, system = _chain(n_keys=10, tie=(1, 2 + MAX_KEY_SPAN))
    assert BandedSystem.build(system, values) is None  # a factor ties keys too far apart
    graph, values, system = _chain()
    values.insert(100, np.zeros(3))  # a key that is not a 9-vector
    assert BandedSystem.build(system, values) is None


def test_a_system_without_a_solution_is_refused_as_gtsam_refuses_it():
    graph, values, system = _chain()
    values.insert(8, values.atVector(7))  # a keyframe no factor determines
    banded = BandedSystem.build(system, values)
    step = banded.linearize(values)
    assert step.solve(0.0) is None  # gtsam: IndeterminateLinearSystemException
    assert step.solve(1e-3) is not None  # damping determines it
    with pytest.raises(IndefiniteSystem):
        banded.marginals(values)
    step.band[banded.u, 3] = np.nan  # a NaN pivot: LAPACK would pass it through
    assert step.solve(1e-3) is None
    with pytest.raises(IndefiniteSystem, match="not finite"):
        step.cholesky(1e-3)
    assert isinstance(IndefiniteSystem(), RuntimeError)  # the batch's note for a failed solve


def test_the_sample_bags_batch_is_gtsams_solution(sample_batch):
    batch = sample_batch
    w = batch.window
    system = VectorisedGraph(w.all_graph, batch.factor_record)
    ref = levenberg_marquardt(w.all_graph, w.all_values, _params(), system)
    assert BandedSystem.build(system, w.all_values) is not None  # the batch took the band
    marg = gtsam.Marginals(system.linearize(ref.values), ref.values)
    final = {e.t: e for e in batch.final_estimates()}
    assert len(final) == len(w.all_kf_t)
    for j, t in w.all_kf_t.items():
        key = w.key(j)
        want = w.with_gauge(j, marg.marginalCovariance(key))[:3, :3]
        x = ref.values.atVector(key)
        assert np.abs(np.array(final[t].pose) - (x[0], x[1], wrap_angle(x[2]))).max() < 1e-8
        assert np.abs(final[t].pose_cov - want).max() <= 1e-7 * np.abs(want).max()


def test_a_jacobian_zero_at_the_start_widens_the_band_when_it_grows():
    """gtsam leaves exact zeros out of the sparse Jacobian: a factor on keyframes 0 and 2 whose
    derivative for keyframe 2 is 0 at the initial values looks like a one-key factor there;
    when it grows the band widens, and the result is the dense normal equations' (gtsam's
    elimination gives up on this one, as on the tie above)."""
    graph, values, system = _chain()
    c = float(values.atVector(2)[3])

    def error(this, v, H):
        x0, x2 = v.atVector(0), v.atVector(2)
        if H is not None:
            H[0] = np.zeros((1, DIM))
            H[0][0, 0] = 1.0
            H[1] = np.zeros((1, DIM))
            H[1][0, 3] = -2.0 * (x2[3] - c)
        return np.array([x0[0] - (x2[3] - c) ** 2])

    f = gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, 0.1), [0, 2], error)
    graph.add(f)
    system.rest.add(f)
    banded = BandedSystem.build(system, values)
    ref = levenberg_marquardt(graph, values, _params(), _DenseSystem(graph, banded.keys))
    assert banded.u == 2 * DIM - 1  # the intervals' span alone at the start
    got = levenberg_marquardt(graph, values, _params(), banded)
    assert banded.u == 3 * DIM - 1
    assert got.iterations == ref.iterations and got.error == pytest.approx(ref.error, rel=1e-10)
    for k in banded.keys:
        assert np.abs(got.values.atVector(k) - ref.values.atVector(k)).max() < 1e-9
