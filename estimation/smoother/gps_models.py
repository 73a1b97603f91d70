"""The smoother's GPS error models of the config's ``gps.model`` (``GpsModelConfig``): the scale
learned from the fixes' innovations, the robust noise models and the max-mixture factor, and
which fixes a model treats as outliers. When to use which: docs/design/urban_gps.md.

Units: covariances m^2 in local ENU; NIS and kernel constants on the whitened residual.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from ddfuse.estimation.config import GpsModelConfig
from ddfuse.estimation.gps_scale import (  # noqa: F401 - re-exported
    CHI2_2_QUANTILE,
    KERNEL_K,
    MIN_SAMPLES,
    QUANTILE,
    GpsScale,
    kernel_weight,
)
from ddfuse.factors.gps import gps_factor
from ddfuse.factors.gps_mixture import MixtureModel, gps_maxmix_factor


def robust_model(model: str, k: float, base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
    """``base`` under the M-estimator ``model`` ('cauchy', 'geman_mcclure', 'dcs')."""
    m = gtsam.noiseModel.mEstimator
    est = {"cauchy": m.Cauchy, "geman_mcclure": m.GemanMcClure, "dcs": m.DCS}[model]
    return gtsam.noiseModel.Robust.Create(est.Create(k), base)


class RobustGps:
    """One smoother's robust GPS model (``gps.model``): the learned scale and each fix's
    factor."""

    def __init__(self, gm: GpsModelConfig) -> None:
        self.gm = gm
        self.scale = GpsScale(gm.scale_window)
        self.k = gm.k if gm.k is not None else KERNEL_K.get(gm.model, 0.0)

    def factor(self, key: int, e: float, n: float, cov: np.ndarray, r: np.ndarray, f: float,
               lever: tuple[float, float], dt: float, y: np.ndarray, s_inn: np.ndarray,
               gate_nis: float) -> tuple[gtsam.NonlinearFactor, bool]:
        """The factor of a fix at (``e``, ``n``) m on ``key``, and whether the model takes it
        for an outlier at the prediction. ``cov`` (2, 2) m^2: the fix's stated covariance
        ``r`` plus the motion carry (``GpsFusion.carried_cov``); ``f``: its inflation for time
        correlation (1 without). The stated part goes in as ``r`` s^2 f (s^2 learned); the
        kernel's constant is divided by sqrt(f) (DCS's squared one by f), so it acts on the
        same residuals in metres as without the inflation. ``y`` (2,) m and ``s_inn`` (2, 2)
        m^2: the innovation against the newest keyframe and its covariance with the stated
        ``r``, for the outlier verdict: its NIS with the learned scale beyond ``gate_nis`` (the
        sensor's chi-square gate: what an EKF's gate would reject; the kernels weight such a
        fix at most 0.2), for maxmix the outlier component the likelier."""
        s2 = self.scale.factor
        c = cov + (s2 * f - 1.0) * r
        s_y = s_inn + (s2 - 1.0) * r
        if self.gm.model == "maxmix":
            out = c + self.gm.outlier_std ** 2 * np.eye(2)
            mix = MixtureModel(c, out, self.gm.outlier_weight)
            judge = MixtureModel(s_y, s_y + self.gm.outlier_std ** 2 * np.eye(2),
                                 self.gm.outlier_weight)
            return gps_maxmix_factor(key, e, n, mix, lever, dt), judge.choose(y) == 1
        base = (gtsam.noiseModel.Diagonal.Variances(np.array((c[0, 0], c[1, 1])))
                if c[0, 1] == 0.0 else gtsam.noiseModel.Gaussian.Covariance(c))
        k = self.k / (f if self.gm.model == "dcs" else math.sqrt(f))
        outlier = float(y @ np.linalg.solve(s_y, y)) > gate_nis
        return gps_factor(key, e, n, robust_model(self.gm.model, k, base), lever, dt), outlier

    def inlier_factor(self, key: int, e: float, n: float, cov: np.ndarray, r: np.ndarray,
                      f: float, lever: tuple[float, float], dt: float) -> gtsam.NonlinearFactor:
        """``factor``'s fix as an inlier, without the kernel or the outlier component: for a
        fix the estimate is moved to (a start taken for wrong, ``GpsFusion``), where a kernel
        would weigh it by its distance from the wrong estimate, i.e. not at all."""
        c = cov + (self.scale.factor * f - 1.0) * r
        base = (gtsam.noiseModel.Diagonal.Variances(np.array((c[0, 0], c[1, 1])))
                if c[0, 1] == 0.0 else gtsam.noiseModel.Gaussian.Covariance(c))
        return gps_factor(key, e, n, base, lever, dt)
