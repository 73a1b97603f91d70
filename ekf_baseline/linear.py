"""Seed 004's linear Kalman filters, corrected: the 1-D filter and the constant-acceleration model.

Both run on :class:`ddfuse.ekf_baseline.kalman.KalmanCore` (Joseph update, gates, innovation log).
The seed's errors (update without the residual, a process noise that is not a covariance, the
measurement matrix's shape, R's off-diagonal) are listed in docs/errata.md, "Seed 004".

* :class:`Kalman1D` -- a scalar state (e.g. a position along a line, m) moved by a known velocity
  (m/s) and measured directly (e.g. by encoders or a rangefinder). Its process noise is a
  velocity-error spectral density (m^2/s), so the variance added per step grows with the step
  length instead of the seed's fixed PROCESS_VAR per call.
* :class:`ConstantAccelerationKF` -- per axis the state (p, v, a), the seed's transition
  [[1, dt, dt^2/2], [0, 1, dt], [0, 0, 1]] replicated block-diagonally, the process noise of a
  continuous white-jerk model discretised exactly (the zero-order-hold/Van Loan discretisation the
  seed's "Discretization" section points to), direct measurements of the axes' positions.
* :func:`multiply_gaussians` -- the seed's product of two multivariate Gaussians.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from ddfuse.ekf_baseline.kalman import KalmanCore
from ddfuse.estimation.estimator import EstimatorLog

__all__ = [
    "Kalman1D",
    "ConstantAccelerationKF",
    "ca_transition",
    "ca_process_noise",
    "multiply_gaussians",
]


class Kalman1D:
    """Scalar Kalman filter: position ``x`` (m) with variance ``var`` (m^2).

    ``process_psd`` (m^2/s) is the spectral density of the error of the commanded velocity
    (white noise): a step of ``dt`` seconds adds ``process_psd * dt`` to the variance.
    ``meas_var`` (m^2) is the measurement variance; ``gate`` an optional chi-square acceptance
    probability for the measurement gate."""

    def __init__(
        self,
        x0: float,
        var0: float,
        process_psd: float,
        meas_var: float,
        *,
        sensor: str = "position",
        gate: float | None = None,
        log: EstimatorLog | None = None,
    ) -> None:
        if var0 < 0 or process_psd < 0 or meas_var <= 0:
            raise ValueError("variances must be >= 0 (measurement variance > 0)")
        self.kf = KalmanCore([x0], [[var0]], log)
        self.process_psd = float(process_psd)
        self.meas_var = float(meas_var)
        self.sensor = sensor
        self.gate = gate
        self.t = 0.0
        self._one = np.ones((1, 1))

    @property
    def x(self) -> float:
        return float(self.kf.x[0])

    @property
    def var(self) -> float:
        return float(self.kf.P[0, 0])

    @property
    def log(self) -> EstimatorLog:
        return self.kf.log

    def predict(self, velocity: float, dt: float) -> None:
        """Move by ``velocity`` (m/s) for ``dt`` (s); the variance grows by process_psd * dt."""
        self.t += dt
        self.kf.predict(self._one, np.array([[self.process_psd * dt]]),
                        np.array([self.x + velocity * dt]))

    def update(self, z: float, meas_var: float | None = None) -> bool:
        """Fuse a direct measurement ``z`` (m) of the state; returns False if gated out.

        The gain is var / (var + meas_var), the seed's formula; the state moves by the gain
        times the residual z - x (the seed's pseudocode forgets the residual). ``z`` is an
        absolute position: an encoder *increment* since the last step is the motion input
        (``predict``'s velocity = increment / dt), not a measurement (errata 004 #15)."""
        r = self.meas_var if meas_var is None else meas_var
        return self.kf.update(self.t, self.sensor, "position", [z], [self.x], self._one,
                              [[r]], gate=self.gate)

    def gain(self, meas_var: float | None = None) -> float:
        """The Kalman gain the next update would use, var / (var + meas_var)."""
        r = self.meas_var if meas_var is None else meas_var
        return self.var / (self.var + r)


def ca_transition(dt: float) -> np.ndarray:
    """One axis' constant-acceleration transition for state (p, v, a) over ``dt`` s, (3, 3)."""
    return np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])


def ca_process_noise(dt: float, jerk_psd: float) -> np.ndarray:
    """Exact discrete process noise of one axis of the constant-acceleration model, (3, 3).

    The acceleration is driven by continuous white jerk of spectral density ``jerk_psd``
    ((m/s^3)^2 / Hz = m^2/s^5). Q = integral_0^dt e^{A s} G q G^T e^{A^T s} ds with
    A = [[0,1,0],[0,0,1],[0,0,0]], G = (0, 0, 1)^T; this is symmetric positive definite for
    dt > 0, unlike the seed's example Q."""
    d2 = dt * dt
    d3 = d2 * dt
    d4 = d3 * dt
    d5 = d4 * dt
    return jerk_psd * np.array(
        [
            [d5 / 20.0, d4 / 8.0, d3 / 6.0],
            [d4 / 8.0, d3 / 3.0, d2 / 2.0],
            [d3 / 6.0, d2 / 2.0, dt],
        ]
    )


