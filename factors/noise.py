"""Noise-model helpers shared by the factor constructors."""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

NoiseLike = gtsam.noiseModel.Base | float | Sequence[float]


def as_noise_model(noise: NoiseLike, dim: int) -> gtsam.noiseModel.Base:
    """Return ``noise`` unchanged if it is a gtsam noise model, else build one.

    A float is an isotropic sigma; a sequence of ``dim`` floats are per-row sigmas (units of the
    factor's error rows). Pass a ``gtsam.noiseModel.Robust`` (Huber, Cauchy...) for outlier-prone
    sensors; it is used as is.
    """
    if isinstance(noise, gtsam.noiseModel.Base):
        if noise.dim() != dim:
            raise ValueError(f"noise model has dimension {noise.dim()}, factor needs {dim}")
        return noise
    if isinstance(noise, (int, float)):
        return gtsam.noiseModel.Isotropic.Sigma(dim, float(noise))
    sig = np.asarray(noise, dtype=np.float64).reshape(-1)
    if sig.shape != (dim,):
        raise ValueError(f"expected {dim} sigmas, got shape {sig.shape}")
    return gtsam.noiseModel.Diagonal.Sigmas(sig)
