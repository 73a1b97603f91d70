"""The EKFs' robust GPS model (``gps.model`` other than 'default' / 'gaussian'; design and
figures: docs/design/urban_gps.md, "The EKFs"): what a filter can do where the smoother revisits.

Per GPS sensor, :class:`EkfRobustGps` judges each fix's innovation (y (2,) m, its covariance S
(2, 2) m^2 with the stated R, and R) once, against the prediction:

* the stated R is scaled by s^2 >= 1 learned from the innovations of the fixes taken for inliers
  (``estimation.gps_scale.GpsScale``, the smoother's rule);
* the fix is fused with R s^2 / w, w the weight of the model's M-estimator
  (``kernel_weight``; 'maxmix' uses Cauchy's) at the NIS against S with the scaled R: the
  filter's analogue of an iteratively re-weighted factor; 1 / w is bounded by ``MAX_FACTOR``.
  A fix whose scaled NIS is beyond the sensor's gate is not fused at all: a filter cannot
  take a fix back, and one 50 m jump fused at weight 0.1 after an outage moved it 15 m;
* a sliding-window chi-square test: over the fixes of the last ``fault_window`` s (at least
  ``MIN_WINDOW_FIXES``), the sum of their scaled NIS, each capped at the sensor's gate (one
  gross jump counts as one rejected fix, not as a hundred), beyond chi-square(2 N_eff)'s
  ``WINDOW_PROB`` quantile (scaled to the N fixes; N_eff = 1 + span / tau independent fixes
  for a sensor whose ``correlation_time`` tau is stated, else N) declares the GPS faulty: its
  fixes are not fused, the filter dead-reckons, its covariance grows, and the GPS is
  re-admitted at the first fix whose window is consistent again;
* bounded: if the window is still inconsistent ``fault_hold`` s after the GPS was declared
  faulty, the filter takes itself for lost -- P is inflated so the fix is ordinary (the gate
  lock-out's recovery, ``KalmanCore``) and the GPS followed again; the next hold doubles until
  a re-admission on a consistent window.

A fix whose scaled NIS is beyond the gate, or that comes while the GPS is faulty, is an outlier:
counted as ``(sensor, 'outlier')`` and its innovation logged not accepted (it is not fused), as
the smoother's models count theirs. The verdicts are said in the log (``notes``, which
``KalmanCore`` moves to its log).
"""

from __future__ import annotations

import math
from collections import deque

from ddfuse.estimation import chi2
from ddfuse.estimation.config import GpsModelConfig
from ddfuse.estimation.gps_scale import KERNEL_K, GpsScale, kernel_weight

__all__ = ["EkfRobustGps", "FUSE", "EXCLUDE", "RECOVER", "MAX_FACTOR", "WINDOW_PROB"]

FUSE, EXCLUDE, RECOVER = 0, 1, 2  # EkfRobustGps.judge's verdicts
MAX_FACTOR = 1.0e4  # the largest factor on R (a fix 100 sigma off still has a finite R)
WINDOW_PROB = 0.999  # the window test's chi-square quantile
MIN_WINDOW_FIXES = 3  # fewer fixes in the window: no verdict
# fixes in a row taken for inliers after which the GPS has agreed with the estimate; before
# that, a faulty window blames the start, not the GPS (the smoother's DISAGREE_FIXES)
AGREE_FIXES = 10
START_HOLD = 10.0  # s: and such a faulty stretch is the start's after this long (DISAGREE_S)


