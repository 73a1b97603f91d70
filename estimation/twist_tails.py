"""The heavy-tailed speed walk (``robot.twist_walk.speed_burst``, ``burst_share``): the forward
speed's random walk as a two-component scale mixture, the one model every estimator and
``ddfuse tune``'s likelihood use.

Over an interval of dt seconds between two speed samples the speed changes by a white
acceleration of density ``steady`` (m/s/sqrt(s), ``robot.twist_walk.speed``) with probability
1 - ``share``, or of density ``burst`` (``speed_burst``) with probability ``share`` (a start, a
stop, a bump): a Gaussian scale mixture, whose speed changes are heavy-tailed (kurtosis
3 (1 - p + p r^2) / (1 - p + p r)^2 for a density ratio r = burst^2 / steady^2).

The filter predicts with the steady density. At a speed sample with innovation nu (m/s) and
innovation variance ``s`` under that prediction ((m/s)^2), the burst adds ``extra`` =
(burst^2 - steady^2) dt to the speed's variance; its posterior probability given nu is

    w = p N(nu; 0, s + extra) / (p N(nu; 0, s + extra) + (1 - p) N(nu; 0, s)),

and the speed's prior variance is widened by ``extra`` before the update where w > 1/2 (the
more probable component chosen from the innovation, a hard-decision two-model filter: a steady
stretch keeps the small q, a burst gets the burst's). The soft choice, widening by w extra
(variational-Bayes style), was measured first and dropped: with the burst's variance 100x the
steady one on rl_jackal.bag, the prior's w alone tripled a steady sample's S (docs/design/
tuning.md, session 23). The innovation's density under the model, the likelihood ``ddfuse
tune`` fits, is the mixture's itself (:meth:`SpeedTails.nll`).

Where no sample tells the components apart (the smoother's held sample ageing past its span)
the walk's density is the mixture's mean, (1 - p) steady^2 + p burst^2.

Units: m/s, s; variances (m/s)^2. Design and measured figures: docs/design/tuning.md
("Measured, session 23: the heavy-tailed twist walk").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["DEFAULT_SHARE", "SpeedBursts", "SpeedTails", "held_speed_walk"]

# robot.twist_walk.burst_share when only speed_burst is stated: a burst in one speed interval
# in twenty
DEFAULT_SHARE = 0.05


@dataclass(frozen=True)
class SpeedTails:
    """The mixture's densities ``steady``, ``burst`` (m/s/sqrt(s), burst > steady) and the
    burst's prior probability ``share`` per speed interval (0 < share < 1)."""

    steady: float
    burst: float
    share: float = DEFAULT_SHARE

    @classmethod
    def from_robot(cls, robot) -> SpeedTails | None:
        """The model a ``RobotConfig`` states, or None (the Gaussian walk) without
        ``twist_walk.speed_burst``."""
        tw = robot.twist_walk
        if "speed_burst" not in tw or "speed" not in tw:  # (the config refuses the latter)
            return None
        return cls(tw["speed"], tw["speed_burst"], tw.get("burst_share", DEFAULT_SHARE))

    def extra(self, dt: float) -> float:
        """Variance ((m/s)^2) a burst adds to the speed over ``dt`` s beyond the steady walk."""
        return (self.burst * self.burst - self.steady * self.steady) * max(dt, 0.0)

    def weight(self, nu: float, s: float, extra: float) -> float:
        """Posterior probability of the burst given innovation ``nu`` (m/s) whose variance is
        ``s`` under the steady walk and ``s + extra`` under the burst."""
        if extra <= 0.0:
            return 0.0
        sb = s + extra
        # log of the burst's over the steady's weighted density
        a = (math.log(self.share / (1.0 - self.share)) - 0.5 * math.log(sb / s)
             + 0.5 * nu * nu * (1.0 / s - 1.0 / sb))
        return 1.0 / (1.0 + math.exp(-a)) if a > -700.0 else 0.0

    def widening(self, nu: float, s: float, extra: float) -> float:
        """What the speed's prior variance is widened by ((m/s)^2) for innovation ``nu``
        (m/s) of variance ``s`` under the steady walk: ``extra`` where the burst is the more
        probable component given nu (:meth:`weight` above one half), else 0 (module
        docstring)."""
        return extra if self.weight(nu, s, extra) > 0.5 else 0.0

    def nll(self, nu: float, s: float, extra: float, clip: float = math.inf) -> float:
        """The innovation's negative log density under the mixture, less 0.5 log(2 pi) (as
        ``ddfuse tune``'s Gaussian terms, 0.5 (log S + NIS)); nu^2 clipped at ``clip`` times
        the burst's variance (the tune's gate clip)."""
        sb = s + extra
        q = min(nu * nu, clip * sb)
        ls = -0.5 * (math.log(s) + q / s) + math.log1p(-self.share)
        lb = -0.5 * (math.log(sb) + q / sb) + math.log(self.share)
        hi = max(ls, lb)
        return -(hi + math.log(math.exp(ls - hi) + math.exp(lb - hi)))

    def mean_density(self) -> float:
        """The mixture's mean density ((m/s)^2 per s): (1 - p) steady^2 + p burst^2."""
        p = self.share
        return (1.0 - p) * self.steady * self.steady + p * self.burst * self.burst


class SpeedBursts:
    """An EKF's bookkeeping of the heavy-tailed walk ``tails``: per odometry sensor the stamp
    of its last speed sample, and per speed innovation what the mixture's likelihood needs,
    ``terms[sensor]``: (nu m/s, its variance under the steady walk, the burst's extra
    variance of the measured speed, (m/s)^2), in the order the innovations are logged (read by
    ``ddfuse tune``)."""

    def __init__(self, tails: SpeedTails) -> None:
        self.tails = tails
        self.last: dict[str, float] = {}
        self.terms: dict[str, list[tuple[float, float, float]]] = {}

    def widen(self, P: np.ndarray, sensor: str, t: float, nu: float, r: float, h: np.ndarray,
              g: np.ndarray) -> None:
        """Widen the prior covariance ``P`` (n, n), in place, before the update with
        ``sensor``'s speed sample at ``t`` (innovation ``nu`` m/s, variance ``r``, row ``h``
        (n,) of H): by the burst's extra variance over the time since the sensor's previous
        sample along ``g`` (n,), the states' change per m/s of the true speed, where the burst
        is the more probable component (the first sample: never)."""
        last = self.last.get(sensor)
        self.last[sensor] = t
        extra = 0.0 if last is None else self.tails.extra(t - last)
        gain = float(h @ g)  # the measured speed's change per m/s of the true speed
        s = float(h @ P @ h) + r
        e = extra * gain * gain
        self.terms.setdefault(sensor, []).append((nu, s, e))
        if self.tails.widening(nu, s, e) > 0.0:
            P += extra * np.outer(g, g)


def held_speed_walk(robot) -> float | None:
    """The speed's walk density (m/s/sqrt(s)) where no sample tells a burst from a steady
    stretch (the smoother's ageing of a held sample): the stated ``twist_walk.speed``, or with
    the heavy-tailed walk the square root of the mixture's mean density; None when the config
    states neither."""
    tails = SpeedTails.from_robot(robot)
    if tails is None:
        return robot.twist_walk.get("speed")
    return math.sqrt(tails.mean_density())
