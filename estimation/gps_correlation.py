"""Time-correlated GPS errors, fused as if white: the variance inflation that keeps the
estimate's covariance honest.

A receiver's position error is not white: multipath, the atmosphere and the satellite geometry
change over tens of seconds, so fixes 0.4 s apart carry nearly the same error. An estimator that
fuses each fix as an independent measurement of variance sigma^2 averages N of them down to
sigma^2 / N, while the error it cannot see (the slowly varying part) stays at sigma^2: it
becomes over-confident and follows the GPS's wander.

Model the error as a first-order Gauss-Markov process per axis, stationary variance sigma^2
(the fix's covariance) and correlation time tau (the sensor's ``correlation_time``): fixes dt
apart are correlated by rho = exp(-dt / tau). A long run of such fixes carries the information
of fixes with variance sigma^2 (1 + rho) / (1 - rho) each (the variance of a long average of an
AR(1) sequence), so each fix is fused with its covariance times

    f = (1 + rho) / (1 - rho),    rho = exp(-dt / tau),

dt the time since the previous fix of that sensor the estimator fused (``inflation``). At 2.5 Hz
with tau = 30 s, f = 150; a fix after a 60 s outage, f = 1.3; the first fix, f = 1.

This is the cheap remedy, not the model: the fixes' common error is not a state, so the estimate
does not learn it, and over stretches much shorter than tau the inflated fixes are pessimistic.
The gate and the NIS keep the fix's own covariance: a fix is judged as one sample of the
receiver's error, and a gross outlier is rejected as with white fixes.
"""

from __future__ import annotations

import math

__all__ = ["inflation"]


def inflation(dt: float, tau: float) -> float:
    """The factor (>= 1) by which a fix's covariance is multiplied for fusion: ``dt`` (s) since
    the previous fused fix of its sensor (inf or nan: none), ``tau`` (s) the sensor's
    ``correlation_time`` (0: white, factor 1). A ``dt`` of 0 or below (two fixes with one stamp)
    is taken as 1 ms: the factor is large, not infinite."""
    if not tau > 0.0 or not dt < math.inf:  # white, or no previous fix (nan as well)
        return 1.0
    x = max(dt, 1e-3) / tau
    # (1 + e^-x) / (1 - e^-x) = coth(x / 2); expm1 keeps it exact for small x
    return (2.0 + math.expm1(-x)) / -math.expm1(-x)
