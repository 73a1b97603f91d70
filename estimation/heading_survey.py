"""A compass's heading offset measured from the data, and what it says about the config.

A compass (an IMU's orientation yaw, a magnetometer) reports sensor yaw = ENU yaw + offset. The
offset can be declination, a mounting error, or a magnetometer disturbed along the way; a config
states it (``heading_offset``: a number, or ``estimate`` with a ``heading_offset_walk``). A wrong
fixed value makes every estimator fight its GPS, and an offset that wanders needs a walk.

The survey measures it without any estimator: per window of ``WINDOW_S`` seconds, dead reckoning
along the compass's own yaw at the odometry's speed is a copy of the path rotated by minus the
offset, so the least-squares rotation (Kabsch) that maps it onto the GPS fixes of the window is
the offset. The odometry's scale errors change only the copy's size, not its rotation; the fit
is refitted once without the fixes whose residual is far above the median (outliers).

``OffsetRecorder`` takes the measurements one at a time (a run's stream is never held whole)
and keeps one pair of points per GPS fix; ``surveys()`` fits the windows. ``config_warnings``
compares the result with what the config states.
"""

from __future__ import annotations

import math
from array import array
from dataclasses import dataclass

import numpy as np
from ddfuse.estimation.measurements import GpsFix, Heading, WheelOdometry, WheelSpeeds

WINDOW_S = 30.0  # s: long enough to average 1 m GPS noise to under a degree at walking speed
MIN_FIXES = 5
MIN_EXTENT_M = 3.0  # RMS distance of a window's dead-reckoned points from their mean
# a fix whose residual is this many median residuals (and > 1 m) is left out (for Gaussian
# noise the median is 1.18 sigma: 5.9 sigma, never a good fix)
OUTLIER_FACTOR = 5.0
MISMATCH_RAD = 0.1  # a fixed offset this far from the measured one gets a warning (5.7 deg)
DRIFT_RAD = 0.1  # windows this far apart (max - min) may mean the offset wanders,
# if they change slowly rather than scatter: the von Neumann ratio of the windows' offsets (mean
# squared successive difference over variance) is about 2 for independent scatter and small for
# a slow change; the fits' own sigmas cannot tell (figures: docs/design/heading_survey.md)
WANDER_RATIO = 1.0
MIN_WANDER_WINDOWS = 4


def _wrap(a):
    return (a + np.pi) % (2.0 * np.pi) - np.pi


@dataclass(frozen=True)
class OffsetWindow:
    """One window's fit. Times in seconds of the stream's clock (header stamps)."""

    t0: float  # s, first fix of the window
    t1: float  # s, last fix
    offset: float  # rad, sensor yaw minus ENU yaw, wrapped to [-pi, pi)
    sigma: float  # rad, the fit's standard error for white GPS noise (correlated: larger)
    fixes: int  # fixes in the fit (outliers left out)
    extent_m: float  # m, RMS distance of the dead-reckoned points from their mean
    residual_m: float  # m, RMS distance of the fixes from the fitted copy


@dataclass(frozen=True)
class OffsetSurvey:
    """The windows of one compass sensor, in time order (at least one)."""

    sensor: str
    windows: tuple[OffsetWindow, ...]

    def _deviations(self) -> tuple[float, np.ndarray]:
        off = np.array([w.offset for w in self.windows])
        centre = math.atan2(float(np.sin(off).sum()), float(np.cos(off).sum()))
        return centre, _wrap(off - centre)

    @property
    def median(self) -> float:
        """rad, the median of the windows' offsets (taken around their circular mean)."""
        centre, dev = self._deviations()
        return float(_wrap(centre + np.median(dev)))

    @property
    def spread(self) -> float:
        """rad, the largest minus the smallest window offset (0 with one window)."""
        _, dev = self._deviations()
        return float(dev.max() - dev.min())

    @property
    def duration(self) -> float:
        """s, from the first window's first fix to the last window's last fix."""
        return self.windows[-1].t1 - self.windows[0].t0

    @property
    def successive_ratio(self) -> float | None:
        """The von Neumann ratio of the windows' offsets in time order (mean squared
        successive difference over their variance): ~2 for independent scatter, small for a
        slow change; None with fewer than two windows or no spread."""
        _, dev = self._deviations()
        if len(dev) < 2 or float(dev.var()) == 0.0:
            return None
        return float(np.mean(np.diff(dev) ** 2) / dev.var())

    @property
    def wanders(self) -> bool:
        """Whether the offset changes over the run: the windows spread by more than DRIFT_RAD,
        and change slowly rather than scatter (``successive_ratio`` < WANDER_RATIO, over at
        least MIN_WANDER_WINDOWS windows)."""
        r = self.successive_ratio
        return (len(self.windows) >= MIN_WANDER_WINDOWS and self.spread > DRIFT_RAD
                and r is not None and r < WANDER_RATIO)

    def walk(self) -> float:
        """rad/sqrt(s), the random-walk density whose 1-sigma over the surveyed time is the
        windows' spread: a heading_offset_walk that lets an estimator follow the offset."""
        return self.spread / math.sqrt(max(self.duration, 1.0))

    def describe(self) -> str:
        """One line: the median, the spread and the windows' offsets in degrees."""
        offs = " ".join(f"{math.degrees(w.offset):+.1f}" for w in self.windows)
        sig = float(np.median([w.sigma for w in self.windows]))
        r = self.successive_ratio
        ratio = "" if r is None else (f", successive ratio {r:.2f} (about 2 for scatter, small "
                                      "for a slow change)")
        return (f"yaw minus GPS course (the heading offset) {math.degrees(self.median):+.1f} deg "
                f"(median of {len(self.windows)} windows of {WINDOW_S:.0f} s; fit sigma "
                f"{math.degrees(sig):.1f} deg for white GPS), spread "
                f"{math.degrees(self.spread):.1f} deg{ratio}; per window: {offs}")

    def to_dict(self) -> dict:
        return {"sensor": self.sensor, "median_rad": self.median, "spread_rad": self.spread,
                "window_s": WINDOW_S,
                "windows": [{"t0": w.t0, "t1": w.t1, "offset_rad": w.offset, "sigma_rad": w.sigma,
                             "fixes": w.fixes, "extent_m": w.extent_m,
                             "residual_m": w.residual_m} for w in self.windows]}


