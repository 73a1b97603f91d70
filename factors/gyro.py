"""Gyro-bias factor on one keyframe state (rad/s, 1-D error).

``bias_difference_factor``: the mean gyro reading and the mean odometry yaw rate over the
same interval, z_g - k_w z_o = bg, error ``bg + k_w z_o - z_g`` whitened by its k_w-dependent
sigma (errors in both rates). State layout: ``ddfuse.factors.state``.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from ddfuse.factors.noise import as_noise_model
from ddfuse.factors.state import BG, DIM, KW

__all__ = ["bias_difference_factor"]


def bias_difference_factor(key: int, mean_gyro: float, mean_odo: float, sigma_gyro: float,
                           sigma_odo: float, record: list | None = None) -> gtsam.CustomFactor:
    """The gyro bias seen as the difference of two yaw rates held over the same interval.

    Both means are noisy: the odometry rate is a regressor with errors (errors-in-variables).
    Treating it as exact, with a fixed residual sigma, makes k_w the least-squares slope of
    gyro on odometry, attenuated towards 0 by var(noise) / (var(noise) + var(rate)): about 3 %
    with 0.4 s keyframe intervals on the simulated Husky, 5 sigma of k_w's posterior. The
    maximum-likelihood form with the unknown true rate u eliminated (z_g = u + bg + n_g,
    z_o = u / k_w + n_o) is the same residual ``r = bg + k_w z_o - z_g`` whitened by its
    k_w-dependent sigma, ``e = r / sqrt(sigma_g^2 + k_w^2 sigma_o^2)`` (Deming regression,
    consistent); the factor's noise model is unit.

    Args:
        key: 9-vector state key (``ddfuse.factors.state``), at the end of the interval.
        mean_gyro: mean gyro yaw rate over the interval, rad/s (bias included).
        mean_odo: mean odometry yaw rate over the same time, rad/s (before the k_w scale).
        sigma_gyro, sigma_odo: sigmas of the two means, rad/s (the rates' noise densities over
            the interval's duration, square-rooted).
        record: when given, ``(factor, (zg, zo, vg, vo))`` is appended to it (the means and the
            variances; the batch evaluates these factors together with numpy:
            ``estimation.smoother.batch_factors``).
    """
    zg, zo = float(mean_gyro), float(mean_odo)
    vg, vo = float(sigma_gyro) ** 2, float(sigma_odo) ** 2
    if not vg + vo > 0.0:
        raise ValueError("bias_difference_factor: sigma_gyro and sigma_odo are both zero")
    h = np.zeros((1, DIM))
    e = np.zeros(1)
    me = memoryview(e)
    sqrt = math.sqrt

    def error(this, values, H):
        s = values.atVector(key).tolist()
        k = s[KW]
        r = s[BG] + k * zo - zg
        var = vg + k * k * vo
        sd = sqrt(var)
        if H is not None:
            h[0, BG] = 1.0 / sd
            h[0, KW] = zo / sd - r * k * vo / (var * sd)
            H[0] = h
        me[0] = r / sd
        return e

    factor = gtsam.CustomFactor(as_noise_model(1.0, 1), [key], error)
    if record is not None:
        record.append((factor, (zg, zo, vg, vo)))
    return factor
