"""The smoother's GPS error models of the config's ``gps.model`` (``GpsModelConfig``): the scale
learned from the fixes' innovations, the robust noise models and the max-mixture factor, and
which fixes a model treats as outliers. When to use which: docs/design/urban_gps.md.

Units: covariances m^2 in local ENU; NIS and kernel constants on the whitened residual.
"""

from __future__ import annotations

import bisect
import math
from collections import deque

import gtsam
import numpy as np
from ddfuse.estimation.config import GpsModelConfig
from ddfuse.factors.gps import gps_factor
from ddfuse.factors.gps_mixture import MixtureModel, gps_maxmix_factor

# The kernels' constants on the whitened residual norm when the config gives none: Cauchy's
# 95 %-efficiency constant (Holland and Welsch 1977); Geman-McClure's and DCS's put the weight
# 1/2 near 1.6 and 2.9 sigma of a 2-D residual (DCS's Phi is a squared norm: Agarwal et al. 2013)
KERNEL_K = {"cauchy": 2.3849, "geman_mcclure": 2.5, "dcs": 5.99}
# The scale is read off the window's lower quartile of NIS: a quantile q of chi-square(2) is
# -2 ln(1 - q). The lower quartile stays on the inliers up to 75 % outliers and is biased less by
# them than the median (30 % outliers: x1.5 on s^2 against the median's x1.8)
QUANTILE = 0.25
CHI2_2_QUANTILE = -2.0 * math.log(1.0 - QUANTILE)
MIN_SAMPLES = 10  # innovations before the scale is learned (1 until then)


class GpsScale:
    """The variance factor s^2 >= 1 by which the fixes' stated covariance is too optimistic,
    learned from the NIS (innovation against the newest keyframe, stated covariance) of the
    fixes taken for inliers over the last ``window`` s: the NIS's lower quartile over
    chi-square(2)'s (QUANTILE), ignoring outliers while they are under three quarters of the
    window's fixes."""

    def __init__(self, window: float) -> None:
        self.window = float(window)
        self._t: deque[float] = deque()
        self._nis: list[float] = []  # sorted NIS of the window
        self._order: deque[float] = deque()  # the NIS in stamp order, for removal

    def add(self, t: float, nis: float) -> None:
        """Record the NIS ``nis`` of a fix at ``t`` s (stamp order)."""
        if self.window <= 0.0 or not math.isfinite(nis):
            return
        self._t.append(t)
        self._order.append(nis)
        bisect.insort(self._nis, nis)
        while self._t and self._t[0] < t - self.window:
            self._t.popleft()
            old = self._order.popleft()
            del self._nis[bisect.bisect_left(self._nis, old)]

    @property
    def factor(self) -> float:
        """s^2 (1 until MIN_SAMPLES innovations are in the window)."""
        n = len(self._nis)
        if n < MIN_SAMPLES:
            return 1.0
        return max(1.0, self._nis[int(QUANTILE * (n - 1))] / CHI2_2_QUANTILE)


def kernel_weight(model: str, k: float, r: float) -> float:
    """The weight the M-estimator ``model`` of constant ``k`` gives a whitened residual norm
    ``r`` (gtsam's definitions; DCS's ``k`` is on the squared norm)."""
    if model == "cauchy":
        return 1.0 / (1.0 + (r / k) ** 2)
    if model == "geman_mcclure":
        return k ** 4 / (k * k + r * r) ** 2
    if model == "dcs":
        return min(1.0, (2.0 * k / (k + r * r)) ** 2)
    return 1.0


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
