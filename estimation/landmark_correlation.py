"""Time-correlated landmark sightings, fused as if white: the variance inflation that keeps the
estimate's covariance honest, as for a correlated GPS (``estimation.gps_correlation``).

A camera's range and bearing to one landmark err alike from one frame to the next (the same
partial occlusion, the same segmentation of the same barcode, a range error that grows with
range): on mrclam1_robot1.bag two sightings of one landmark 0.05-0.2 s apart have range errors
correlated 0.95 and bearing errors 0.83, 1-2 s apart 0.46 and 0.54 (docs/design/tuning.md).
Fused as independent, a burst of N such sightings counts N times the information it carries.

The model is the GPS's: per landmark, a first-order Gauss-Markov error of the sighting's stated
variance and the sensor's ``correlation_time`` tau; each sighting is fused with its covariance
times f = (1 + rho) / (1 - rho), rho = exp(-dt / tau) (``gps_correlation.inflation``), dt the
time since the previous sighting of the same landmark by the same sensor that the estimator was
given (fused or not: a pure function of the stream, so every estimator inflates the same
sighting alike). The gate, the NIS and the log keep the sighting's own covariance.
"""

from __future__ import annotations

import math

from ddfuse.estimation.config import Config
from ddfuse.estimation.gps_correlation import inflation
from ddfuse.estimation.measurements import LandmarkObservation

__all__ = ["SightingClock"]


class SightingClock:
    """Per (sensor, landmark id), the stamp of the previous sighting: each sighting's factor
    on its covariance for fusion (``factor``, >= 1; 1 for a sensor without
    ``correlation_time``)."""

    def __init__(self, cfg: Config) -> None:
        self.tau = {s.name: float(s.correlation_time) for s in cfg.of_kind("landmarks")
                    if s.correlation_time > 0.0}
        self._last: dict[tuple[str, str], float] = {}

    def factor(self, m: LandmarkObservation) -> float:
        """The factor for sighting ``m``; call once per sighting, in the order given."""
        tau = self.tau.get(m.sensor)
        if tau is None:
            return 1.0
        key = (m.sensor, m.landmark_id)
        dt = m.t - self._last.get(key, -math.inf)
        self._last[key] = m.t
        return inflation(abs(dt), tau)
