"""What every estimator's robust GPS model shares (``gps.model``; docs/design/urban_gps.md): the
scale by which the fixes' stated covariance is too optimistic, learned from their innovations,
and the weight an M-estimator gives a whitened residual. No gtsam here: the EKFs use it too.

Units: NIS and kernel constants on the whitened residual (dimensionless).
"""

from __future__ import annotations

import bisect
import math
from collections import deque

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
