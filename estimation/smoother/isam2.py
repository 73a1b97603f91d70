"""ISAM2 settings of the fixed-lag smoother (design study, section 4; the figures behind the
thresholds: docs/design/smoother.md, ISAM2 parameters)."""

from __future__ import annotations

import gtsam
import numpy as np

# Relinearisation thresholds per state component (m, m, rad, m/s, rad/s, rad/s, rad, 1, 1).
# Positions and v enter every factor linearly, so their linearisation point hardly matters; the
# heading enters through sin and cos, so it keeps a tight 0.05 rad (3 deg).
RELINEARIZE = (1.0, 1.0, 0.05, 1.0, 0.1, 0.01, 0.05, 0.01, 0.01)
# Updates between relinearisation checks (gtsam's default); with 1 each preintegrated factor
# (a Python callback) was relinearised several times in its window.
RELINEARIZE_SKIP = 10
# Under a strongly redescending GPS model (a far fix's weight falling as ~1/r^4) the fixes'
# weights are read at the linearisation point, so it is checked at every update: a weight
# ten updates stale held a wrong side after an outage (docs/results/urban.md, session 28).
# Cauchy's tail (~1/r^2) lets a long burst in once re-weighted that often, so it keeps the
# default.
REDESCENDING_GPS = frozenset({"dcs", "geman_mcclure"})
RELINEARIZE_SKIP_REDESCENDING = 1


def threshold_map() -> gtsam.ISAM2ThresholdMap:
    tm = gtsam.ISAM2ThresholdMap()
    tm.insert(("x", np.array(RELINEARIZE)))
    return tm


def relinearize_skip(gps_model: str) -> int:
    """Updates between ISAM2's relinearisation checks under the config's ``gps.model``."""
    return RELINEARIZE_SKIP_REDESCENDING if gps_model in REDESCENDING_GPS else RELINEARIZE_SKIP


def isam2_params(skip: int = RELINEARIZE_SKIP) -> gtsam.ISAM2Params:
    """ISAM2 settings from the design study: per-component relinearisation thresholds (the
    scalar mixes m, rad and m/s), a check every ``skip`` updates (``relinearize_skip``),
    Cholesky, cached linear factors, and findUnusedFactorSlots, which a hand-made ISAM2Params
    leaves off (factor slots would grow)."""
    p = gtsam.ISAM2Params()
    p.setRelinearizeThreshold(threshold_map())
    p.relinearizeSkip = skip
    p.cacheLinearizedFactors = True
    p.findUnusedFactorSlots = True
    p.evaluateNonlinearError = False
    p.enableDetailedResults = False
    p.setFactorization("CHOLESKY")
    return p

