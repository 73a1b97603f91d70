"""evaluation.tune_rules.sighting_scatter: a landmark sensor's correlation time from each landmark's
own sightings, gps_scatter's neighbour rule at the tuned bearing sigma."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from ddfuse.estimation.measurements import LandmarkObservation
from ddfuse.evaluation.tune_rules import sighting_scatter

SIGMA = 0.02  # rad


def _problem(tau: float, seed: int = 1) -> SimpleNamespace:
    """Bursts of sightings of 3 landmarks 0.25 s apart (20 per burst, 10 s between bursts),
    seen from a robot turning at 0.1 rad/s, bearing errors a Gauss-Markov process of sigma
    SIGMA and correlation time ``tau`` per landmark (0: white)."""
    rng = np.random.default_rng(seed)
    ms = []
    for lid in ("a", "b", "c"):
        e = 0.0
        for burst in range(40):
            t0 = 15.0 * burst + {"a": 0.0, "b": 0.1, "c": 0.2}[lid]
            e = rng.normal(0.0, SIGMA)  # bursts 10 s apart: independent at these tau
            for k in range(20):
                t = t0 + 0.25 * k
                if k and tau > 0.0:
                    rho = math.exp(-0.25 / tau)
                    e = rho * e + math.sqrt(1.0 - rho * rho) * rng.normal(0.0, SIGMA)
                elif k:
                    e = rng.normal(0.0, SIGMA)
                ms.append(LandmarkObservation(t=t, landmark_id=lid, range=2.0,
                                              bearing=1.0 - 0.1 * t + e, range_var=0.01,
                                              bearing_var=SIGMA ** 2, has_bearing=True,
                                              sensor="/lm"))
    ms.sort(key=lambda m: m.t)
    return SimpleNamespace(stream=SimpleNamespace(measurements=ms))


# (gps_scatter calls errors correlated from about 6 sample intervals up: 1.5 s here)
@pytest.mark.parametrize("tau", [2.0, 4.0])
def test_the_correlation_time_of_correlated_sightings_is_found(tau):
    got = sighting_scatter(_problem(tau), "/lm", SIGMA)
    assert got == pytest.approx(tau, rel=0.25)


def test_white_sightings_have_none():
    assert sighting_scatter(_problem(0.0), "/lm", SIGMA) is None


def test_another_sensor_or_too_few_sightings_have_none():
    p = _problem(2.0)
    assert sighting_scatter(p, "/other", SIGMA) is None
    p.stream.measurements = p.stream.measurements[:10]
    assert sighting_scatter(p, "/lm", SIGMA) is None
