"""The twist samples integrated in a frame of their own: what the plausibility screen
(``ddfuse.estimation.robot_limits``) and the GPS watch (``ddfuse.estimation.gps_watch``) compare
the GPS fixes with, before and whatever any estimator makes of them.

``TwistTrack(cfg)`` takes the forward speed from the first odometry sensor that uses ``v``
(else the first wheel-speed sensor, through ``robot.wheel_radius`` and ``track_width``) and the
yaw rate from the first gyro that uses ``yaw_rate`` (else that odometry's, else the wheels'). Fed
the twist samples in stamp order (``feed``), it holds each sample's twist until the next and
integrates it at the mid heading when advanced to a stamp (``advance``). State: ``x``, ``y`` (m)
and ``yaw`` (rad) in the frame of its start (x along the heading at the start), ``s`` the path
length (m). ``on`` is False without a speed source. ``restart`` begins afresh (after a gap in
the feed, where the held twist says nothing) and counts ``epoch``: states of different epochs
are not comparable.
"""

from __future__ import annotations

import math

from ddfuse.estimation.config import Config
from ddfuse.estimation.measurements import GyroYawRate, WheelOdometry, WheelSpeeds

__all__ = ["TwistTrack"]


class TwistTrack:
    """Planar dead reckoning of one stream from its twist samples (module docstring)."""

    def __init__(self, cfg: Config) -> None:
        r = cfg.robot
        self.geometry = (r.wheel_radius, r.track_width)
        odo = [s for s in cfg.of_kind("odometry") if "v" in s.use]
        wheels = [s for s in cfg.of_kind("wheels")] if None not in self.geometry else []
        self.v_src = odo[0].name if odo else (wheels[0].name if wheels else None)
        gyros = [s for s in cfg.of_kind("imu") if "yaw_rate" in s.use]
        w_odo = [s for s in cfg.of_kind("odometry") if "yaw_rate" in s.use]
        self.w_src = gyros[0].name if gyros else (w_odo[0].name if w_odo else
                                                  (self.v_src if wheels and not odo else None))
        self.on = self.v_src is not None
        self.epoch = 0
        self.x = self.y = self.s = self.yaw = 0.0
        self._v = self._w = 0.0
        self.t: float | None = None  # the state's stamp, s (None: nothing fed since the start)

    def restart(self) -> None:
        """Dead-reckon afresh from the next twist sample (a new ``epoch``)."""
        self.epoch += 1
        self.x = self.y = self.s = self.yaw = 0.0
        self._v = self._w = 0.0
        self.t = None

    def feed(self, m) -> None:
        """Take the twist of ``m`` (a measurement in stamp order; other kinds and other sensors
        are ignored) from its stamp on."""
        if m.sensor not in (self.v_src, self.w_src):
            return
        typ = type(m)
        if typ not in (WheelOdometry, GyroYawRate, WheelSpeeds):
            return
        self.advance(m.t)
        if typ is WheelOdometry:
            if m.sensor == self.v_src and m.v is not None:
                self._v = m.v
            if m.sensor == self.w_src and m.yaw_rate is not None:
                self._w = m.yaw_rate
        elif typ is GyroYawRate:
            self._w = m.yaw_rate
        else:
            v, w, _, _ = m.twist(*self.geometry)
            self._v = v
            if m.sensor == self.w_src:
                self._w = w

    def advance(self, t: float) -> None:
        """Integrate the held twist up to stamp ``t`` (s; an earlier stamp changes nothing)."""
        if self.t is not None and t > self.t:
            dt = t - self.t
            # the twist held since the last sample, integrated at the mid heading
            h = self.yaw + 0.5 * self._w * dt
            step = self._v * dt
            self.x += step * math.cos(h)
            self.y += step * math.sin(h)
            self.s += abs(step)
            self.yaw += self._w * dt
        if self.t is None or t > self.t:
            self.t = t
