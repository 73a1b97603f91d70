"""Gate lock-out: when a run of gate rejections means the estimate, not the sensor, is wrong,
and how far to widen the estimate's covariance so that it can recover.

A Mahalanobis gate can lock an estimator out for good: once the estimate has drifted away (or
its covariance collapsed), every later measurement disagrees by more than the gate allows, is
rejected, and nothing widens the covariance again. The rule, shared by the EKFs
(``ekf_baseline.kalman``) and the smoother's GPS gate: at least ``count`` consecutive rejections
of one measurement model spanning at least ``time`` seconds (both, so that a burst of outliers
from a fast sensor or a single bad fix does not trigger it) mean the estimator is locked out.
If other measurements observing the same states were accepted meanwhile, they corroborate the
estimate and the sensor is the outlier: no recovery. Otherwise the estimator recovers by
inflating its covariance by the smallest factor that makes the current innovation ordinary
(:func:`inflation`). A recovery that does not take (the measurement is not accepted ``count``
times before it locks out again) makes the next one wait ``holdoff`` seconds, doubling each time.
"""

from __future__ import annotations

import math
from collections.abc import Hashable

import numpy as np
from ddfuse.estimation.config import DEFAULT_LOCKOUT_COUNT, DEFAULT_LOCKOUT_TIME

DEFAULT_RECOVERY_HOLDOFF = 10.0  # s before a second recovery of the same measurement; doubles
# acceptances in a row after which a measurement model has agreed with the estimate since the
# start (``Lockout.agreed``; the smoother's robust GPS models count their inliers here too)
AGREED_RUN = 10
MAX_INFLATION = 1e12  # largest covariance scale factor tried by a recovery


def inflation(y: np.ndarray, A: np.ndarray, R: np.ndarray) -> tuple[float, np.ndarray | None]:
    """The smallest alpha >= 1 for which innovation ``y`` (m,) is ordinary, NIS = m, against
    S = alpha A + R: ``A`` (m, m) is the state's share H P H^T, ``R`` (m, m) the measurement's.

    Returns (alpha, None), or (MAX_INFLATION, d) when no alpha up to MAX_INFLATION is enough
    (P has no variance in a measured direction): then the caller also adds the rank-one term
    d d^T, with d = H^+ y the minimum-norm state error explaining the innovation, which the
    caller forms because only it has H."""
    m = y.shape[0]

    def nis_at(alpha: float) -> float:
        return float(y @ np.linalg.solve(alpha * A + R, y))

    if nis_at(1.0) <= m:
        return 1.0, None
    if nis_at(MAX_INFLATION) > m:
        return MAX_INFLATION, y
    lo, hi = 0.0, math.log(MAX_INFLATION)  # NIS(alpha) falls monotonically: bisect on log alpha
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if nis_at(math.exp(mid)) > m:
            lo = mid
        else:
            hi = mid
    return math.exp(hi), None


def gate_streak(rejected: bool, t: float, count: int, first: float, accepted: int
                ) -> tuple[int, float, int]:
    """A measurement model's streak after one gate verdict at ``t`` (s): (consecutive
    rejections, stamp of the first of them, acceptances since the last recovery or
    corroboration verdict). A new streak is (0, t, 0). Plain floats: the EKF kernels compile
    this same function."""
    if rejected:
        if count == 0:
            first = t
        return count + 1, first, accepted
    return 0, first, accepted + 1


def lockout_due(count: int, first: float, t: float, lockout_count: int, lockout_time: float
                ) -> bool:
    """True if a streak of ``count`` rejections since ``first`` (s) means a lock-out at ``t``:
    at least ``lockout_count`` of them spanning at least ``lockout_time`` s."""
    return count >= lockout_count and t - first >= lockout_time


def holdoff_over(held: bool, until: float, accepted: int, lockout_count: int, t: float) -> bool:
    """True if a recovery of a locked-out model is allowed at ``t`` (s): no hold-off is set
    (``held``), or the last recovery took (accepted ``lockout_count`` times since; the hold-off
    is then dropped), or the hold-off ran out (``until``)."""
    return not held or accepted >= lockout_count or t >= until


class Lockout:
    """Gate rejection streaks and recovery hold-offs of an estimator's measurement models, each
    named by a hashable key (a sensor, or (sensor, kind)). Times in seconds (stamps)."""

    def __init__(self, count: int = DEFAULT_LOCKOUT_COUNT, time: float = DEFAULT_LOCKOUT_TIME,
                 holdoff: float = DEFAULT_RECOVERY_HOLDOFF) -> None:
        self.count, self.time, self.holdoff = int(count), float(time), float(holdoff)
        # key -> [consecutive rejections, stamp of the first of them, acceptances since recovery]
        self._streak: dict[Hashable, list] = {}
        # key -> (earliest stamp of the next recovery, the hold-off that set it)
        self._hold: dict[Hashable, tuple[float, float]] = {}
        self._run: dict[Hashable, int] = {}  # key -> acceptances in a row
        self._agreed: set[Hashable] = set()  # keys with AGREED_RUN of them at some time

    def accepted(self, key: Hashable) -> None:
        """The measurement passed the gate: its streak ends."""
        s = self._streak.get(key)
        if s is not None:
            s[:] = gate_streak(False, math.nan, *s)
        n = self._run[key] = self._run.get(key, 0) + 1
        if n == AGREED_RUN:
            self._agreed.add(key)

    def disagreed(self, key: Hashable) -> None:
        """The measurement was not taken, with no gate to judge it (a robust model's outlier):
        its run of acceptances ends, its streak is left alone."""
        self._run[key] = 0

    def agreed(self, key: Hashable) -> bool:
        """Whether ``key`` was ever accepted AGREED_RUN times in a row: without that, a
        lock-out from the start is the stated start's fault, not a lost estimate's."""
        return key in self._agreed

    def rejected(self, key: Hashable, t: float) -> bool:
        """The measurement at ``t`` failed the gate. True if that locks the estimator out and a
        recovery is allowed now (the caller then checks corroboration, and recovers or calls
        :meth:`corroborated`); False for a plain rejection."""
        s = self._streak.setdefault(key, [0, t, 0])
        s[:] = gate_streak(True, t, *s)
        self.disagreed(key)
        if not lockout_due(s[0], s[1], t, self.count, self.time):
            return False
        ho = self._hold.get(key)
        if ho is not None and s[2] >= self.count:  # the last recovery took: a new lock-out
            del self._hold[key]
        return holdoff_over(ho is not None, ho[0] if ho else 0.0, s[2], self.count, t)

    def streak(self, key: Hashable) -> tuple[int, float]:
        """(consecutive rejections, stamp of the first) of ``key``."""
        s = self._streak.get(key, (0, math.nan))
        return s[0], s[1]

    def _hold_off(self, key: Hashable, t: float) -> float:
        """The next recovery of ``key`` waits (doubling); acceptances count from now."""
        wait = self._hold.get(key, (0.0, self.holdoff / 2.0))[1] * 2.0
        self._hold[key] = (t + wait, wait)
        self._streak[key][2] = 0
        return wait

    def recovered(self, key: Hashable, t: float) -> float:
        """The estimator recovered on ``key`` at ``t``: the streak restarts and the next recovery
        waits; returns that wait (s)."""
        wait = self._hold_off(key, t)
        self._streak[key][0] = 0
        return wait

    def corroborated(self, key: Hashable, t: float) -> float:
        """Other accepted measurements vouch for the estimate: no recovery; the rejections go on
        and the question is asked again after the returned wait (s)."""
        return self._hold_off(key, t)
