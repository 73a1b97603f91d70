"""Chi-square quantiles without ``scipy.stats``.

``scipy.stats`` is too heavy an import for the few gate thresholds and consistency bands
ddfuse needs (docs/design/performance.md). ``ppf`` computes the quantile the way
``scipy.stats.chi2.ppf`` does (``2 * gammaincinv(dof / 2, p)``, scipy 1.17's
``chi2_gen._ppf``; the scale 1 and location 0 it then applies change no bit), from
``scipy.special`` alone; tests/test_chi2.py checks it equals ``chi2.ppf`` value for value.
"""

from __future__ import annotations

import math

# The quantiles a run asks for (its gates' usual probabilities and the 95 % consistency band's
# two tails, 1-3 dof), exactly as the formula below gives them with scipy 1.17
# (tests/test_chi2.py checks every entry against it): a run then starts without importing
# scipy.special, a large share of its start-up (docs/design/performance.md). 1 - 0.975 is a key
# of its own: the bands compute it.
KNOWN: dict[tuple[float, float], float] = {
    (0.025, 1): 0.0009820691171752555,
    (0.025, 2): 0.05063561596857975,
    (0.025, 3): 0.21579528262389785,
    (0.025000000000000022, 1): 0.0009820691171752583,
    (0.025000000000000022, 2): 0.050635615968579795,
    (0.025000000000000022, 3): 0.21579528262389797,
    (0.05, 1): 0.003932140000019522,
    (0.05, 2): 0.10258658877510106,
    (0.05, 3): 0.35184631774927144,
    (0.95, 1): 3.841458820694124,
    (0.95, 2): 5.991464547107979,
    (0.95, 3): 7.814727903251179,
    (0.975, 1): 5.023886187314888,
    (0.975, 2): 7.377758908227871,
    (0.975, 3): 9.348403604496148,
    (0.99, 1): 6.6348966010212145,
    (0.99, 2): 9.21034037197618,
    (0.99, 3): 11.344866730144373,
    (0.995, 1): 7.879438576622417,
    (0.995, 2): 10.596634733096073,
    (0.995, 3): 12.838156466598647,
    (0.999, 1): 10.827566170662733,
    (0.999, 2): 13.815510557964274,
    (0.999, 3): 16.26623619623813,
    (0.9999, 1): 15.136705226623606,
    (0.9999, 2): 18.420680743952584,
    (0.9999, 3): 21.107513466160444,
}


def ppf(p: float, dof: float) -> float:
    """The ``p`` quantile of the chi-square distribution with ``dof`` (> 0) degrees of freedom:
    0 at p = 0, inf at p = 1, NaN for p outside [0, 1], dof <= 0 or a NaN argument (as
    ``scipy.stats.chi2.ppf``). The values in KNOWN without scipy; others import
    scipy.special on first use (an estimator's gate is computed when it is built, not in a
    timed update)."""
    if not (dof > 0.0 and 0.0 <= p <= 1.0):  # NaN fails these comparisons too
        return math.nan
    known = KNOWN.get((p, dof))
    if known is not None:
        return known
    from scipy.special import gammaincinv

    return 2.0 * float(gammaincinv(dof / 2.0, p))
