"""Seed 004's g-h filter: a fixed gain, against the Kalman filter's computed one.

The article introduces the Kalman filter through the g-h filter (its "G-H Filter ... uses a
single gain value"; errata 004 #12: there are two). For a 1-D constant-velocity state
(position p, velocity v) measured in position every ``dt`` seconds, one step is

    predict:  p_ = p + v dt,  v_ = v
    update:   r = z - p_,  p = p_ + g r,  v = v_ + (h / dt) r

with g and h fixed. The Kalman filter has the same structure with the gain K_k = (g_k, h_k / dt)
computed from P every step; for a constant model and noise K_k converges, so the steady-state
Kalman filter IS a g-h filter. For the constant-velocity model driven by a piecewise-constant
white acceleration of standard deviation ``accel_std`` (m/s^2, the discrete white-noise
acceleration model: Q = accel_std^2 [[dt^4/4, dt^3/2], [dt^3/2, dt^2]]) and position noise
``meas_std`` (m), the steady-state pair depends only on the tracking index
lambda = accel_std dt^2 / meas_std (Kalata 1984; Bar-Shalom, Li and Kirubarajan, *Estimation
with Applications to Tracking and Navigation*, 2001, sec. 6.5.3):

    g = -(lambda^2 + 8 lambda - (lambda + 4) sqrt(lambda^2 + 8 lambda)) / 8
    h = (lambda^2 + 4 lambda - lambda sqrt(lambda^2 + 8 lambda)) / 4,   h^2 / (1 - g) = lambda^2

(:func:`kalata_gains`; :func:`steady_state_gain` solves the Riccati equation for any model).
A g-h pair chosen by hand has no such tie to the noise: it is stable for 0 < g, 0 < h < 4 - 2g,
and its error then depends on how far it is from the Kalata pair (docs/design/gh_filter.md).

The same holds one order up: seed 004's constant-acceleration filter
(``linear.ConstantAccelerationKF``, state (p, v, a)) tends to the g-h-k filter of
:func:`ghk_gains` (:class:`GHKFilter`; the acceleration moves by 2 k r / dt^2).

Pure math: the plots are in ``ddfuse.evaluation.gh_figure``; the Kalman filter is
:class:`ddfuse.ekf_baseline.kalman.KalmanCore`, as in ``linear.py``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from ddfuse.ekf_baseline.kalman import KalmanCore
from ddfuse.ekf_baseline.linear import ca_process_noise, ca_transition
from scipy.linalg import solve_discrete_are

__all__ = [
    "GHFilter",
    "gh_run",
    "cv_matrices",
    "kalata_gains",
    "steady_state_gain",
    "cv_kalman",
    "cv_track",
    "GHKFilter",
    "ghk_gains",
    "ca_track",
]

_H = np.array([[1.0, 0.0]])


class GHFilter:
    """The g-h filter of a 1-D constant-velocity state: position ``x`` (m), velocity ``dx``
    (m/s), fixed gains ``g`` (on the position residual) and ``h`` (on the rate: the velocity
    moves by h r / dt)."""

    def __init__(self, x0: float, dx0: float, g: float, h: float) -> None:
        self.x, self.dx, self.g, self.h = float(x0), float(dx0), float(g), float(h)

    def step(self, z: float, dt: float, velocity: float | None = None) -> tuple[float, float]:
        """Predict ``dt`` s ahead and fuse the position ``z`` (m); returns (x m, dx m/s).

        ``velocity`` (m/s): a known velocity (the seed's commanded speed) instead of the state's;
        with it, h is unused and the filter is the article's single-gain g filter."""
        v = self.dx if velocity is None else float(velocity)
        xp = self.x + v * dt
        r = z - xp
        self.x = xp + self.g * r
        self.dx = v if velocity is not None else v + self.h / dt * r
        return self.x, self.dx


def gh_run(zs: Sequence[float], dt: float, x0: float, dx0: float, g: float,
           h: float) -> np.ndarray:
    """The g-h filter over the positions ``zs`` (m) at a fixed step ``dt`` (s), started at
    (x0, dx0): the (n, 2) estimates (x m, dx m/s) after each measurement."""
    f = GHFilter(x0, dx0, g, h)
    return np.array([f.step(float(z), dt) for z in zs])


def cv_matrices(dt: float, accel_std: float) -> tuple[np.ndarray, np.ndarray]:
    """(F, Q) of the 1-D constant-velocity model over ``dt`` s, (2, 2) each: Q of a
    piecewise-constant white acceleration of standard deviation ``accel_std`` (m/s^2)."""
    F = np.array([[1.0, dt], [0.0, 1.0]])
    G = np.array([[0.5 * dt * dt], [dt]])
    return F, accel_std * accel_std * (G @ G.T)


def kalata_gains(dt: float, accel_std: float, meas_std: float) -> tuple[float, float]:
    """The steady-state Kalman gains (g, h) of the constant-velocity model (module docstring):
    the Kalman filter's gain tends to (g, h / dt)."""
    lam = accel_std * dt * dt / meas_std
    s = math.sqrt(lam * lam + 8.0 * lam)
    g = -(lam * lam + 8.0 * lam - (lam + 4.0) * s) / 8.0
    h = (lam * lam + 4.0 * lam - lam * s) / 4.0
    return g, h


def steady_state_gain(F: np.ndarray, H: np.ndarray, Q: np.ndarray,
                      R: np.ndarray) -> np.ndarray:
    """The steady-state Kalman gain (n, m) of a constant linear model, from the prior
    covariance P solving the discrete algebraic Riccati equation
    P = F P F^T - F P H^T (H P H^T + R)^-1 H P F^T + Q: K = P H^T (H P H^T + R)^-1."""
    P = solve_discrete_are(F.T, H.T, Q, R)
    return P @ H.T @ np.linalg.inv(H @ P @ H.T + R)


def cv_kalman(zs: Sequence[float], dt: float, accel_std: float, meas_std: float,
              x0: Sequence[float], p0_std: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """The Kalman filter of the same model (KalmanCore, Joseph update) over ``zs``: the (n, 2)
    estimates (x m, dx m/s) after each measurement and the (n, 2) gains used, (g_k, h_k) in
    the g-h filter's units (K = (g_k, h_k / dt))."""
    F, Q = cv_matrices(dt, accel_std)
    R = np.array([[meas_std * meas_std]])
    kf = KalmanCore(np.asarray(x0, dtype=float), np.diag(np.square(p0_std)))
    est, gains = [], []
    for k, z in enumerate(zs):
        kf.predict(F, Q)
        PHt = kf.P @ _H.T
        K = PHt / (_H @ PHt + R)[0, 0]
        gains.append((K[0, 0], K[1, 0] * dt))
        kf.update(k * dt, "position", "position", [float(z)], _H @ kf.x, _H, R)
        est.append(kf.x.copy())
    return np.array(est), np.array(gains)


def cv_track(rng: np.random.Generator, n: int, dt: float, accel_std: float, meas_std: float,
             x0: Sequence[float] = (0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """A truth drawn from the constant-velocity model and its position readings: (n, 2) true
    (x m, dx m/s) at steps 1..n and the (n,) readings (m), white noise of ``meas_std``."""
    F, _ = cv_matrices(dt, accel_std)
    G = np.array([0.5 * dt * dt, dt])
    x = np.asarray(x0, dtype=float)
    truth = np.empty((n, 2))
    for k in range(n):
        x = F @ x + G * (accel_std * rng.normal())
        truth[k] = x
    return truth, truth[:, 0] + meas_std * rng.normal(size=n)


class GHKFilter:
    """The g-h-k filter of a 1-D constant-acceleration state (x m, dx m/s, ddx m/s^2): fixed
    gains g, h, k; the residual r moves x by g r, dx by h r / dt and ddx by 2 k r / dt^2."""

    def __init__(self, x0: Sequence[float], g: float, h: float, k: float) -> None:
        self.x = np.asarray(x0, dtype=float).copy()
        self.g, self.h, self.k = float(g), float(h), float(k)

    def step(self, z: float, dt: float) -> np.ndarray:
        """Predict ``dt`` s ahead and fuse the position ``z`` (m); returns (x, dx, ddx)."""
        xp = ca_transition(dt) @ self.x
        r = z - xp[0]
        self.x = xp + r * np.array([self.g, self.h / dt, 2.0 * self.k / (dt * dt)])
        return self.x.copy()


def ghk_gains(dt: float, jerk_psd: float, meas_std: float) -> tuple[float, float, float]:
    """The steady-state (g, h, k) of ``linear.ConstantAccelerationKF``'s one-axis model (white
    jerk of density ``jerk_psd``, m^2/s^5; readings of ``meas_std`` m): its Kalman gain tends
    to (g, h / dt, 2 k / dt^2)."""
    K = steady_state_gain(ca_transition(dt), np.array([[1.0, 0.0, 0.0]]),
                          ca_process_noise(dt, jerk_psd), np.array([[meas_std * meas_std]]))
    return float(K[0, 0]), float(K[1, 0] * dt), float(K[2, 0] * dt * dt / 2.0)


def ca_track(rng: np.random.Generator, n: int, dt: float, jerk_psd: float, meas_std: float,
             x0: Sequence[float] = (0.0, 1.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """A truth drawn from ``linear.ConstantAccelerationKF``'s one-axis model and its position
    readings: (n, 3) true (x, dx, ddx) at steps 1..n and the (n,) readings (m)."""
    F, Q = ca_transition(dt), ca_process_noise(dt, jerk_psd)
    w = rng.multivariate_normal(np.zeros(3), Q, size=n)
    x = np.asarray(x0, dtype=float)
    truth = np.empty((n, 3))
    for i in range(n):
        x = F @ x + w[i]
        truth[i] = x
    return truth, truth[:, 0] + meas_std * rng.normal(size=n)
