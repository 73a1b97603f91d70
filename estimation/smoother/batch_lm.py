"""Levenberg-Marquardt over a whole-run factor graph, iterated from Python.

gtsam's ``LevenbergMarquardtOptimizer`` holds its ``Values`` in C++, so every Python
``CustomFactor`` callback it makes receives a pybind11 copy of the whole ``Values`` (every
keyframe of the run): the cost grows with the square of the run's length. Called from Python
on a ``Values`` that Python owns, ``graph.linearize`` and ``graph.error`` pass it by reference.
``levenberg_marquardt`` therefore runs gtsam's own iteration (``tryLambda`` and
``NonlinearOptimizer::defaultOptimize`` of gtsam 4.3: isotropic damping ``lambda * I`` per
variable, the params' lambda schedule, the model-fidelity test and the stopping rules) with each
linearisation, error and solve a single gtsam call made from Python. The result is gtsam's up to
rounding (docs/results/batch_speed.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import gtsam
import numpy as np

MIN_MODEL_FIDELITY = 1e-3  # gtsam's LevenbergMarquardtParams default (no Python accessor)


@dataclass
class LmResult:
    """The optimised values, the number of successful steps (gtsam's ``iterations()``), the
    final error (half the sum of squared whitened residuals), the final lambda and the number of
    tried steps that were rejected (lambda raised)."""

    values: gtsam.Values
    iterations: int
    error: float
    lam: float
    rejected: int = 0


def _check(params: gtsam.LevenbergMarquardtParams) -> None:
    if params.getDiagonalDamping() or not params.getUseFixedLambdaFactor():
        raise ValueError("levenberg_marquardt: only isotropic damping with a fixed lambda "
                         "factor (gtsam's defaults) is implemented")
    if (params.getLinearSolverType(), params.getOrderingType()) != ("MULTIFRONTAL_CHOLESKY",
                                                                    "COLAMD"):
        raise ValueError("levenberg_marquardt: only multifrontal Cholesky is implemented")


def _damping(dims: list[tuple[int, int]], lam: float) -> gtsam.GaussianFactorGraph:
    """One ``JacobianFactor`` per variable: ``I dx = 0`` with sigma 1/sqrt(lam)."""
    damp = gtsam.GaussianFactorGraph()
    sigma = 1.0 / math.sqrt(lam)
    models: dict[int, tuple[np.ndarray, np.ndarray, object]] = {}
    for key, d in dims:
        m = models.get(d)
        if m is None:
            m = models[d] = (np.eye(d), np.zeros(d), gtsam.noiseModel.Isotropic.Sigma(d, sigma))
        damp.push_back(gtsam.JacobianFactor(key, m[0], m[1], m[2]))
    return damp


class _GtsamStep:
    """One linearisation solved by gtsam: the damped graph eliminated by multifrontal Cholesky
    in COLAMD order."""

    def __init__(self, linear: gtsam.GaussianFactorGraph, ordering: gtsam.Ordering,
                 dims: list[tuple[int, int]], zero: gtsam.VectorValues) -> None:
        self.linear, self.ordering, self.dims = linear, ordering, dims
        self.old_error = linear.error(zero)

    def solve(self, lam: float) -> gtsam.VectorValues | None:
        damped = gtsam.GaussianFactorGraph()
        damped.push_back(self.linear)
        damped.push_back(_damping(self.dims, lam))
        try:
            return damped.optimize(self.ordering)
        except RuntimeError:  # gtsam's IndeterminateSystemException
            return None

    def change(self, delta: gtsam.VectorValues) -> float:
        return self.old_error - self.linear.error(delta)


class _GtsamSystem:
    """A graph (``linearize`` to a ``GaussianFactorGraph``, ``error``) solved by gtsam."""

    def __init__(self, graph, ordering: gtsam.Ordering, initial: gtsam.Values) -> None:
        self.graph, self.ordering = graph, ordering
        self.zero = initial.zeroVectors()
        self.dims = [(int(k), self.zero.at(k).shape[0]) for k in initial.keys()]  # noqa: SIM118

    def error(self, values: gtsam.Values) -> float:
        return self.graph.error(values)

    def linearize(self, values: gtsam.Values) -> _GtsamStep:
        return _GtsamStep(self.graph.linearize(values), self.ordering, self.dims, self.zero)

    def retract(self, values: gtsam.Values, delta: gtsam.VectorValues) -> gtsam.Values:
        return values.retract(delta)


def levenberg_marquardt(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values,
                        params: gtsam.LevenbergMarquardtParams, system=None) -> LmResult:
    """Minimise ``graph``'s error from ``initial`` as gtsam's ``LevenbergMarquardtOptimizer``
    with ``params`` does (isotropic damping, fixed lambda factor, multifrontal Cholesky in COLAMD
    order; ValueError for other params). A system that cannot be solved at any lambda is not an
    error: as gtsam, it stops at ``lambdaUpperBound`` with the values it has. ``system``: what
    evaluates and solves ``graph``: either a graph-like object (``linearize(values)`` to a
    ``GaussianFactorGraph`` and ``error(values)``, e.g. ``batch_factors.VectorisedGraph``; by
    default ``graph`` itself), solved by gtsam, or a system with ``error``, ``retract(values,
    delta)`` and ``linearize(values)`` returning a step with ``old_error``, ``solve(lam)``
    (None where the damped system has no solution) and ``change(delta)`` (the linear model's
    decrease), e.g. ``batch_banded.BandedSystem``."""
    _check(params)
    if system is None or not hasattr(system, "retract"):
        # gtsam's ensureHasOrdering
        system = _GtsamSystem(graph if system is None else system,
                              gtsam.Ordering.ColamdNonlinearFactorGraph(graph), initial)
    lam, factor = params.getlambdaInitial(), params.getlambdaFactor()
    upper, lower = params.getlambdaUpperBound(), params.getlambdaLowerBound()
    rel_tol, abs_tol = params.getRelativeErrorTol(), params.getAbsoluteErrorTol()
    max_iter = params.getMaxIterations()
    values, error, iterations, rejected = initial, system.error(initial), 0, 0
    if error <= params.getErrorTol() or iterations >= max_iter:
        return LmResult(values, iterations, error, lam)
    while True:
        current = error
        linear = system.linearize(values)
        old_linear = linear.old_error
        while True:  # tryLambda until it returns true
            delta = linear.solve(lam)
            success = stop = False
            if delta is not None:
                change_linear = linear.change(delta)
                if change_linear >= 0.0:
                    new_values = system.retract(values, delta)
                    new_error = system.error(new_values)
                    change = error - new_error
                    if change_linear > np.finfo(float).eps * old_linear:
                        success = change / change_linear > MIN_MODEL_FIDELITY
                    if abs(change) < rel_tol * error:
                        stop = True
            if success:
                values, error, iterations = new_values, new_error, iterations + 1
                lam = max(lower, lam / factor)
                break
            if stop:
                break
            lam *= factor
            rejected += 1
            if lam >= upper:
                break
        decrease = current - error
        converged = current == 0.0 or (rel_tol and decrease / current <= rel_tol) \
            or decrease <= abs_tol
        if iterations >= max_iter or converged or not math.isfinite(current):
            return LmResult(values, iterations, error, lam, rejected)
