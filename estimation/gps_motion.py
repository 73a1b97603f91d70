"""Whether two GPS fixes agree with the motion the odometry dead-reckoned between them: the
plausibility screen's odometry-aided test (``ddfuse.estimation.robot_limits``).

``MotionCheck(cfg)`` dead-reckons from the twist samples the screen passes
(``ddfuse.estimation.twist_track``: its own frame, no estimate) and learns the rotation from
that frame to local ENU from pairs of accepted fixes (``accepted``): per pair whose
dead-reckoned chord makes the fixes' noise worth at most ``PAIR_SD`` of angle, the angle
between the GPS displacement and the dead-reckoned one; the rotation is the circular median of
the last ``PAIRS`` such angles (pairs restart at a re-anchor, ``forget``). With it, fix b is
predicted from fix a as p_a + R (DR_b - DR_a), and ``fits(a, b)`` is whether b lies within

    K sqrt(s_a^2 + s_b^2) + path (HEADING_ERR + YAW_DRIFT age + SCALE_ERR) + ABS_M     (m)

of that prediction (s: each fix's larger horizontal standard deviation, m; path: the
dead-reckoned path length between a and b, m; age: the longer of a's and b's times from the
rotation's newest pair, s): the fixes' noise part and the dead reckoning's part. The latter
grows with the distance driven and the time since the rotation was learnt, so after a long
rejected run it is as lax as the top speed's reach. ``vouches(a, b)``: b fits and the dead
reckoning's part is within the noise part. Both are None / False when it cannot tell: no speed
source, a fix without dead reckoning (before the first twist sample, or of another epoch: the
dead reckoning restarts after a gap in the feed), or no rotation yet (fewer than ``MIN_PAIRS``
pairs). Design and figures: docs/design/plausibility.md.
"""

from __future__ import annotations

import math
from collections import deque

from ddfuse.estimation.config import Config
from ddfuse.estimation.gaps import is_gap
from ddfuse.estimation.twist_track import TwistTrack

__all__ = ["ABS_M", "HEADING_ERR", "MIN_PAIRS", "PAIR_SD", "PAIRS", "SCALE_ERR", "YAW_DRIFT",
           "MotionCheck"]

PAIR_SD = 0.05  # rad: a pair's angle sigma from the fixes' noise, sqrt(s_a^2 + s_b^2) / chord
PAIRS = 9  # the rotation is the circular median of this many newest pair angles
MIN_PAIRS = 3  # pair angles needed before the rotation is used
HEADING_ERR = 0.1  # rad: the learnt rotation's error bound, 2 PAIR_SD
# rad/s: the dead-reckoned heading's drift bound: an uncalibrated MEMS gyro's bias is up to
# about 1 deg/s (the simulated urban gyro's is 0.01 rad/s)
YAW_DRIFT = 0.02
SCALE_ERR = 0.05  # the odometry's path-length error per metre (wheel radius, slip)
ABS_M = 1.0  # m: the GPS stamp's delay and the antenna's lever arm


