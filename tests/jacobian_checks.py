"""Jacobian checks for any gtsam factor, done through gtsam's own ``Values.retract``.

Used by the tests; also handy when writing a new factor. Not in any hot path.
"""

from __future__ import annotations

import gtsam
import numpy as np


def _keys(obj) -> list[int]:
    # gtsam containers, not dicts: .keys() is their only key accessor
    return list(obj.keys())


def _dims(values: gtsam.Values) -> dict[int, int]:
    vv = values.zeroVectors()
    return {k: int(vv.at(k).shape[0]) for k in _keys(values)}


def _single(key: int, vec: np.ndarray) -> gtsam.VectorValues:
    vv = gtsam.VectorValues()
    vv.insert(key, vec)
    return vv


def analytic_jacobians(factor: gtsam.NonlinearFactor, values: gtsam.Values) -> list[np.ndarray]:
    """Unwhitened Jacobians of ``factor`` at ``values``, one (error_dim, key_dim) array per key.

    Linearizes the factor and undoes the whitening with the noise model's R (Gaussian models
    only: a robust model also reweights, so build the factor with a Gaussian model to check it).
    """
    jf = factor.linearize(values)
    a, _ = jf.jacobian()
    model = factor.noiseModel()
    if isinstance(model, gtsam.noiseModel.Robust):
        raise ValueError("check Jacobians with a Gaussian noise model, not a robust one")
    r = model.R()
    a = np.linalg.solve(r, a)
    dims = _dims(values)
    out = []
    col = 0
    for k in _keys(factor):
        n = dims[k]
        out.append(a[:, col : col + n])
        col += n
    return out


def numerical_jacobians(
    factor: gtsam.NoiseModelFactor, values: gtsam.Values, step: float = 1e-6
) -> list[np.ndarray]:
    """Central-difference Jacobians of ``unwhitenedError`` through ``Values.retract``.

    Angle residuals are wrapped by the factors, so differences are wrapped to [-pi, pi) too.
    """
    dims = _dims(values)
    zero = values.zeroVectors()
    out = []
    for k in _keys(factor):
        n = dims[k]
        cols = []
        for c in range(n):
            d = np.zeros(n)
            d[c] = step
            vp = gtsam.VectorValues(zero)
            vp.update(_single(k, d))
            vm = gtsam.VectorValues(zero)
            vm.update(_single(k, -d))
            ep = factor.unwhitenedError(values.retract(vp))
            em = factor.unwhitenedError(values.retract(vm))
            diff = ep - em
            diff = (diff + np.pi) % (2.0 * np.pi) - np.pi
            cols.append(diff / (2.0 * step))
        out.append(np.column_stack(cols))
    return out


def max_jacobian_error(
    factor: gtsam.NoiseModelFactor, values: gtsam.Values, step: float = 1e-6
) -> float:
    """Largest absolute difference between analytic and central-difference Jacobians."""
    an = analytic_jacobians(factor, values)
    nu = numerical_jacobians(factor, values, step)
    return max(float(np.max(np.abs(a - n))) for a, n in zip(an, nu, strict=True))
