"""Odometry scale states, shared by the filters that estimate them.

When the config states how well the robot's nominal geometry is known (robot.wheel_radius_std,
track_width_std), a filter with an odometry source carries k_v and k_w (unitless): the true
twist is (k_v v, k_w w) of the odometry's (v, w), k_v = true / nominal wheel radius and k_w =
that times nominal / true track width. Their prior is mean 1 with the covariance of
``ddfuse.estimation.config.RobotConfig.scale_std``; they are constants (no process noise).
"""

from __future__ import annotations

from ddfuse.estimation.config import Config

__all__ = ["ScaleStates"]


class ScaleStates:
    """Where a filter's k_v, k_w sit in its state, and their prior. ``ScaleStates.of(cfg, n)``
    is None when the config states no geometry uncertainty or has no odometry source;
    otherwise ``index`` is n (k_v; k_w follows) and ``names`` the two state names to append."""

    names = ("k_v", "k_w")

    def __init__(self, index: int, sd_v: float, sd_w: float, cov_vw: float) -> None:
        self.index = index
        self.cov = ((sd_v * sd_v, cov_vw), (cov_vw, sd_w * sd_w))

    @classmethod
    def of(cls, cfg: Config, index: int) -> ScaleStates | None:
        prior = cfg.robot.scale_std
        if prior is None or not (cfg.of_kind("odometry") or cfg.of_kind("wheels")):
            return None
        return cls(index, *prior)

    @classmethod
    def append_to(cls, cfg: Config, names: list) -> ScaleStates | None:
        """``of(cfg, len(names))``, appending the two state names to ``names`` if there are
        scales to estimate."""
        scale = cls.of(cfg, len(names))
        if scale is not None:
            names += cls.names
        return scale

    def set_prior(self, x0, P0) -> None:
        """Write the prior into the initial mean ``x0`` (n,) and covariance ``P0`` (n, n)."""
        k = self.index
        x0[k] = x0[k + 1] = 1.0
        P0[k:k + 2, k:k + 2] = self.cov
