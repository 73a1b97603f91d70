"""The plausibility screen: samples the robot cannot physically produce are rejected before any
estimator sees them.

``RobotLimits(cfg, rejected)`` is fed every measurement in stamp order (``admit(m)``, True: pass
it on) by the bag stream (``ddfuse.estimation.bags``) and the live converter
(``ddfuse.estimation.live``). It rejects, per sensor:

* a twist sample (odometry v and yaw rate; wheel speeds through ``robot.wheel_radius`` and
  ``track_width``; a gyro's yaw rate) beyond the robot's top speed or yaw rate
  (``RobotConfig.speed_limit`` m/s, ``yaw_rate_limit`` rad/s) by more than ``K_SIGMA`` of its
  standard deviation (the stated one, or the sensor's own scatter where that is larger:
  ``_Scatter``; ``warnings()`` names a scatter over 3x the stated noise);
* a twist sample whose change since the sensor's last accepted one needs more acceleration than
  the robot has: |dv| > a_max dt + K_SIGMA sqrt(var_1 + var_2) (``robot.max_accel`` /
  ``max_yaw_accel`` when given, else ``DEFAULT_MAX_ACCEL`` / ``DEFAULT_MAX_YAW_ACCEL``);
* a GPS fix further from the sensor's last accepted fix than the top speed explains:
  distance > v_max dt + K_SIGMA_GPS sqrt(s_1^2 + s_2^2) (s: the larger horizontal standard
  deviation of each fix's covariance, m).

Re-anchoring (the last accepted sample could itself be the glitch, or the robot really changed
speed faster than the limit says): ``REANCHOR`` consecutive rejected samples of one sensor that
agree with each other by the same test replace the anchor. For a twist sensor: at once while the
anchor is not confirmed (the first sample, or a re-anchor, until ``REANCHOR`` samples in a row
fit it), else once the run spans ``TWIST_HOLD_S``; the next sample decides: one that fits the run
is passed on, one that fits the anchor before it restores that anchor (the run was a dropout:
none of it is passed).
For GPS the last of the run is passed on, and only while the anchor is provisional (the first
fix, or one accepted more than ``GAP_S`` after the one before it, until ``REANCHOR`` fixes in a
row have agreed with it): a confirmed fix keeps its place, and a held GPS jump stays
rejected while it holds: a fix that goes on the run of rejected fixes (fits its last one, nearer
to it than to the anchor) is rejected even when the aged anchor's reach would take it, up to
``HOLD_S``; a run that lasts longer re-anchors (the receiver has said the same for a minute).
A fix that fits the anchor and not the run ends the jump. A jump taken so keeps the anchor
before it as the other side for ``HOLD_S``: rejected fixes within the top speed's reach of it
re-anchor too, so the return costs ``REANCHOR`` - 1 fixes. A jump can also be accepted, being
within the top speed's reach of the anchor (an NLOS fix some 25 m off at 25 m/s): when a run of
rejected fixes starts, the last ``REANCHOR`` fixes accepted (since the last re-anchor) are
searched, newest first, for one on the run's side: one that needs less than half the speed to
reach the run's first fix than to reach the anchor, the anchor beyond the noise allowance from
it. Found, the anchor's side is shorter than a confirmation and the run may return to the
track the screen followed before it: held as any run, it re-anchors after ``REANCHOR`` fixes
within the top speed's reach of that fix, so the return costs ``REANCHOR`` - 1 fixes (taking
its fixes at once would let an NLOS run in wherever a fix before the anchor happens to lie near
it), and the anchor it leaves is the other side for ``HOLD_S`` (the choice can be wrong: an NLOS
fix where the robot was seconds before looks the same; the next run back to it undoes it at
the same cost). Otherwise the run is a jump away, held as above. A sample beyond the top speed
or yaw rate never re-anchors.

Aided by the odometry (``ddfuse.estimation.gps_motion``): where the twist samples the screen
passed can tell (a speed source, the rotation from their frame to ENU learnt from accepted
fixes, no gap in the feed between the two fixes), a fix must also lie where the motion
dead-reckoned from the other fix puts it, within the fixes' noise and the dead reckoning's
own drift allowance. There the dead reckoning, not the GPS alone, decides a held jump: a fix
that fits the anchor so is taken (the hold above is for the aged top-speed reach, which the
motion test replaces), and a fix accepted after a gap is not provisional when the odometry
vouches for it (its drift allowance within the fixes' noise: the gap was the screen's own
rejections, not an outage), so a run of jumped fixes cannot re-anchor on it.

Each rejection is counted in ``rejected[(topic, reason)]`` (``Stream.rejected``); ``warnings()``
gives one line per topic and reason with the count, the first time, value and limit. Design and
measured figures: docs/design/plausibility.md.
"""

