"""Ground-truth samples no robot can produce, left out of the scores.

A motion-capture or simulator truth can carry samples that are artefacts of how it was recorded
or resampled rather than poses: a truth resampled onto a grid with its yaw interpolated across
+-pi the long way round (UTIAS MRCLAM's) has the robot spin a full turn between two samples.
Scored against such a sample, every estimator's heading is wrong by up to 180 deg there, and
one sample can outweigh thousands in a mean NEES.

``impossible_samples(t, pose, speed_limit, yaw_rate_limit)`` marks them. A step between two
truth samples is impossible when the heading turns by more than the robot's top yaw rate times
the step plus ``YAW_SLACK`` rad, or the position moves by more than the top speed times the step
plus ``POS_SLACK`` m. The samples of an excursion, the truth leaving its path at one impossible
step and coming back at a later one (within ``MAX_EXCURSION_S``) to where the robot could be,
are left out: the one shape that says which samples are wrong. An impossible step with no return
(a truth that jumps and stays) is kept and counted, since either side of it could be the wrong
one. A truth without heading (a NavSatFix, yaw NaN) is not screened: its position noise is not
known here.

``TruthScreen`` holds the verdict of one truth topic and its warning line; the bag stream
(``ddfuse.estimation.bags``) applies it when the bag is read to its end. Design and measured
figures: docs/design/plausibility.md ("Ground truth").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MAX_EXCURSION_S", "POS_SLACK", "YAW_SLACK", "TruthScreen", "impossible_samples",
           "screen_truth"]

# Allowances over the robot's limits for the truth's own noise and stamp jitter: a mocap's
# heading noise is milliradians, a resampled truth's a few; a glitch is a full turn.
YAW_SLACK = 0.05  # rad per step
POS_SLACK = 0.05  # m per step
# the longest excursion of the truth that is left out; a truth away longer is kept and its
# steps counted (a mocap that lost the robot for seconds is a gap, not a glitch)
MAX_EXCURSION_S = 2.0


def _moves(t0, t1, p0, p1):
    """(dt s, |turn| rad, distance m) from pose ``p0`` at ``t0`` to ``p1`` at ``t1`` (arrays
    broadcast: (..., 3) poses, (...) stamps)."""
    dyaw = np.abs((p1[..., 2] - p0[..., 2] + np.pi) % (2.0 * np.pi) - np.pi)
    return np.abs(t1 - t0), dyaw, np.hypot(p1[..., 0] - p0[..., 0], p1[..., 1] - p0[..., 1])


def _impossible(t0, t1, p0, p1, speed_limit: float, yaw_rate_limit: float):
    """Whether moving from pose ``p0`` at ``t0`` to ``p1`` at ``t1`` needs more than the
    robot can do (``_moves``' broadcasting)."""
    dt, dyaw, dxy = _moves(t0, t1, p0, p1)
    return (dyaw > yaw_rate_limit * dt + YAW_SLACK) | (dxy > speed_limit * dt + POS_SLACK)


def impossible_samples(t: np.ndarray, pose: np.ndarray, speed_limit: float,
                       yaw_rate_limit: float) -> tuple[np.ndarray, int]:
    """The truth samples to leave out, (N,) bool, and the number of impossible steps not
    resolved so (a lone jump). ``t`` (N,) s in stamp order, ``pose`` (N, 3) (x m, y m, yaw
    rad); a truth with any NaN yaw, or fewer than 3 samples, gives no samples.

    An excursion leaves at an impossible step k -> k + 1 and returns at the first later
    impossible step j -> j + 1, within ``MAX_EXCURSION_S``, where the robot could have gone from
    sample k to sample j + 1 and the step out of j + 1 is possible: samples k + 1 .. j are left
    out."""
    n = len(t)
    out = np.zeros(n, bool)
    if n < 3 or not np.isfinite(pose[:, 2]).all():
        return out, 0
    bad = np.flatnonzero(_impossible(t[:-1], t[1:], pose[:-1], pose[1:], speed_limit,
                                     yaw_rate_limit))
    unresolved, a = 0, 0
    while a < len(bad):
        k = bad[a]
        later = bad[a + 1:]
        later = later[t[later] - t[k] <= MAX_EXCURSION_S]
        back = later[~_impossible(t[k], t[later + 1], pose[k], pose[later + 1], speed_limit,
                                  yaw_rate_limit)] if len(later) else later
        if len(back):
            # the first return after which the truth goes on possibly: a return to a sample
            # that itself leaves at once (reachable from k under a generous limit) is part of
            # the excursion
            settled = back[~np.isin(back + 1, bad)]
            j = settled[0] if len(settled) else back[0]
            out[k + 1:j + 1] = True
            a = int(np.searchsorted(bad, j)) + 1
        else:
            unresolved += 1
            a += 1
    return out, unresolved


@dataclass(frozen=True)
class TruthScreen:
    """What ``screen_truth`` found in one truth topic: the samples left out (``dropped``), the
    stretches they form, the fastest turn (rad/s) and motion (m/s) their steps imply, the first
    one's stamp (s), and the impossible steps left in (``unresolved``)."""

    topic: str
    samples: int
    dropped: int
    stretches: int
    max_yaw_rate: float
    max_speed: float
    first_t: float | None
    unresolved: int
    speed_limit: float
    yaw_rate_limit: float

    def warning(self, t0: float) -> str | None:
        """One line for the run's warnings, times from ``t0`` (s); None when nothing was
        found."""
        if not self.dropped and not self.unresolved:
            return None
        parts = []
        if self.dropped:
            over = []
            if self.max_yaw_rate > self.yaw_rate_limit:
                over.append(f"turns at up to {self.max_yaw_rate:.0f} rad/s against "
                            f"robot.max_yaw_rate {self.yaw_rate_limit:g}")
            if self.max_speed > self.speed_limit:
                over.append(f"moves at up to {self.max_speed:.1f} m/s against robot.max_speed "
                            f"{self.speed_limit:g}")
            parts.append(
                f"{self.dropped} of {self.samples} ground-truth samples in {self.stretches} "
                f"stretch(es) left out of the scores (first at t={self.first_t - t0:.2f} s): "
                f"the truth leaves its path and returns, and {' and '.join(over)}")
        if self.unresolved:
            parts.append(f"{self.unresolved} step(s) of the truth beyond those limits kept (a "
                         f"jump that stays: which side is wrong cannot be told)")
        return f"{self.topic}: " + "; ".join(parts)


def screen_truth(topic: str, t: np.ndarray, pose: np.ndarray, speed_limit: float,
                 yaw_rate_limit: float) -> tuple[np.ndarray, TruthScreen]:
    """``impossible_samples`` of one truth topic: the mask of the samples to keep (N,) and
    what was found."""
    drop, unresolved = impossible_samples(t, pose, speed_limit, yaw_rate_limit)
    stretches = int(np.count_nonzero(np.diff(np.r_[0, drop.astype(np.int8)]) == 1))
    max_w = max_v = 0.0
    if drop.any():
        k = np.flatnonzero(drop[:-1] | drop[1:])  # the steps into, within and out of them
        dt, dyaw, dxy = _moves(t[k], t[k + 1], pose[k], pose[k + 1])
        dt = np.maximum(dt, 1e-9)
        max_w, max_v = float((dyaw / dt).max()), float((dxy / dt).max())
    first = float(t[np.argmax(drop)]) if drop.any() else None
    return ~drop, TruthScreen(topic, len(t), int(drop.sum()), stretches, max_w, max_v, first,
                              unresolved, speed_limit, yaw_rate_limit)