class EkfRobustGps:
    """One GPS sensor's robust model in an EKF (module docstring). ``gm``: the config's
    ``gps``; ``gate``: the sensor's chi-square acceptance probability (None: 0.9999)."""

    def __init__(self, sensor: str, gm: GpsModelConfig, gate: float | None,
                 tau: float = 0.0) -> None:
        self.sensor = sensor
        self.model = gm.model if gm.model in KERNEL_K else "cauchy"
        self.k = gm.k if gm.k is not None else KERNEL_K[self.model]
        self.scale = GpsScale(gm.scale_window)
        self.gate_nis = chi2.ppf(0.9999 if gate is None else gate, 2)
        self.window = float(gm.fault_window)
        self.hold = float(gm.fault_hold)
        self.tau = float(tau)
        self._hold_now = self.hold
        self._win: deque[tuple[float, float]] = deque()  # (stamp, capped scaled NIS)
        self._sum = 0.0
        self.faulty_since: float | None = None
        self._excluded = 0
        self.faults: list[tuple[float, float, int, str]] = []  # (from, to, fixes, how it ended)
        self._inliers = 0  # fixes in a row fused as inliers
        self.agreed = False  # AGREE_FIXES of them since the start
        self.notes: list[tuple[float, str]] = []  # (stamp, message) for the caller's log

    def judge(self, t: float, y, S, R) -> tuple[int, float, bool]:
        """The verdict on a fix at ``t`` s: (FUSE, EXCLUDE or RECOVER, the factor f >= 1 on its
        R in the fusion, outlier?). ``y`` (2,) m, ``S`` and ``R`` (2, 2) m^2 as nested
        sequences: the innovation, its covariance with the stated R, and R. After RECOVER the
        caller inflates P (so the fix is ordinary against ``S`` with R scaled by f; for RECOVER
        f is the learned scale alone, no kernel: the fix is followed) and fuses."""
        s2 = self.scale.factor
        a, b, d = (S[0][0] + (s2 - 1.0) * R[0][0], S[0][1] + (s2 - 1.0) * R[0][1],
                   S[1][1] + (s2 - 1.0) * R[1][1])
        det = a * d - b * b
        if not (a > 0.0 and det > 0.0):
            return EXCLUDE, 1.0, False
        nis = (d * y[0] * y[0] - 2.0 * b * y[0] * y[1] + a * y[1] * y[1]) / det
        w = kernel_weight(self.model, self.k, math.sqrt(nis))
        f = min(MAX_FACTOR, s2 / max(w, 1.0 / MAX_FACTOR))
        outlier = nis > self.gate_nis
        faulty = self._window_add(t, min(nis, self.gate_nis))
        if self.faulty_since is None:
            if faulty:
                self.faulty_since = t
                self._excluded = 1
                self.notes.append((t, (
                    f"{self.sensor}: GPS and odometry disagree: {len(self._win)} fixes over "
                    f"{self.window:.0f} s inconsistent (window chi-square {self._sum:.0f} > "
                    f"{self._limit():.0f}); following the odometry")))
                return EXCLUDE, f, True
            if outlier:  # beyond the gate: not fused (a filter cannot take it back)
                self._inliers = 0
                return EXCLUDE, f, True
            # the NIS with the stated R: the scale is learned from the inliers only
            self.scale.add(t, _nis2(y, S))
            self._inliers += 1
            self.agreed = self.agreed or self._inliers >= AGREE_FIXES
            return FUSE, f, False
        if not faulty:
            self._end(t, "consistent", (
                f"{self.sensor}: GPS agrees with the odometry again after "
                f"{t - self.faulty_since:.1f} s ({self._excluded} fixes not fused); "
                "following the GPS"))
            self._hold_now = self.hold
            return (EXCLUDE, f, True) if outlier else (FUSE, f, False)
        # no run of agreement since the start: after START_HOLD (the smoother's DISAGREE_S)
        # the start, one stated value, is taken for wrong rather than the GPS
        start = not self.agreed and t - self.faulty_since >= START_HOLD
        if start or t - self.faulty_since >= self._hold_now:
            span, n = t - self.faulty_since, self._excluded
            self._end(t, "recovered", (
                f"{self.sensor}: no fix has agreed with the estimate since the start (GPS "
                f"inconsistent for {span:.1f} s, {n} fixes not fused): the start is taken for "
                "wrong (the config's initial_pose?), not the GPS; covariance inflated; "
                "following the GPS" if start else
                f"{self.sensor}: GPS inconsistent for {span:.1f} s ({n} fixes not fused): the "
                "filter takes itself for lost, covariance inflated; following the GPS"))
            if not start:
                self._hold_now *= 2.0
            self._win.clear()
            self._sum = 0.0
            # the fix the filter now follows is fused as an inlier (R s^2): the kernel's weight
            # at its distance from the lost estimate, up to 1 / MAX_FACTOR, made the inflation
            # and the fusion a no-op (x1), the filter lost on (a wrong start, session 31)
            return RECOVER, s2, False
        self._excluded += 1
        return EXCLUDE, f, True

    def _end(self, t: float, how: str, note: str) -> None:
        self.faults.append((self.faulty_since, t, self._excluded, how))
        self.notes.append((t, note))
        self.faulty_since = None

    def _n_eff(self) -> float:
        """The window's number of independent fixes: with the sensor's correlation time tau,
        1 + span / tau (at most the fixes)."""
        n = len(self._win)
        if self.tau <= 0.0 or n < 2:
            return float(n)
        return min(float(n), 1.0 + (self._win[-1][0] - self._win[0][0]) / self.tau)

    def _limit(self) -> float:
        """The window's NIS sum beyond which it is inconsistent: chi-square(2 N_eff)'s
        WINDOW_PROB quantile, scaled from N_eff to the window's N fixes."""
        n_eff = self._n_eff()
        return chi2.ppf(WINDOW_PROB, 2.0 * n_eff) * len(self._win) / n_eff

    def _window_add(self, t: float, nis: float) -> bool:
        """Add a capped NIS at ``t``; True if the window's fixes are inconsistent."""
        win = self._win
        win.append((t, nis))
        self._sum += nis
        while win and win[0][0] < t - self.window:
            self._sum -= win.popleft()[1]
        if len(win) < MIN_WINDOW_FIXES:
            return False
        return self._sum > self._limit()


def _nis2(y, S) -> float:
    det = S[0][0] * S[1][1] - S[0][1] * S[0][1]
    return (S[1][1] * y[0] * y[0] - 2.0 * S[0][1] * y[0] * y[1] + S[0][0] * y[1] * y[1]) / det


def robust_spec(cfg) -> tuple | None:
    """What a filter keeps of ``cfg`` (a ``Config``) for :func:`robust_judges`: None unless
    ``gps.model`` is a robust one."""
    if not cfg.gps.robust:
        return None
    return cfg.gps, tuple((s.name, s.gate, float(s.correlation_time))
                          for s in cfg.of_kind("gps"))


def robust_judges(spec: tuple | None) -> dict:
    """A fresh model per GPS sensor of ``spec`` (:func:`robust_spec`), keyed as
    ``KalmanCore.robust`` wants them: (sensor, 'gps')."""
    if spec is None:
        return {}
    gm, sensors = spec
    return {(name, "gps"): EkfRobustGps(name, gm, gate, tau) for name, gate, tau in sensors}
