"""A gap in the feed, and what an estimator knows after it: the rule every estimator uses.

A gap is a stretch of more than ``GAP_S`` seconds with no message of any kind (a driver
restart, a dropped link, a bag recorded in pieces). Shorter silences are predicted over by each
estimator's own motion model. Over a longer one the held twist says nothing (the robot may have
stopped, turned or been carried), and a prediction with it put the outputs hundreds of metres
off with a covariance that either missed the truth or grew without bound (the unicycle EKF's
twist walk: 53 km of position sigma after 300 s). So after a gap an estimator restarts from what
it knows: the last pose, its covariance grown by what the robot could have done in the gap
(``grown_pose_cov``: the robot's top speed and top yaw rate, ``cfg.robot.speed_limit`` m/s and
``cfg.robot.yaw_rate_limit`` rad/s), and the next absolute measurement (a GPS fix, a heading)
from there. Design notes and measured figures: docs/design/gaps.md.
"""

from __future__ import annotations

import math

import numpy as np
from ddfuse.estimation.config import RobotConfig

# s without any message: a gap in the feed. Every clean bag shipped or tested has at most
# 0.1 s between messages; a robot's own drivers publish at 5-100 Hz.
GAP_S = 10.0
# rad: the heading sigma at which it is unknown (a heading uniform on the circle has sigma
# pi / sqrt(3) = 1.81 rad); a gap long enough to turn around grows it to this and no further
HEADING_UNKNOWN_SIGMA = math.pi / math.sqrt(3.0)


def is_gap(dt: float) -> bool:
    """True if ``dt`` seconds without any message is a gap in the feed (more than GAP_S)."""
    return dt > GAP_S


def gap_growth(gap: float, robot: RobotConfig) -> tuple[float, float]:
    """What a gap of ``gap`` s can do to the pose: (position sigma m, heading sigma rad) added
    to the last pose's, from the robot's top speed (it is within speed_limit * gap of where it
    was, in any direction) and top yaw rate (yaw_rate_limit * gap, capped at
    HEADING_UNKNOWN_SIGMA)."""
    return (robot.speed_limit * gap, min(robot.yaw_rate_limit * gap, HEADING_UNKNOWN_SIGMA))


def grown_pose_cov(cov: np.ndarray, gap: float, robot: RobotConfig) -> np.ndarray:
    """The 3x3 pose covariance (x m, y m, psi rad; world frame, or any frame whose position
    axes are rotated by the heading: the growth is isotropic) after a gap of ``gap`` s: ``cov``
    plus ``gap_growth``'s variances on the diagonal, the heading's total variance capped at
    HEADING_UNKNOWN_SIGMA squared (and its cross terms scaled down with it)."""
    d, h = gap_growth(gap, robot)
    out = np.array(cov, dtype=float)[:3, :3].copy()
    out[0, 0] += d * d
    out[1, 1] += d * d
    var_psi = out[2, 2] + h * h
    cap = HEADING_UNKNOWN_SIGMA ** 2
    if var_psi > cap:
        s = math.sqrt(cap / var_psi)
        out[2, :2] *= s
        out[:2, 2] *= s
        var_psi = cap
    out[2, 2] = var_psi
    return out


def gap_note(who: str, gap: float, cov: np.ndarray) -> str:
    """The log line of a restart after a gap: who, how long, the sigmas it restarts with."""
    return (f"{who}: no message for {gap:.1f} s (a gap in the feed, over {GAP_S:g} s): restarted "
            f"from the last pose, position sigma {math.sqrt(max(cov[0, 0], cov[1, 1])):.1f} m, "
            f"heading sigma {math.sqrt(cov[2, 2]):.2f} rad (docs/design/gaps.md)")


def gap_warning(source: str, gaps: list[tuple[float, float]], t0: float | None) -> str:
    """One line for the gaps of an input (``source``, e.g. the bag's path): each (last stamp
    before, first stamp after), s; times said from ``t0`` (the input's first stamp)."""
    t0 = gaps[0][0] if t0 is None else t0
    said = ", ".join(f"{b - a:.1f} s from {a - t0:.1f} s" for a, b in gaps[:3])
    more = f" and {len(gaps) - 3} more" if len(gaps) > 3 else ""
    return (f"{source}: {len(gaps)} gap(s) with no message on any sensor topic for more than "
            f"{GAP_S:g} s ({said}{more} into the input): every estimator restarts after it "
            "from its last pose, the covariance grown by the robot's limits (robot.max_speed, "
            "max_yaw_rate), or from the next GPS fix")