def rotation_fit(a: np.ndarray, b: np.ndarray) -> tuple[float, np.ndarray]:
    """The angle (rad) of the rotation R that best maps the centred points a (n, 2) onto the
    centred b (n, 2) in least squares (2-D Kabsch), and the residuals b - R a, (n, 2)."""
    th = math.atan2(float((a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum()), float((a * b).sum()))
    c, s = math.cos(th), math.sin(th)
    return th, b - a @ np.array([[c, s], [-s, c]])


def fit_window(t: np.ndarray, dr: np.ndarray, fix: np.ndarray) -> OffsetWindow | None:
    """The offset over one window: ``dr`` (n, 2) dead reckoning along the compass yaw (m, in the
    compass's frame) and ``fix`` (n, 2) the GPS positions (m, ENU) at times ``t`` (n,) s. None
    when the window has too few fixes or the robot did not move enough to fix a rotation."""
    keep = np.ones(len(t), bool)
    for refit in (False, True):
        if keep.sum() < MIN_FIXES:
            return None
        a = dr[keep] - dr[keep].mean(axis=0)
        b = fix[keep] - fix[keep].mean(axis=0)
        saa = float((a * a).sum())
        if saa < MIN_EXTENT_M ** 2 * len(a):
            return None
        th, res = rotation_fit(a, b)
        r = np.hypot(res[:, 0], res[:, 1])
        out = r > max(OUTLIER_FACTOR * float(np.median(r)), 1.0)
        if refit or not out.any():
            break
        keep[np.flatnonzero(keep)[out]] = False
    rms = math.sqrt(float((r * r).mean()))
    # per-axis residual sigma over the lever of the points about their mean
    sigma = rms / math.sqrt(2.0) / math.sqrt(saa)
    return OffsetWindow(float(t[keep][0]), float(t[keep][-1]), float(_wrap(-th)), sigma,
                        int(keep.sum()), math.sqrt(saa / len(a)), rms)


class _DeadReckoning:
    """Dead reckoning along one compass's yaw; one (dead-reckoned, GPS) pair per fix."""

    __slots__ = ("x", "y", "yaw", "t", "pair_t", "pairs")

    def __init__(self) -> None:
        self.x = self.y = 0.0
        self.yaw: float | None = None
        self.t: float | None = None
        self.pair_t = array("d")
        self.pairs = array("d")  # dr x, dr y, fix east, fix north per fix

    def advance(self, t: float, v: float | None) -> None:
        if self.t is not None and v is not None and self.yaw is not None and t > self.t:
            dt = t - self.t
            self.x += v * math.cos(self.yaw) * dt
            self.y += v * math.sin(self.yaw) * dt
        self.t = t if self.t is None else max(self.t, t)


class OffsetRecorder:
    """Collects what the survey needs from a stream, one measurement at a time (``add``).

    ``wheel_geometry`` (wheel radius m, track width m) turns wheel speeds into a body speed;
    ``gps_delay`` maps a GPS sensor name to its delay (s: a fix is the position that long
    before its stamp). Memory: one pair of points per GPS fix and compass."""

    def __init__(self, wheel_geometry: tuple[float, float] | None = None,
                 gps_delay: dict[str, float] | None = None) -> None:
        self.geometry = wheel_geometry
        self.gps_delay = gps_delay or {}
        self.v: float | None = None
        self.compasses: dict[str, _DeadReckoning] = {}

    def add(self, m) -> None:
        if isinstance(m, Heading):
            dr = self.compasses.get(m.sensor)
            if dr is None:
                dr = self.compasses[m.sensor] = _DeadReckoning()
            dr.advance(m.t, self.v)
            dr.yaw = m.yaw
        elif isinstance(m, WheelOdometry):
            if m.v is not None:
                self._speed(m.t, m.v)
        elif isinstance(m, WheelSpeeds):
            if self.geometry is not None:
                self._speed(m.t, m.twist(*self.geometry)[0])
        elif isinstance(m, GpsFix) and m.enu is not None:
            delay = self.gps_delay.get(m.sensor, 0.0)
            for dr in self.compasses.values():
                dr.advance(m.t, self.v)
                if dr.yaw is None or self.v is None:
                    continue
                # the fix is the position ``delay`` before its stamp: step back along the yaw
                back = self.v * delay
                dr.pair_t.append(m.t - delay)
                dr.pairs.extend((dr.x - back * math.cos(dr.yaw), dr.y - back * math.sin(dr.yaw),
                                 m.enu[0], m.enu[1]))

    def _speed(self, t: float, v: float) -> None:
        for dr in self.compasses.values():
            dr.advance(t, self.v)
        self.v = v

    def surveys(self, window: float = WINDOW_S) -> list[OffsetSurvey]:
        """Per compass with at least one window that fits, its survey (sensor name order)."""
        out = []
        for name in sorted(self.compasses):
            dr = self.compasses[name]
            if not dr.pair_t:
                continue
            t = np.array(dr.pair_t, float)
            p = np.array(dr.pairs, float).reshape(-1, 4)
            edges = np.arange(t[0], t[-1] + window, window)
            wins = []
            for lo in edges:
                m = (t >= lo) & (t < lo + window)
                w = fit_window(t[m], p[m, :2], p[m, 2:])
                if w is not None:
                    wins.append(w)
            if wins:
                out.append(OffsetSurvey(name, tuple(wins)))
        return out


def recorder_for(cfg) -> OffsetRecorder:
    """An OffsetRecorder with the config's wheel geometry and GPS delays."""
    geometry = ((cfg.robot.wheel_radius, cfg.robot.track_width)
                if cfg.robot.wheel_radius and cfg.robot.track_width else None)
    return OffsetRecorder(geometry, {s.name: s.delay for s in cfg.sensors if s.kind == "gps"})


def config_warnings(surveys: list[OffsetSurvey], cfg) -> list[str]:
    """What the surveys say the config gets wrong, one sentence each: a fixed heading_offset
    more than MISMATCH_RAD from the measured one, and an offset that wanders
    (``OffsetSurvey.wanders``) while the config holds it constant (fixed, or estimated with
    walk 0)."""
    by_name = {s.name: s for s in cfg.sensors}
    out = []
    for sv in surveys:
        s = by_name.get(sv.sensor)
        if s is None or "yaw" not in s.use:
            continue
        fixed = not isinstance(s.heading_offset, str)
        measured = (f"its yaw minus the GPS course is {sv.median:+.3f} rad "
                    f"({math.degrees(sv.median):+.1f} deg, median of {len(sv.windows)} windows)")
        if fixed and abs(float(_wrap(sv.median - s.heading_offset))) > MISMATCH_RAD:
            out.append(f"{s.topic}: heading_offset is fixed at {s.heading_offset:+.3f} rad but "
                       f"{measured}: every estimator will find the compass and the GPS in "
                       "conflict; set heading_offset to the measured value or 'estimate'")
        if sv.wanders and (fixed or s.noise.get("heading_offset_walk") == 0.0):
            held = "fixed" if fixed else "estimated with heading_offset_walk 0"
            out.append(f"{s.topic}: the heading offset wanders by {math.degrees(sv.spread):.0f} "
                       f"deg over {sv.duration:.0f} s (windows of {WINDOW_S:.0f} s) but it is "
                       f"{held}; 'estimate' with heading_offset_walk {suggested_walk(sv)} "
                       "rad/sqrt(s) follows it")
    return out


def suggested_walk(sv: OffsetSurvey) -> float:
    """A heading_offset_walk (rad/sqrt(s)) for a wandering offset: ``OffsetSurvey.walk``
    rounded up to one significant digit."""
    return _round_up(sv.walk())


def _round_up(x: float) -> float:
    """x rounded up to one significant digit (a suggested noise value)."""
    if x <= 0.0:
        return 0.0
    e = math.floor(math.log10(x))
    return round(math.ceil(x / 10.0 ** e) * 10.0 ** e, -e)
