"""The interface that every estimator (each EKF, the smoother) implements, and what it reports.

An estimator consumes one measurement at a time in time order (``process``), gives its current
estimate on demand (``estimate``), and keeps a record of every innovation or residual it used
and every measurement it rejected, so that NIS and gate statistics can be computed afterwards.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from estimation.measurements import Measurement


def wrap_angle(a: float) -> float:
    """Wrap an angle to [-pi, pi), rad."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(slots=True)
class Estimate:
    """An estimator's belief at time ``t``.

    ``pose`` is (x, y, yaw) in the local frame (m, m, rad) and ``pose_cov`` its 3x3 covariance in
    the same world-frame coordinates (x, y, yaw), so that every estimator is scored alike.
    ``state``/``state_cov`` hold the estimator's full state vector and covariance, with
    ``state_names`` naming each component (e.g. ('x', 'y', 'yaw', 'v', 'yaw_rate'))."""

    t: float
    pose: tuple[float, float, float]
    pose_cov: np.ndarray  # (3, 3)
    state: np.ndarray | None = None  # (n,)
    state_cov: np.ndarray | None = None  # (n, n)
    state_names: tuple[str, ...] = ()


@dataclass(slots=True)
class Innovation:
    """One measurement update: the innovation (EKF) or residual (smoother) and its covariance.

    ``residual`` is z - h(x) with angles wrapped, shape (m,); ``cov`` is its covariance S, (m, m).
    ``nis`` is residual^T S^-1 residual. ``accepted`` is False when the gate rejected it.
    ``kind`` names the measurement model ('gps', 'heading', 'gyro', 'v', 'landmark', ...)."""

    t: float
    sensor: str
    kind: str
    residual: np.ndarray
    cov: np.ndarray
    nis: float
    accepted: bool = True


@dataclass
class EstimatorLog:
    """What an estimator used and rejected, for NIS, gate counts and the report."""

    innovations: list[Innovation] = field(default_factory=list)
    rejected: Counter = field(default_factory=Counter)  # (sensor, reason) -> count
    messages: list[str] = field(default_factory=list)  # notable events: resets, recoveries

    def note(self, t: float, text: str) -> None:
        self.messages.append(f"t={t:.3f}: {text}")


class Estimator(ABC):
    """Base class for every estimator.

    Subclasses implement ``process`` and ``estimate``. ``finish`` is called once after the last
    measurement (a smoother flushes its window there). Measurements an estimator cannot use
    (ground truth, a sensor type it does not model) are ignored, not rejected."""

    name: str = "estimator"

    def __init__(self) -> None:
        self.log = EstimatorLog()

    @abstractmethod
    def process(self, m: Measurement) -> None:
        """Consume one measurement. Measurements arrive in non-decreasing time order."""

    @abstractmethod
    def estimate(self) -> Estimate | None:
        """The current estimate, or None before the estimator is initialised."""

    def finish(self) -> None:  # noqa: B027 - optional hook
        """Called once after the last measurement."""

    @property
    def innovations(self) -> list[Innovation]:
        return self.log.innovations

    @property
    def rejected(self) -> Counter:
        return self.log.rejected