class MotionCheck:
    """The odometry-aided test of one stream's fixes (module docstring)."""

    def __init__(self, cfg: Config, k_sigma: float) -> None:
        self.dr = TwistTrack(cfg)
        self.k = k_sigma
        self._last: float | None = None  # the last measurement's stamp, s
        # per GPS sensor: accepted fixes for pairs, oldest first; (stamp s, angle rad) of the
        # newest pairs
        self._history: dict[str, deque] = {}
        self._angles: dict[str, deque] = {}

    def tick(self, t: float) -> None:
        """Every measurement's stamp, in order: a gap in the feed restarts the dead reckoning
        (``estimation.gaps``: the held twist says nothing over it)."""
        if self._last is not None and is_gap(t - self._last):
            self.dr.restart()
            self._history.clear()
            self._angles.clear()
        self._last = t

    def state(self, t: float) -> tuple[float, float, float, int] | None:
        """The dead reckoning at stamp ``t``: (x m, y m, path m, epoch); None before it has
        started."""
        dr = self.dr
        if not dr.on or dr.t is None:
            return None
        dr.advance(t)
        return dr.x, dr.y, dr.s, dr.epoch

    def accepted(self, sensor: str, fix) -> None:
        """``fix`` (``robot_limits._Fix``) was accepted: a pair with the newest accepted fix far
        enough before it gives a rotation angle."""
        if fix.dr is None:
            return
        x, y, s, epoch = fix.dr
        hist = self._history.setdefault(sensor, deque(maxlen=120))
        if hist and hist[-1].dr[3] != epoch:
            hist.clear()
        for h in reversed(hist):
            hx, hy, _, _ = h.dr
            chord = math.hypot(x - hx, y - hy)
            if chord * PAIR_SD >= math.hypot(fix.sd, h.sd):
                a = math.atan2(fix.n - h.n, fix.e - h.e) - math.atan2(y - hy, x - hx)
                self._angles.setdefault(sensor, deque(maxlen=PAIRS)).append((fix.t, a))
                break
        if not hist or s - hist[-1].dr[2] >= 0.1 * fix.sd:
            hist.append(fix)

    def forget(self, sensor: str) -> None:
        """The screen re-anchored ``sensor``: the fixes accepted before are another side, no
        pair with them."""
        self._history.pop(sensor, None)

    def rotation(self, sensor: str) -> float | None:
        """The rotation from the dead-reckoning frame to ENU learnt from ``sensor``'s fixes,
        rad (None: not yet)."""
        angles = self._angles.get(sensor)
        if angles is None or len(angles) < MIN_PAIRS:
            return None
        ref = angles[-1][1]
        d = sorted(math.remainder(a - ref, math.tau) for _, a in angles)
        return ref + d[len(d) // 2]

    def fits(self, sensor: str, a, b) -> bool | None:
        """Whether fix ``b`` agrees with fix ``a`` moved by the dead-reckoned motion between
        them (module docstring); None: cannot tell."""
        d = self._miss(sensor, a, b)
        return None if d is None else d[0] <= d[1] + d[2]

    def tells(self, sensor: str, a, b) -> bool:
        """Whether ``fits`` can tell for fixes ``a`` and ``b``."""
        return self._miss(sensor, a, b) is not None

    def vouches(self, sensor: str, a, b) -> bool:
        """Whether the odometry vouches for fix ``b`` from fix ``a``: ``b`` fits, and the dead
        reckoning's part of the allowance is within the fixes' noise part (over the span the
        motion is known better than the fixes; after a long outage it is not)."""
        d = self._miss(sensor, a, b)
        return d is not None and d[0] <= d[1] + d[2] and d[2] <= d[1]

    def _miss(self, sensor: str, a, b) -> tuple[float, float, float] | None:
        """(distance of ``b`` from its prediction from ``a``, the fixes' noise allowance, the
        dead reckoning's allowance), m; None: cannot tell."""
        if a.dr is None or b.dr is None or a.dr[3] != b.dr[3]:
            return None
        rot = self.rotation(sensor)
        if rot is None:
            return None
        dx, dy = b.dr[0] - a.dr[0], b.dr[1] - a.dr[1]
        c, s = math.cos(rot), math.sin(rot)
        pe, pn = a.e + c * dx - s * dy, a.n + s * dx + c * dy
        t_rot = self._angles[sensor][-1][0]
        age = max(abs(a.t - t_rot), abs(b.t - t_rot))
        # a heading error e over the path moves its end by at most e times the path
        path = abs(b.dr[2] - a.dr[2])
        drift = path * (HEADING_ERR + YAW_DRIFT * age + SCALE_ERR) + ABS_M
        return math.hypot(b.e - pe, b.n - pn), self.k * math.hypot(a.sd, b.sd), drift