from __future__ import annotations

import logging
import math
from collections import Counter, deque
from dataclasses import dataclass, field

from ddfuse.estimation.config import Config
from ddfuse.estimation.gps_motion import MotionCheck
from ddfuse.estimation.measurements import GpsFix, GyroYawRate, WheelOdometry, WheelSpeeds

__all__ = ["DEFAULT_MAX_ACCEL", "DEFAULT_MAX_YAW_ACCEL", "GAP_S", "K_SIGMA", "K_SIGMA_GPS",
           "HOLD_S", "REANCHOR", "TWIST_HOLD_S", "RobotLimits"]

log = logging.getLogger(__name__)

# Tyre friction bounds a wheeled robot's acceleration by mu g with mu <= ~1: 2 g leaves room for
# stamp jitter (the Jackal's odometry shows 0.41 m/s in one 0.02 s period). A differential drive
# turning on a 0.4 m track with both wheels at that acceleration in opposite directions:
# 2 a / L = 100 rad/s^2 (the Jackal's gyro shows 26 rad/s^2 between two samples).
DEFAULT_MAX_ACCEL = 20.0  # m/s^2
DEFAULT_MAX_YAW_ACCEL = 100.0  # rad/s^2
K_SIGMA = 6.0  # a twist sample's noise allowance, in its standard deviations
K_SIGMA_GPS = 6.0  # a fix's noise allowance (2-D: P(|d| > 6 sigma) = exp(-18) = 1.5e-8)
REANCHOR = 5  # consecutive rejected samples that agree with each other replace the anchor
GAP_S = 2.0  # s: a fix accepted this long after the one before is provisional
HOLD_S = 60.0  # s: a held GPS jump stays rejected this long at most, then it is the position
# s: a run of twist samples against a confirmed anchor re-anchors only once it spans this long
# (a wheel driver's dropout or a spike is shorter; a speed held this long is the robot's)
TWIST_HOLD_S = 1.0


@dataclass(slots=True)
class _Channel:
    """One checked quantity of one sensor: its anchor (the last accepted value), the run of
    rejected samples since (for re-anchoring), and the samples' own scatter (``scatter``)."""

    limit: float  # the top value (m/s or rad/s)
    accel: float  # the top rate of change (m/s^2 or rad/s^2)
    unit: str
    t: float = math.nan  # the anchor's stamp, s (NaN: none yet)
    x: float = 0.0
    var: float = 0.0
    run: list | None = None  # rejected (t, x, var) since the anchor, consecutive and agreeing
    # the anchor a run replaced, (t, x, var, agreed), until a sample fits either: one that
    # fits it says the run was the glitch and restores it
    before: tuple | None = None
    agreed: int = 0  # samples accepted in a row since the first one or a re-anchor
    scatter: _Scatter | None = None
    stated: float = math.nan  # the last sample's stated variance

    def fits(self, t0: float, x0: float, v0: float, t: float, x: float, var: float) -> bool:
        return abs(x - x0) <= self.accel * abs(t - t0) + K_SIGMA * math.sqrt(v0 + var)


