"""Time-correlated heading samples (an IMU's orientation yaw, a compass), fused as if white: the
variance inflation that keeps the estimate's covariance honest, as for a correlated GPS
(``estimation.gps_correlation``) and landmark sightings (``estimation.landmark_correlation``).

An IMU's yaw is the output of its own orientation filter: smooth from one 50 Hz sample to the
next, its error wandering over seconds (docs/design/tuning.md, "Measured, session 22"). Fused as
independent, a second of such samples counts 50 times the information it carries, and a
smoother that averages a keyframe's samples into one factor divides their variance by their
number.

The model is the GPS's: per sensor, a first-order Gauss-Markov error of the sample's stated
variance and the sensor's ``correlation_time`` tau; each sample is fused with its variance
times f = (1 + rho) / (1 - rho), rho = exp(-dt / tau) (``gps_correlation.inflation``), dt the
time since the sensor's previous sample the estimator was given (fused or not: a pure function
of the stream, so every estimator inflates the same sample alike, and a smoother's average of
n samples is inflated as the EKF's n updates are). The gate, the NIS and the log keep the
sample's own variance.
"""

from __future__ import annotations

import math

from ddfuse.estimation.config import Config
from ddfuse.estimation.gps_correlation import inflation
from ddfuse.estimation.measurements import Heading

__all__ = ["HeadingClock"]


class HeadingClock:
    """Per heading sensor with a ``correlation_time``, the stamp of its previous sample: each
    sample's factor on its variance for fusion (``factor``, >= 1; 1 for a sensor without
    one)."""

    def __init__(self, cfg: Config) -> None:
        self.tau = {s.name: float(s.correlation_time) for s in cfg.heading_sensors()
                    if s.correlation_time > 0.0}
        self._last: dict[str, float] = {}  # sensor -> stamp of its newest sample
        # sensor -> {stamp: factor} of its newest samples, for a sample asked about again
        self._given: dict[str, dict[float, float]] = {}

    def __bool__(self) -> bool:
        return bool(self.tau)

    def factor(self, m: Heading) -> float:
        """The factor for sample ``m``, samples taken in stream order. Asked again about a
        recent sample (an estimator that hands a message, or a fixed-rate step's several, from
        its compiled path to its Python one), it gives the same factor."""
        tau = self.tau.get(m.sensor)
        if tau is None:
            return 1.0
        given = self._given.setdefault(m.sensor, {})
        last = self._last.get(m.sensor, -math.inf)
        if m.t <= last and m.t in given:
            return given[m.t]
        f = inflation(m.t - last, tau)
        self._last[m.sensor] = max(m.t, last)
        if len(given) >= _KEEP:
            del given[next(iter(given))]  # the oldest
        given[m.t] = f
        return f


# the samples whose factors are kept: more than a fixed-rate EKF step holds
_KEEP = 256