class ConstantAccelerationKF:
    """Constant-acceleration Kalman filter over several independent axes.

    State order: (p_0, v_0, a_0, p_1, v_1, a_1, ...), one (p, v, a) block per axis (units of the
    axis: m, m/s, m/s^2 for a position axis, rad, rad/s, rad/s^2 for a heading axis). Axes in
    ``angle_axes`` have their position wrapped to [-pi, pi) and their residuals wrapped.

    ``jerk_psd`` is per axis (or one value for all): spectral density of the white jerk, the
    model's only tuning -- the size of unmodelled changes of acceleration. ``meas_std`` is the
    standard deviation of each axis' position measurement. ``p0_std`` is the initial standard
    deviation of (p, v, a) per axis; the seed's P0 with zero velocity variance ("the robot is
    known to start still") is ``p0_std=(0.7, 0.0, 0.0)``."""

    def __init__(
        self,
        x0: Sequence[float],
        *,
        axes: int,
        jerk_psd: float | Sequence[float],
        meas_std: float | Sequence[float],
        p0_std: Sequence[float] = (1.0, 0.0, 0.0),
        angle_axes: Sequence[int] = (),
        gate: float | None = None,
        sensor: str = "position",
        log: EstimatorLog | None = None,
    ) -> None:
        self.axes = int(axes)
        n = 3 * self.axes
        x0 = np.asarray(x0, dtype=float)
        if x0.shape == (self.axes,):  # positions only: start at rest
            x0 = np.concatenate([[p, 0.0, 0.0] for p in x0])
        if x0.shape != (n,):
            raise ValueError(f"x0 must have {self.axes} positions or {n} states")
        self.jerk_psd = np.broadcast_to(np.asarray(jerk_psd, dtype=float), (self.axes,)).copy()
        self.meas_std = np.broadcast_to(np.asarray(meas_std, dtype=float), (self.axes,)).copy()
        p0 = np.tile(np.asarray(p0_std, dtype=float) ** 2, self.axes)
        self.angle_axes = tuple(angle_axes)
        self.kf = KalmanCore(x0, np.diag(p0), log,
                             state_angles=tuple(3 * a for a in self.angle_axes))
        self.gate = gate
        self.sensor = sensor
        self.t = 0.0
        self.H = np.zeros((self.axes, n))
        for a in range(self.axes):
            self.H[a, 3 * a] = 1.0
        self.R = np.diag(self.meas_std**2)
        self._angles_meas = self.angle_axes

    @property
    def x(self) -> np.ndarray:
        return self.kf.x

    @property
    def P(self) -> np.ndarray:
        return self.kf.P

    @property
    def log(self) -> EstimatorLog:
        return self.kf.log

    def matrices(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(F, Q) of a ``dt``-second step, block-diagonal over the axes."""
        n = 3 * self.axes
        F = np.zeros((n, n))
        Q = np.zeros((n, n))
        Fa = ca_transition(dt)
        for a in range(self.axes):
            s = slice(3 * a, 3 * a + 3)
            F[s, s] = Fa
            Q[s, s] = ca_process_noise(dt, self.jerk_psd[a])
        return F, Q

    def predict(self, dt: float) -> None:
        """Propagate by ``dt`` seconds."""
        F, Q = self.matrices(dt)
        self.t += dt
        self.kf.predict(F, Q)

    def update(self, z: Sequence[float], meas_std: Sequence[float] | None = None) -> bool:
        """Fuse one measurement of every axis' position, ``z`` (axes,)."""
        R = self.R if meas_std is None else np.diag(np.asarray(meas_std, dtype=float) ** 2)
        return self.kf.update(self.t, self.sensor, "position", z, self.H @ self.kf.x, self.H, R,
                              angles=self._angles_meas, gate=self.gate)


def multiply_gaussians(
    mean1: np.ndarray, cov1: np.ndarray, mean2: np.ndarray, cov2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Product of two Gaussian densities N(mean1, cov1) N(mean2, cov2), normalised.

    mean = cov2 (cov1 + cov2)^-1 mean1 + cov1 (cov1 + cov2)^-1 mean2,
    cov = cov1 (cov1 + cov2)^-1 cov2 (the seed's formulas, which are right; symmetrised)."""
    mean1 = np.atleast_1d(np.asarray(mean1, dtype=float))
    mean2 = np.atleast_1d(np.asarray(mean2, dtype=float))
    cov1 = np.atleast_2d(np.asarray(cov1, dtype=float))
    cov2 = np.atleast_2d(np.asarray(cov2, dtype=float))
    s = cov1 + cov2
    mean = cov2 @ np.linalg.solve(s, mean1) + cov1 @ np.linalg.solve(s, mean2)
    cov = cov1 @ np.linalg.solve(s, cov2)
    return mean, 0.5 * (cov + cov.T)
