"""The batch's numpy evaluation of its preintegrated and bias-difference factors
(estimation.smoother.batch_factors) is the factors' own: the same error and linear system as
gtsam gets from the CustomFactors, for every arrangement the batch meets (a bias row joined to
its interval or alone, a factor recorded but not in the graph, a robust model kept as a
CustomFactor), and on the sample bag's whole-run graph."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from ddfuse.estimation.smoother import BatchSmoother
from ddfuse.estimation.smoother.batch_factors import VectorisedGraph
from ddfuse.factors.gyro import bias_difference_factor
from ddfuse.factors.preintegration import WheelGyroPreintegration, preintegrated_factor
from ddfuse.factors.state import DIM


def _pim(rng, bg_lin=0.01, kv_lin=1.02, kw_lin=0.97) -> WheelGyroPreintegration:
    p = WheelGyroPreintegration(bg_lin, kv_lin=kv_lin, kw_lin=kw_lin)
    for _ in range(12):
        p.integrate(0.02, 1.0 + rng.normal(0, 0.1), 0.3 + rng.normal(0, 0.05), 1e-3, 1e-4,
                    gain=0.6, w_odo=0.25 + rng.normal(0, 0.05))
    return p


def _state(rng, k: int) -> np.ndarray:
    # psi far from 0 and past pi on some keys: the wrap and the rotation both matter
    return np.array([3.0 * k + rng.normal(), rng.normal(), 2.9 * k + rng.normal(0, 0.3),
                     1.0 + rng.normal(0, 0.1), 0.3 + rng.normal(0, 0.1), rng.normal(0, 0.02),
                     rng.normal(0, 0.3), 1.0 + rng.normal(0, 0.05), 1.0 + rng.normal(0, 0.05)])


def _system(n_keys=6, robust_at=None, lone_bias=True, dropped=True):
    """A chain of preintegrated factors with a bias row at each interval's end key, a bias row
    on the first key (no interval ends there), a recorded factor never added to the graph, a
    prior per key, and (``robust_at``) one interval with a robust model."""
    rng = np.random.default_rng(3)
    graph, values, record = gtsam.NonlinearFactorGraph(), gtsam.Values(), []
    for k in range(n_keys):
        values.insert(k, _state(rng, k))
        graph.add(gtsam.PriorFactorVector(k, _state(rng, k), gtsam.noiseModel.Isotropic.Sigma(
            DIM, 2.0)))
    for k in range(1, n_keys):
        noise = None
        if k == robust_at:
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(
                1.345), gtsam.noiseModel.Isotropic.Sigma(DIM, 0.1))
        graph.add(preintegrated_factor(k - 1, k, _pim(rng), gyro_bias_rw=2e-3,
                                       heading_offset_rw=1e-3, noise=noise, record=record))
        graph.add(bias_difference_factor(k, 0.31, 0.28, 0.01, 0.02, record=record))
    if lone_bias:
        graph.add(bias_difference_factor(0, 0.2, 0.22, 0.02, 0.01, record=record))
    if dropped:  # recorded, never added (a restart dropped it before it reached the batch)
        preintegrated_factor(0, 1, _pim(rng), record=record)
        bias_difference_factor(2, 0.1, 0.1, 0.01, 0.01, record=record)
    return graph, values, record


def _same_system(graph, system, values):
    assert system.error(values) == pytest.approx(graph.error(values), rel=1e-12)
    ref, got = graph.linearize(values).hessian(), system.linearize(values).hessian()
    scale = np.abs(ref[0]).max()
    assert np.abs(got[0] - ref[0]).max() <= 1e-12 * scale
    assert np.abs(got[1] - ref[1]).max() <= 1e-12 * max(np.abs(ref[1]).max(), 1.0)


@pytest.mark.parametrize("lone_bias", [True, False])
def test_same_error_and_linear_system_as_the_custom_factors(lone_bias):
    graph, values, record = _system(lone_bias=lone_bias)
    system = VectorisedGraph(graph, record)
    n_pre, n_bias = 5, 5 + lone_bias
    assert system.n_vectorised == n_pre + n_bias  # the dropped ones are not in the graph
    assert system.rest.size() == graph.size() - system.n_vectorised
    _same_system(graph, system, values)
    # away from the start too (a retracted point, as LM evaluates)
    delta = gtsam.VectorValues()
    rng = np.random.default_rng(5)
    for k in range(6):
        delta.insert(k, rng.normal(0, 0.3, DIM))
    _same_system(graph, system, values.retract(delta))


def test_a_robust_interval_stays_a_custom_factor():
    graph, values, record = _system(robust_at=3)
    system = VectorisedGraph(graph, record)
    assert system.n_vectorised == 4 + 6 and system.rest.size() == graph.size() - 10
    _same_system(graph, system, values)


def test_the_sample_bags_whole_run_graph(sample_husky):
    cfg, stream = sample_husky
    g = stream.ground_truth[0]
    batch = BatchSmoother(cfg, initial_pose=(g.x, g.y, g.yaw))
    batch.finish = lambda: None  # the graph only
    for m in stream.measurements:
        batch.process(m)
    w = batch.window
    system = VectorisedGraph(w.all_graph, batch.factor_record)
    # a preintegrated factor and a bias row per interval (the GPS factors, with a lever arm,
    # stay CustomFactors)
    assert system.n_vectorised == 2 * (len(w.all_kf_t) - 1)
    _same_system(w.all_graph, system, w.all_values)
    assert math.isfinite(system.error(w.all_values))
