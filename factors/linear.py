"""Measurements that are linear in one keyframe state, as one C++ factor.

The absolute heading (``factors.heading``: z = wrap(psi [+ hoff])) has a constant Jacobian (the
gyro-bias difference does not: its sigma depends on k_w, ``ddfuse.factors.gyro``). As Python
``CustomFactor`` it costs a Python callback (and a pybind11 copy of the whole window's Values)
every time ISAM2 relinearises it. As a ``gtsam.JacobianFactor`` wrapped in a
``gtsam.LinearContainerFactor`` it is one factor that ISAM2 relinearises in C++, exactly: for
a linear measurement the linear factor re-centred at any point (``LinearContainerFactor`` shifts
its right-hand side by A (x - x_lin)) is the factor's own linearisation there.

Angle rows are unwrapped against the linearisation point: the stored residual is
wrap(h x_lin - z), so the error at x is wrap(h x_lin - z) + h (x - x_lin), which equals the
wrapped error wrap(h x - z) of the custom factors while the estimate stays within pi of x_lin
(a keyframe's heading estimate moving by pi would be a lost filter anyway).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import gtsam
import numpy as np
from ddfuse.factors.state import DIM, HOFF, PSI

__all__ = ["heading_row", "linear_state_factor"]

_PI = math.pi
_TWO_PI = 2.0 * math.pi

# one row: (h (DIM,) d error / d state, measurement z, sigma, is the row an angle)
Row = tuple[np.ndarray, float, float, bool]


def heading_row(z: float, sigma: float, use_offset: bool = True) -> Row:
    """The absolute heading z (rad) with sigma (rad): error wrap(psi [+ hoff] - z)."""
    h = np.zeros(DIM)
    h[PSI] = 1.0
    if use_offset:
        h[HOFF] = 1.0
    return h, float(z), float(sigma), True


def linear_state_factor(key: int, rows: Sequence[Row],
                        lin: np.ndarray) -> gtsam.LinearContainerFactor:
    """One factor for the linear measurement ``rows`` of the 9-vector state ``key``.

    Args:
        key: the state's key (``ddfuse.factors.state``).
        rows: (h, z, sigma, angle) per measurement: error h x - z (wrapped to [-pi, pi) for
            angle rows) with standard deviation sigma, in the units of z.
        lin: (DIM,) the linearisation point (e.g. the keyframe's initial guess); angle rows are
            unwrapped against it.
    """
    if not rows:
        raise ValueError("linear_state_factor needs at least one row")
    lin = np.asarray(lin, dtype=np.float64).reshape(DIM)
    a = np.empty((len(rows), DIM))
    b = np.empty(len(rows))
    sig = np.empty(len(rows))
    for r, (h, z, sigma, angle) in enumerate(rows):
        e = float(h @ lin) - z
        if angle:
            e = (e + _PI) % _TWO_PI - _PI
        a[r] = h
        b[r] = -e  # JacobianFactor error: A dx - b, with dx = x - lin
        sig[r] = sigma
    jf = gtsam.JacobianFactor(key, a, b, gtsam.noiseModel.Diagonal.Sigmas(sig))
    lp = gtsam.Values()
    lp.insert(key, lin)
    return gtsam.LinearContainerFactor(jf, lp)
