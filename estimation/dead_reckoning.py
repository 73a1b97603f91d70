"""Dead reckoning: the wheel odometry integrated on its own, the baseline every fusing estimator
has to beat.

The pose (x, y, yaw in the local frame; m, m, rad) starts at the initial pose and moves by the
exact constant-twist step (``ddfuse.factors.kinematics.se2_step``) of each odometry sample over the
interval since the previous one: an encoder twist is the mean over its counting interval, so
sample k covers [t_(k-1), t_k], as a wheel-odometry node integrates it (the simulator's odometry
pose and ``evaluation.plot_sim.dead_reckoning`` do the same). The first sample only starts the
clock. Sources: the config's first odometry sensor that uses both v and yaw_rate, else its first
wheel-speed sensor (through the NOMINAL robot.wheel_radius and robot.track_width); every other
measurement is ignored. There is no covariance: ``Estimate.pose_cov`` is NaN.
"""

from __future__ import annotations

import math

import numpy as np
from ddfuse.estimation.config import Config
from ddfuse.estimation.estimator import Estimate, Estimator
from ddfuse.estimation.measurements import WheelOdometry, WheelSpeeds
from ddfuse.factors.kinematics import se2_step

__all__ = ["DeadReckoning", "odometry_source"]

_NAN_COV = np.full((3, 3), np.nan)


def odometry_source(cfg: Config) -> str | None:
    """Name of the sensor dead reckoning integrates (see module docstring), None if none fits."""
    for s in cfg.of_kind("odometry"):
        if "v" in s.use and "yaw_rate" in s.use:
            return s.name
    if cfg.robot.wheel_radius is not None and cfg.robot.track_width is not None:
        for s in cfg.of_kind("wheels"):
            return s.name
    return None


class DeadReckoning(Estimator):
    """Odometry-only pose (module docstring). ``initial_pose`` (x, y, yaw) in the local frame;
    default the origin facing east."""

    name = "dead_reckoning"

    def __init__(self, cfg: Config, *, initial_pose: tuple[float, float, float] | None = None
                 ) -> None:
        super().__init__()
        self.source = odometry_source(cfg)
        if self.source is None:
            raise ValueError("dead reckoning needs an odometry sensor using v and yaw_rate, or "
                             "wheel speeds with robot.wheel_radius and robot.track_width")
        self.pose = tuple(float(v) for v in initial_pose) if initial_pose else (0.0, 0.0, 0.0)
        self.t: float | None = None
        self._r = cfg.robot.wheel_radius
        self._L = cfg.robot.track_width

    def process(self, m) -> None:
        if m.sensor != self.source:
            return
        self.in_order(m)  # a stale sample is refused, not silently skipped
        if isinstance(m, WheelOdometry):
            if m.v is None or m.yaw_rate is None:
                return
            v, w = m.v, m.yaw_rate
        elif isinstance(m, WheelSpeeds):
            v, w = m.twist(self._r, self._L)[:2]
        else:
            return
        if self.t is not None and m.t > self.t:
            x, y, yaw = se2_step(*self.pose, v, w, m.t - self.t)
            self.pose = (x, y, (yaw + math.pi) % (2.0 * math.pi) - math.pi)
        self.t = m.t if self.t is None else max(self.t, m.t)

    def estimate(self) -> Estimate | None:
        if self.t is None:
            return None
        return Estimate(t=self.t, pose=self.pose, pose_cov=_NAN_COV.copy())
