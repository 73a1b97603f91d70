"""A watch on GPS against the odometry: a sustained disagreement is reported while it lasts.

``GpsWatch(cfg)`` is fed every measurement in stamp order (``feed(m, accepted)``, by the bag
stream and the live converter, beside ``ddfuse.estimation.robot_limits``), whatever the estimators
then make of it. It dead-reckons the robot from the accepted twist samples (forward speed from
the first odometry sensor that uses ``v`` or the first wheel-speed sensor, yaw rate from the
first gyro, else from that odometry) in a frame of its own, and compares each GPS fix with the
newest agreeing fix at least ``WINDOW_S`` before it: the distance between the two fixes and the
dead-reckoned distance over the same interval must agree within
``K_SIGMA`` sqrt(s_1^2 + s_2^2) + ``REL`` * (dead-reckoned path length) + ``ABS_M``
(s: each fix's larger horizontal standard deviation, m). Only lengths are compared: they need no
heading, so the watch needs no estimate and is the same for every estimator.

A fix that does not agree is flagged; it never becomes a reference, so during a held jump the
reference stays the last fix before it. ``MIN_FIXES`` consecutive flagged fixes make an episode,
which ends at the last flagged fix before an agreeing one (or at the end of the input):
``episodes`` lists them (topic, start and end stamp s, fixes, largest disagreement m) and
``warnings()`` says each in one line, and a topic with many under a gating GPS model once more,
with the robust model for them. Without a GPS or a speed source the watch is off.
Design and figures: docs/design/plausibility.md.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass

from ddfuse.estimation.config import Config
from ddfuse.estimation.gaps import is_gap
from ddfuse.estimation.measurements import GpsFix
from ddfuse.estimation.twist_track import TwistTrack

__all__ = ["ABS_M", "K_SIGMA", "MANY_EPISODES", "MIN_FIXES", "REL", "ROBUST_ADVICE", "ROBUST_MODEL",
           "WINDOW_S", "Episode", "GpsWatch"]

log = logging.getLogger(__name__)

WINDOW_S = 10.0  # s: a fix is compared with the newest agreeing fix at least this much older
K_SIGMA = 8.0  # the fixes' noise allowance, in their standard deviations (see the design note)
REL = 0.1  # the dead reckoning's allowance per metre travelled (scale and heading errors)
ABS_M = 1.0  # m: and a fixed part (lever arm, the GPS delay's motion)
MIN_FIXES = 3  # consecutive flagged fixes that make an episode
# episodes of one topic that make it a GPS of bursts (multipath, NLOS) rather than of a rare
# fault, where the config's model gates each fix: the summary line suggests a robust model
MANY_EPISODES = 3
# the robust model said for such a GPS, in the config and on the command line
ROBUST_MODEL = "dcs"
ROBUST_ADVICE = (f"gps: {{model: {ROBUST_MODEL}}} in the config, or "
                 f"ddfuse run --gps-model {ROBUST_MODEL}")


@dataclass
class Episode:
    """A sustained disagreement of one GPS topic with the dead reckoning: stamps s, fixes
    flagged, the largest difference of the two distances (m) and its allowance then (m)."""

    topic: str
    start: float
    end: float
    fixes: int
    size_m: float
    allowed_m: float

    def describe(self, t0: float) -> str:
        return (f"topic {self.topic}: GPS disagreed with the odometry's dead reckoning from "
                f"t={self.start:.3f} to t={self.end:.3f} ({self.start - t0:.1f}-"
                f"{self.end - t0:.1f} s into the input, {self.fixes} fixes), by up to "
                f"{self.size_m:.1f} m where noise and drift explain {self.allowed_m:.1f} m")


@dataclass(slots=True)
class _Ref:
    t: float
    e: float
    n: float
    sd: float
    x: float  # the dead reckoning at the fix, m
    y: float
    s: float  # its path length, m


class GpsWatch:
    """The watch of one stream (module docstring)."""

    def __init__(self, cfg: Config) -> None:
        self.topic = {s.name: s.topic for s in cfg.sensors}
        self.model = cfg.gps.model if not cfg.gps.robust else None  # a gating model's name
        self.dr = TwistTrack(cfg)
        self.on = self.dr.on and bool(cfg.of_kind("gps"))
        self.episodes: list[Episode] = []
        self.t0: float | None = None
        self._refs: dict[str, deque] = {}  # sensor -> agreeing fixes (_Ref), oldest first
        self._open: dict[str, Episode] = {}  # sensor -> flagged run (an episode once long)
        self._last: float | None = None  # the last message's stamp, s

    def _restart(self) -> None:
        """After a gap (``estimation.gaps``): close what is open and dead-reckon afresh."""
        for sensor in list(self._open):
            self._close(sensor)
        self._refs.clear()
        self.dr.restart()

    def feed(self, m, accepted: bool = True) -> None:
        """Take measurement ``m`` (stamp order); ``accepted``: whether the plausibility screen
        passed it (a rejected twist sample does not move the dead reckoning)."""
        if not self.on:
            return
        if self.t0 is None:
            self.t0 = m.t
        if self._last is not None and is_gap(m.t - self._last):
            self._restart()  # the odometry says nothing about a gap: its dead reckoning ends
        self._last = m.t
        typ = type(m)
        if typ is GpsFix:
            if m.enu is not None:
                self._fix(m)
            return
        if accepted:
            self.dr.feed(m)

    def finish(self) -> None:
        """At the end of the input: close the open episodes."""
        for sensor in list(self._open):
            self._close(sensor)

    def bursty(self, topic: str) -> bool:
        """Whether GPS ``topic`` disagreed with the odometry in ``MANY_EPISODES`` or more
        episodes: fixes whose errors come and go in bursts."""
        return topic in self.bursts()

    def bursts(self) -> dict[str, list[Episode]]:
        """Per GPS topic with ``MANY_EPISODES`` or more episodes, its episodes in order."""
        by_topic: dict[str, list[Episode]] = {}
        for e in self.episodes:
            by_topic.setdefault(e.topic, []).append(e)
        return {t: eps for t, eps in by_topic.items() if len(eps) >= MANY_EPISODES}

    def warnings(self) -> list[str]:
        """One line per episode (``Episode.describe``); where a topic has ``MANY_EPISODES`` or
        more and the config's GPS model gates each fix, one more: what they look like and the
        model for them."""
        t0 = self.t0 if self.t0 is not None else 0.0
        out = [e.describe(t0) for e in self.episodes]
        if self.model is None:
            return out
        for topic, eps in self.bursts().items():
            out.append(
                f"topic {topic}: GPS disagreed with the odometry {len(eps)} times "
                f"({sum(e.fixes for e in eps)} fixes, up to "
                f"{max(e.size_m for e in eps):.0f} m): errors that come and go in bursts, "
                "as multipath and non-line-of-sight fixes in a city give; gps.model "
                f"'{self.model}' gates each fix and can follow a burst: a robust model "
                f"({ROBUST_ADVICE}) weighs them in the smoother, the batch and the EKFs "
                "(docs/design/urban_gps.md)")
        return out

    # --- inside ----------------------------------------------------------------------------
    def _fix(self, m: GpsFix) -> None:
        dr = self.dr
        if dr.t is None:
            return  # no dead reckoning yet
        dr.advance(m.t)
        c = m.cov
        now = _Ref(m.t, m.enu[0], m.enu[1], math.sqrt(max(c[0, 0], c[1, 1], 0.0)),
                   dr.x, dr.y, dr.s)
        refs = self._refs.setdefault(m.sensor, deque())
        ref = None
        while len(refs) >= 2 and refs[1].t <= m.t - WINDOW_S:
            refs.popleft()  # the newest one at least WINDOW_S old is refs[0]
        if refs and refs[0].t <= m.t - WINDOW_S:
            ref = refs[0]
        if ref is None:
            refs.append(now)
            return
        d_gps = math.hypot(now.e - ref.e, now.n - ref.n)
        d_dr = math.hypot(now.x - ref.x, now.y - ref.y)
        allowed = K_SIGMA * math.hypot(now.sd, ref.sd) + REL * (now.s - ref.s) + ABS_M
        size = abs(d_gps - d_dr)
        m.odometry_agrees = size <= allowed
        if size <= allowed:
            refs.append(now)
            if m.sensor in self._open:
                self._close(m.sensor)
            return
        ep = self._open.get(m.sensor)
        if ep is None:
            ep = self._open[m.sensor] = Episode(self.topic.get(m.sensor, m.sensor), m.t, m.t,
                                                0, 0.0, 0.0)
        ep.end, ep.fixes = m.t, ep.fixes + 1
        if size > ep.size_m:
            ep.size_m, ep.allowed_m = size, allowed
        if ep.fixes == MIN_FIXES:
            log.warning("%s: GPS disagrees with the odometry's dead reckoning since t=%.3f "
                        "(by %.1f m where noise and drift explain %.1f m)", ep.topic, ep.start,
                        ep.size_m, ep.allowed_m)

    def _close(self, sensor: str) -> None:
        ep = self._open.pop(sensor)
        if ep.fixes >= MIN_FIXES:
            self.episodes.append(ep)
            log.warning("%s", ep.describe(self.t0 if self.t0 is not None else 0.0))