SCATTER_N = 64  # order-2 differences the scatter's median is taken over
SCATTER_START = 32  # differences before a scatter is read (a burst of garbage is not one)
SCATTER_EVERY = 16  # recomputed every this many samples
SCATTER_GAP_S = 1.0  # s: a longer gap between samples starts the differences afresh
SCATTER_SAY = 3.0  # the scatter's sd over the stated sd that warnings() mentions
# the median of |x_k - 2 x_k-1 + x_k-2| over a white sample's sd (|N(0, 6)|'s median)
_D2_MEDIAN = 0.67449 * math.sqrt(6.0)


@dataclass(slots=True)
class _Scatter:
    """A twist sensor's own sample noise, read off its samples (every one, passed or not): the
    median absolute order-2 difference of the last ``SCATTER_N``, as the variance (units^2) of
    white noise that has that median. A smooth motion's part of a difference is its jerk times
    dt^2; the median holds while under half the differences are glitches (a glitch moves
    three), and a lower quantile would be biased by an encoder's quantisation; held values
    (quantised, or a sensor that repeats) give 0. ``var`` is 0 until ``SCATTER_START``
    differences are in."""

    t: float = math.nan
    x1: float = math.nan  # the last two samples
    x2: float = math.nan
    d2: deque = field(default_factory=lambda: deque(maxlen=SCATTER_N))
    count: int = 0
    var: float = 0.0

    def add(self, t: float, x: float) -> float:
        if not t - self.t <= SCATTER_GAP_S:  # the first sample, a gap, or out of order
            self.x1 = self.x2 = math.nan
        if self.x2 == self.x2:  # not NaN: two samples before this one
            self.d2.append(abs(x - 2.0 * self.x1 + self.x2))
            self.count += 1
            if self.count % SCATTER_EVERY == 0 and len(self.d2) >= SCATTER_START:
                med = sorted(self.d2)[len(self.d2) // 2]
                self.var = (med / _D2_MEDIAN) ** 2
        self.t, self.x2, self.x1 = t, self.x1, x
        return self.var


@dataclass(slots=True)
class _Fix:
    t: float
    e: float
    n: float
    sd: float  # m
    dr: tuple[float, float, float, int] | None = None  # the dead reckoning (gps_motion)


class RobotLimits:
    """The screen of one stream (module docstring). ``rejected``: the stream's Counter of
    (topic, reason) -> count, incremented here."""

    def __init__(self, cfg: Config, rejected: Counter) -> None:
        r = cfg.robot
        self.rejected = rejected
        self.topic = {s.name: s.topic for s in cfg.sensors}
        self.v_max, self.w_max = r.speed_limit, r.yaw_rate_limit
        self.a_max = r.max_accel if r.max_accel else DEFAULT_MAX_ACCEL
        self.alpha_max = r.max_yaw_accel if r.max_yaw_accel else DEFAULT_MAX_YAW_ACCEL
        self.geometry = (r.wheel_radius, r.track_width)
        self._channels: dict[tuple[str, str], _Channel] = {}
        self.motion = MotionCheck(cfg, K_SIGMA_GPS)  # fixes against the dead reckoning
        # sensor -> (anchor, how many more agreeing fixes confirm it: 0 = confirmed)
        self._fix: dict[str, tuple[_Fix, int]] = {}
        self._fix_run: dict[str, list[_Fix]] = {}
        # sensor -> (the anchor before a jump taken after HOLD_S, when it was taken, s)
        self._before_jump: dict[str, tuple[_Fix, float]] = {}
        # sensor -> the last REANCHOR fixes accepted since the last re-anchor, oldest first
        self._recent: dict[str, deque[_Fix]] = {}
        # sensor -> the fix before the anchor's side that the current run returns to (None: the
        # run is a jump away from the anchor)
        self._return_to: dict[str, _Fix | None] = {}
        # (topic, reason) -> (first t, value, limit text) for the warnings
        self._first: dict[tuple[str, str], tuple[float, str, str]] = {}

    # --- the entry point -------------------------------------------------------------------
    def admit(self, m) -> bool:
        """Whether measurement ``m`` (stamp order per sensor) is plausible; a rejected one is
        counted. Measurements of other kinds always pass."""
        self.motion.tick(m.t)
        ok = self._admit(m)
        if ok:
            self.motion.dr.feed(m)
        return ok

    def _admit(self, m) -> bool:
        typ = type(m)
        if typ is WheelOdometry:
            ok = True
            if m.v is not None:
                ok = self._twist(m.sensor, "speed", m.t, m.v, m.v_var)
            if m.yaw_rate is not None:
                ok = self._twist(m.sensor, "yaw rate", m.t, m.yaw_rate, m.yaw_rate_var) and ok
            return ok
        if typ is GyroYawRate:
            return self._twist(m.sensor, "yaw rate", m.t, m.yaw_rate, m.var)
        if typ is WheelSpeeds:
            r, L = self.geometry
            if r is None or L is None:
                return True
            v, w, vv, wv = m.twist(r, L)
            ok = self._twist(m.sensor, "speed", m.t, v, vv)
            return self._twist(m.sensor, "yaw rate", m.t, w, wv) and ok
        if typ is GpsFix and m.enu is not None:
            return self._gps(m)
        return True

    def warnings(self) -> list[str]:
        """One line per (topic, reason) rejected here: the count, the first time, value and
        limit."""
        out = []
        for (topic, reason), (t, value, limit) in sorted(self._first.items()):
            n = self.rejected[(topic, reason)]
            out.append(f"topic {topic}: {n} sample(s) rejected as physically implausible: "
                       f"{reason} (first at t={t:.3f}: {value}; {limit})")
        for (sensor, what), ch in sorted(self._channels.items()):
            sc = ch.scatter
            if sc is None or not sc.var > SCATTER_SAY ** 2 * ch.stated:
                continue
            out.append(f"topic {self.topic.get(sensor, sensor)}: its {what} samples scatter with "
                       f"sd {math.sqrt(sc.var):.3g} {ch.unit} (order-2 differences of the last "
                       f"{len(sc.d2)}), over {SCATTER_SAY:g}x the stated "
                       f"{math.sqrt(ch.stated):.3g} {ch.unit}: the plausibility screen allowed "
                       "for the scatter, the estimators use the stated noise (check the "
                       "sensor's noise, or run 'ddfuse tune')")
        return out

    # --- the checks ------------------------------------------------------------------------
    def _reject(self, sensor: str, reason: str, t: float, value: str, limit: str) -> bool:
        key = (self.topic.get(sensor, sensor), reason)
        self.rejected[key] += 1
        if key not in self._first:
            self._first[key] = (t, value, limit)
            log.warning("%s: t=%.3f: %s (%s); rejected and counted", key[0], t, value, limit)
        return False

    def _twist(self, sensor: str, what: str, t: float, x: float, var: float) -> bool:
        ch = self._channels.get((sensor, what))
        if ch is None:
            ch = self._channels[(sensor, what)] = (
                _Channel(self.v_max, self.a_max, "m/s") if what == "speed"
                else _Channel(self.w_max, self.alpha_max, "rad/s"))
        var = var if var > 0.0 and math.isfinite(var) else 0.0
        ch.stated = var
        if math.isfinite(x):
            # a stated noise below the samples' own scatter would reject good samples
            sc = ch.scatter
            if sc is None:
                sc = ch.scatter = _Scatter()
            var = max(var, sc.add(t, x))
        sd = math.sqrt(var)
        if abs(x) > ch.limit + K_SIGMA * sd:
            key = "robot.max_speed" if what == "speed" else "robot.max_yaw_rate"
            return self._reject(sensor, f"{what} beyond the robot's top {what} ({key})", t,
                                f"{what} {x:.6g} {ch.unit}", f"limit {ch.limit:g} {ch.unit}")
        first = math.isnan(ch.t)
        fits = first or ch.fits(ch.t, ch.x, ch.var, t, x, var)
        b = ch.before
        if fits or (b is not None and ch.fits(b[0], b[1], b[2], t, x, var)):
            # the anchor confirmed once more, or (the run was the glitch) the one before it as
            # confirmed as it was
            ch.agreed = 0 if first else ch.agreed + 1 if fits else b[3] + 1
            ch.t, ch.x, ch.var, ch.run, ch.before = t, x, var, None, None
            return True
        run = ch.run
        if run and ch.fits(*run[-1], t, x, var):
            run.append((t, x, var))
        else:
            run = ch.run = [(t, x, var)]
        if len(run) >= REANCHOR and (ch.agreed < REANCHOR or t - run[0][0] >= TWIST_HOLD_S):
            # they agree with each other: the anchor may have been the odd one (one not yet
            # confirmed by REANCHOR samples at once, a confirmed one after TWIST_HOLD_S). The
            # next sample decides, so that the run itself reaches no estimator: one that fits
            # the run is passed on (the robot did change faster than the limit), one that fits
            # the old anchor restores it (a dropout, a wheel driver's second of zeros)
            ch.before = (ch.t, ch.x, ch.var, ch.agreed)
            ch.t, ch.x, ch.var, ch.run, ch.agreed = t, x, var, None, 0
        acc = "robot.max_accel" if what == "speed" else "robot.max_yaw_accel"
        return self._reject(
            sensor, f"{what} change faster than the robot can accelerate ({acc})", t,
            f"{what} {x:.6g} {ch.unit} {t - ch.t:.3f} s after {ch.x:.6g} {ch.unit}",
            f"limit {ch.accel:g} {ch.unit}/s plus {K_SIGMA:g} sigma")

    def _gps(self, m: GpsFix) -> bool:
        c = m.cov
        sd = math.sqrt(max(c[0, 0], c[1, 1], 0.0))
        fix = _Fix(m.t, m.enu[0], m.enu[1], sd, self.motion.state(m.t))
        prev = self._fix.get(m.sensor)
        if prev is None:
            self._take(m.sensor, fix, REANCHOR)
            return True
        anchor, unconfirmed = prev
        run = self._fix_run.get(m.sensor)
        if self._fix_fits(m.sensor, anchor, fix) and not self._holds(m.sensor, run, anchor, fix):
            # after a gap a fix is provisional, unless the odometry vouches for it (a gap made
            # of rejected fixes: the jump, not the fix after it, was the glitch)
            gap = fix.t - anchor.t > GAP_S and not self.motion.vouches(m.sensor, anchor, fix)
            self._fix[m.sensor] = (fix, REANCHOR if gap else max(unconfirmed - 1, 0))
            self._recent[m.sensor].append(fix)
            self.motion.accepted(m.sensor, fix)
            self._fix_run.pop(m.sensor, None)
            self._return_to.pop(m.sensor, None)
            return True
        if run and self._fix_fits(m.sensor, run[-1], fix):
            run.append(fix)
            back_to = self._return_to.get(m.sensor)
        else:
            run = self._fix_run[m.sensor] = [fix]
            back_to = self._return_to[m.sensor] = self._side_before(m.sensor, anchor, fix)
        other, since = self._before_jump.get(m.sensor, (None, 0.0))
        # back to the side before a jump taken at ``since`` (for HOLD_S after it), or before a
        # jump accepted within reach
        back = (other is not None and fix.t - since <= HOLD_S
                and self._fix_fits(m.sensor, other, fix))
        returns = back_to is not None and self._fix_fits(m.sensor, back_to, fix)
        if len(run) >= REANCHOR and (unconfirmed or back or returns
                                     or fix.t - run[0].t > HOLD_S):
            if (back or unconfirmed) and not returns:
                self._before_jump.pop(m.sensor, None)
            else:  # a jump held past HOLD_S, or a return that may be wrong, taken: the side
                # before it stays the other one
                self._before_jump[m.sensor] = (anchor, fix.t)
            self._take(m.sensor, fix, 0)
            return True
        d = math.hypot(fix.e - anchor.e, fix.n - anchor.n)
        dt = fix.t - anchor.t
        return self._reject(
            m.sensor, "fix further from the last accepted one than the robot's top speed "
            "explains (robot.max_speed)", m.t,
            f"{d:.1f} m in {dt:.2f} s", f"limit {self.v_max:g} m/s plus {K_SIGMA_GPS:g} sigma of "
            f"the fixes ({anchor.sd:.2g} m, {fix.sd:.2g} m)")

    def _take(self, sensor: str, fix: _Fix, unconfirmed: int) -> None:
        """``fix`` the new anchor by (re-)anchoring: the fixes accepted before it are no
        side to return to."""
        self._fix[sensor] = (fix, unconfirmed)
        self._recent[sensor] = deque([fix], maxlen=REANCHOR)
        self.motion.forget(sensor)
        self.motion.accepted(sensor, fix)
        self._fix_run.pop(sensor, None)
        self._return_to.pop(sensor, None)

    def _side_before(self, sensor: str, anchor: _Fix, fix: _Fix) -> _Fix | None:
        """The newest recently accepted fix on the side of the rejected ``fix`` rather than on
        the ``anchor``'s, when the anchor's side is shorter than the ``REANCHOR`` fixes that
        confirm one: the anchor was a jump accepted within reach and ``fix`` returns to the
        track before it. A fix is on the run's side when it needs less than half the speed to
        reach ``fix`` than to reach the anchor, and the anchor is beyond the noise allowance from
        it (on a smooth track driven away from a jump both speeds are the track's). None: the
        anchor's side has ``REANCHOR`` fixes (or is all there is), ``fix`` is a jump away."""
        for h in reversed(self._recent[sensor]):
            to_anchor = math.hypot(anchor.e - h.e, anchor.n - h.n) / max(anchor.t - h.t, 1e-9)
            to_fix = math.hypot(fix.e - h.e, fix.n - h.n) / max(fix.t - h.t, 1e-9)
            if h is not anchor and 2.0 * to_fix < to_anchor and \
                    math.hypot(anchor.e - h.e, anchor.n - h.n) > \
                    K_SIGMA_GPS * math.hypot(anchor.sd, h.sd):
                return h
        return None

    def _holds(self, sensor: str, run: list[_Fix] | None, anchor: _Fix, fix: _Fix) -> bool:
        """Whether ``fix``, within reach of ``anchor`` only because the anchor has aged, goes on
        the rejected ``run`` (a held jump): it fits the run's last fix, nearer than the anchor.
        Never where the odometry can tell: its test has no aged reach. (A run longer than
        ``HOLD_S`` re-anchors in ``_gps``.)"""
        if not run or not self._fix_fits(sensor, run[-1], fix) or \
                self.motion.tells(sensor, anchor, fix):
            return False
        last = run[-1]
        return math.hypot(fix.e - last.e, fix.n - last.n) < \
            math.hypot(fix.e - anchor.e, fix.n - anchor.n)

    def _fix_fits(self, sensor: str, a: _Fix, b: _Fix) -> bool:
        """Whether ``b`` is within the top speed's reach of ``a`` and, where the odometry can
        tell, where the motion dead-reckoned between them puts it (``gps_motion``)."""
        d = math.hypot(b.e - a.e, b.n - a.n)
        if d > self.v_max * abs(b.t - a.t) + K_SIGMA_GPS * math.hypot(a.sd, b.sd):
            return False
        return self.motion.fits(sensor, a, b) is not False
