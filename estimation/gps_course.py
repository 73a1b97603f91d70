"""The start pose from the GPS course: position and heading of a robot that has no initial pose
and no absolute heading sensor, from GPS fixes and the dead-reckoned odometry between them.

Contract (``GpsCourseStart``):

* ``add(m)`` buffers every measurement (time order) until it decides; it returns None while it
  waits, then once a ``CourseStart``.
* It waits for odometry that moves (a ``WheelOdometry`` with a speed, or ``WheelSpeeds``); the
  baseline starts at the first fix no older than ``odometry_wait`` s before that sample.
* It decides when the fixes since then span at least ``distance`` m, more with poor fixes: until
  the course's sigma (both fixes' errors across the baseline) is at most ``sigma_max``, and
  when the odometry dead-reckoned from heading 0 over the same interval has moved at least half
  ``distance`` (else the robot turned on the spot or slid: it waits on).
* ``CourseStart``: the first fix's stamp (s) and east/north (m, local ENU); the heading there
  (rad, ENU yaw: the fixes' direction minus the dead-reckoned one); the position sigma (m, the
  fix's larger axis) and the heading sigma (rad, at least ``min_psi_sigma``); the buffered
  measurements from that stamp on, to replay; the fixes buffered before it (unusable: no motion
  relates them to the next).

Only odometry and gyro yaw rates enter the dead reckoning (a fixed gyro bias subtracted); units
are SI. Used by the smoother and by the IGVC EKF (``ekf_igvc``) alike. Design notes:
docs/design/smoother.md (Start from the GPS course), docs/design/igvc_ekf.md.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

from ddfuse.estimation.estimator import wrap_angle
from ddfuse.estimation.measurements import GpsFix, GyroYawRate, WheelOdometry, WheelSpeeds

INIT_DISTANCE = 5.0  # m of GPS travel before the heading is taken from the GPS course
COURSE_SIGMA_MAX = 0.4  # rad: with poor fixes, the travel waits for a course this good
# rad: the least heading sigma a course start claims (slip and the fixes' correlated errors
# bend the course more than the fixes' stated sigmas say)
COURSE_MIN_PSI_SIGMA = 0.2


@dataclass(frozen=True)
class CourseStart:
    """The start ``GpsCourseStart`` decided on (see the module docstring for the units)."""

    t: float
    position: tuple[float, float]
    heading: float
    pos_sigma: float
    psi_sigma: float
    replay: list
    dropped: list[GpsFix]


class GpsCourseStart:
    """Buffers measurements until the GPS course gives the start heading (module docstring).

    ``gyro_names``: the gyro sensors whose yaw rate dead-reckons (``fixed_bias`` rad/s taken
    off); ``wheel_radius``, ``track_width`` (m): to turn ``WheelSpeeds`` into a twist;
    ``odometry_wait`` (s): how far before the first moving odometry sample a fix may start the
    baseline (odometry held back over its period covers it)."""

    def __init__(self, *, gyro_names: set[str], fixed_bias: float, wheel_radius: float,
                 track_width: float, min_psi_sigma: float, odometry_wait: float,
                 distance: float = INIT_DISTANCE, sigma_max: float = COURSE_SIGMA_MAX) -> None:
        self.gyro_names, self.fixed_bias = gyro_names, fixed_bias
        self.wheel_radius, self.track_width = wheel_radius, track_width
        self.min_psi_sigma, self.odometry_wait = min_psi_sigma, odometry_wait
        self.distance, self.sigma_max = distance, sigma_max
        self.buffer: list = []  # measurements held until the heading is known
        self._fixes: tuple[GpsFix, GpsFix] | None = None  # the baseline's first and last fix
        self._moving = False  # whether the buffer holds an odometry speed
        self.last_fix: GpsFix | None = None  # the buffer's last fix

    @classmethod
    def for_config(cls, cfg, *, min_psi_sigma: float, odometry_wait: float,
                   distance: float = INIT_DISTANCE) -> GpsCourseStart:
        """The start for a robot configured by ``cfg`` (a ``Config``): its gyros are the IMUs
        that use ``yaw_rate``, the bias taken off the first fixed ``gyro_bias`` (0 when every
        one is estimated), the geometry ``cfg.robot``'s."""
        imus = [s for s in cfg.of_kind("imu") if "yaw_rate" in s.use]
        fixed = next((float(s.gyro_bias) for s in imus if s.gyro_bias != "estimate"), 0.0)
        return cls(gyro_names={s.name for s in imus}, fixed_bias=fixed,
                   wheel_radius=cfg.robot.wheel_radius, track_width=cfg.robot.track_width,
                   min_psi_sigma=min_psi_sigma, odometry_wait=odometry_wait, distance=distance)

    def add(self, m) -> CourseStart | None:
        """Buffer ``m``; the start once the course is good enough, else None. The buffer is
        read in stamp order: a late ``m`` (a smoother's late fix) goes to its place."""
        if self.buffer and m.t < self.buffer[-1].t:
            bisect.insort(self.buffer, m, key=lambda b: b.t)
        else:
            self.buffer.append(m)
        # The buffer's first and last fix (no rescan per message). The window starts at a fix
        # that odometry covers: from odometry_wait before the first sample on (held back over
        # its period); an earlier one has no motion to relate it to the next.
        if isinstance(m, GpsFix):
            self.last_fix = m
            if self._moving:
                self._fixes = (self._fixes[0] if self._fixes else m, m)
        elif not self._moving and (isinstance(m, WheelSpeeds) or (
                isinstance(m, WheelOdometry) and m.v is not None)):
            self._moving = True
            first = next((b for b in self.buffer if isinstance(b, GpsFix)
                          and b.t >= m.t - self.odometry_wait), None)
            self._fixes = (first, self.last_fix) if first is not None else None
        if self._fixes is None or self._fixes[0] is self._fixes[1]:
            return None
        f0, f1 = self._fixes
        de, dn = f1.enu[0] - f0.enu[0], f1.enu[1] - f0.enu[1]
        # the course's direction error is both fixes' errors across the baseline d, and with
        # poor fixes the wait is for a baseline that gives sigma_max
        across = max(f0.cov[0, 0], f0.cov[1, 1]) + max(f1.cov[0, 0], f1.cov[1, 1])
        d = math.hypot(de, dn)
        if d < max(self.distance, math.sqrt(across) / self.sigma_max):
            return None
        psi0 = self._course_heading(f0, f1)
        if psi0 is None:
            return None
        replay = [b for b in self.buffer if b.t >= f0.t]
        dropped = []
        for b in self.buffer:
            if b.t >= f0.t:
                break
            if isinstance(b, GpsFix):
                dropped.append(b)
        self.buffer = []
        self._fixes = self.last_fix = None
        self._moving = False
        sig = max(math.sqrt(f0.cov[0, 0]), math.sqrt(f0.cov[1, 1]))
        # the baseline the fixes' own errors lengthened (by 2 across in the mean square): the
        # wait ended at a noisy d that had reached the threshold early
        d_true = math.sqrt(max(d * d - 2.0 * across, 0.25 * d * d))
        return CourseStart(f0.t, (f0.enu[0], f0.enu[1]), psi0, sig,
                           max(self.min_psi_sigma, math.sqrt(across) / d_true), replay, dropped)

    def _course_heading(self, f0: GpsFix, f1: GpsFix) -> float | None:
        """Initial heading at f0: the GPS displacement's direction minus the direction of the
        dead-reckoned displacement (odometry from heading 0) over the same interval."""
        x = y = psi = 0.0
        v = w = None
        last = None
        for b in self.buffer:
            if b.t < f0.t:
                if isinstance(b, WheelOdometry):
                    v = b.v if b.v is not None else v
                    w = b.yaw_rate if b.yaw_rate is not None else w
                continue
            if b.t > f1.t:
                break
            if last is not None and v is not None and w is not None:
                dt = b.t - last
                x += v * math.cos(psi) * dt
                y += v * math.sin(psi) * dt
                psi += w * dt
            last = b.t
            if isinstance(b, WheelOdometry):
                v = b.v if b.v is not None else v
                w = b.yaw_rate if b.yaw_rate is not None else w
            elif isinstance(b, GyroYawRate) and b.sensor in self.gyro_names:
                w = b.yaw_rate - self.fixed_bias
            elif isinstance(b, WheelSpeeds):
                v, w = b.twist(self.wheel_radius, self.track_width)[:2]
        if math.hypot(x, y) < 0.5 * self.distance:
            return None  # odometry disagrees with GPS about having moved: wait
        de, dn = f1.enu[0] - f0.enu[0], f1.enu[1] - f0.enu[1]
        return wrap_angle(math.atan2(dn, de) - math.atan2(y, x))
