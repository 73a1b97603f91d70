"""Whether a landmark sensor's bearings share an error within a frame, from one EKF run's
innovations under the independent model (``ddfuse tune`` decides with it whether to fit a
``noise.bearing_common`` the config does not state).

An EKF fuses a frame's sightings one after the other; under a right model its innovations are
white, so the bearing innovations of consecutive sightings of one frame (same sensor and stamp),
each divided by its standard deviation, are uncorrelated whatever the pose's uncertainty. An
error common to the frame's bearings, which the independent model leaves out, correlates them:
about c^2 / (c^2 + s^2) for a common part c and an own part s. The statistic is that
correlation over every such pair of accepted innovations; under white innovations it is
N(0, 1 / n) for n pairs.

Measured (docs/design/tuning.md, session 23): mrclam1_robot1.bag at the independent model's
tuned values 0.617 over 1 409 pairs; data/sample_seed002.bag (simulated, independent bearings)
0.003 over 4 683 pairs.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["MIN_CORRELATION", "MIN_PAIRS", "Z_SCORE", "frame_correlation", "shows_common"]

MIN_CORRELATION = 0.1  # a common part of about a tenth of the bearing's variance, or more
Z_SCORE = 3.0  # and beyond what white innovations give by chance
MIN_PAIRS = 30  # fewer pairs of same-frame sightings tell nothing


def frame_correlation(innovations, sensor: str) -> tuple[float, int]:
    """(correlation, pairs): the correlation of the normalised bearing innovations (the last
    component of each 'landmark' innovation over the square root of its variance) of
    consecutive accepted sightings of ``sensor`` at the same stamp, and how many such pairs the
    log ``innovations`` (an iterable of ``Innovation``, in log order) holds; (nan, n) under
    ``MIN_PAIRS``."""
    a, b = [], []
    prev = None
    for e in innovations:
        if e.sensor != sensor or e.kind != "landmark" or not e.accepted:
            prev = None if e.sensor == sensor else prev
            continue
        var = float(np.asarray(e.cov)[-1, -1])
        z = float(np.asarray(e.residual)[-1]) / math.sqrt(var) if var > 0.0 else math.nan
        if prev is not None and prev[0] == e.t and math.isfinite(z) and math.isfinite(prev[1]):
            a.append(prev[1])
            b.append(z)
        prev = (e.t, z)
    n = len(a)
    if n < MIN_PAIRS:
        return math.nan, n
    x, y = np.array(a), np.array(b)
    return float(np.sum(x * y) / math.sqrt(np.sum(x * x) * np.sum(y * y))), n


def shows_common(corr: float, pairs: int) -> bool:
    """Whether ``frame_correlation``'s figure says the frames share a bearing error: at least
    ``MIN_CORRELATION`` and ``Z_SCORE`` standard errors of white innovations' above 0."""
    return (math.isfinite(corr) and corr >= MIN_CORRELATION
            and corr * math.sqrt(pairs) >= Z_SCORE)
