"""Chi-square quantiles without ``scipy.stats``.

Importing ``scipy.stats`` costs 0.6-1.2 s of start-up (it loads every distribution, sparse
matrices, spatial and optimize), more than a whole EKF run on a 400 s bag, for the few gate
thresholds and consistency bands ddfuse needs. ``ppf`` computes the quantile the way
``scipy.stats.chi2.ppf`` does (``2 * gammaincinv(dof / 2, p)``, scipy 1.17's
``chi2_gen._ppf``; the scale 1 and location 0 it then applies change no bit), from
``scipy.special`` alone; tests/test_chi2.py checks it equals ``chi2.ppf`` value for value.
"""

from __future__ import annotations

import math

# imported here, not on first use: the first use may be an estimator's timed update
from scipy.special import gammaincinv


def ppf(p: float, dof: float) -> float:
    """The ``p`` quantile of the chi-square distribution with ``dof`` (> 0) degrees of freedom:
    0 at p = 0, inf at p = 1, NaN for p outside [0, 1], dof <= 0 or a NaN argument (as
    ``scipy.stats.chi2.ppf``)."""
    if not (dof > 0.0 and 0.0 <= p <= 1.0):  # NaN fails these comparisons too
        return math.nan
    return 2.0 * float(gammaincinv(dof / 2.0, p))
