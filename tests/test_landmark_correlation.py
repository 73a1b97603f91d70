"""estimation.landmark_correlation: each sighting's factor from the previous sighting of the
same landmark by the same sensor, the GPS's Gauss-Markov inflation."""

from __future__ import annotations

import dataclasses

import pytest
from ddfuse.estimation.config import Config, SensorConfig
from ddfuse.estimation.gps_correlation import inflation
from ddfuse.estimation.landmark_correlation import SightingClock
from ddfuse.estimation.measurements import LandmarkObservation


def _cfg(tau: float) -> Config:
    s = SensorConfig(kind="landmarks", topic="/lm", name="/lm", use=("range", "bearing"),
                     correlation_time=tau)
    return Config(sensors=[s])


def _sighting(t: float, lid: str) -> LandmarkObservation:
    return LandmarkObservation(t=t, landmark_id=lid, range=2.0, bearing=0.1, range_var=0.01,
                               bearing_var=0.001, has_bearing=True, sensor="/lm")


def test_factor_per_landmark_from_its_previous_sighting():
    clock = SightingClock(_cfg(2.0))
    assert clock.factor(_sighting(10.0, "a")) == 1.0  # the first sighting of 'a'
    assert clock.factor(_sighting(10.1, "b")) == 1.0  # another landmark: its own clock
    f = clock.factor(_sighting(10.25, "a"))
    assert f == pytest.approx(inflation(0.25, 2.0)) and f > 10.0  # (1+rho)/(1-rho), rho 0.88
    assert clock.factor(_sighting(30.25, "a")) == pytest.approx(1.0, abs=1e-3)  # 20 s later


def test_white_sensor_and_other_sensors_are_not_inflated():
    clock = SightingClock(_cfg(0.0))
    assert [clock.factor(_sighting(t, "a")) for t in (1.0, 1.1, 1.2)] == [1.0, 1.0, 1.0]
    clock = SightingClock(_cfg(2.0))
    other = dataclasses.replace(_sighting(1.0, "a"), sensor="/other")
    assert [clock.factor(other), clock.factor(dataclasses.replace(other, t=1.1))] == [1.0, 1.0]
