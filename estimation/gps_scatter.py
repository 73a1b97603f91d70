"""How well neighbouring GPS fixes predict each fix, and the GPS sensor's ``correlation_time``
that scatter gives: the one measurement and the one rule behind `ddfuse inspect`'s suggested
config, `ddfuse run`'s warning and the shipped configs (docs/design/gps_correlation.md).

Each fix is compared with the time interpolation of its two neighbours. White errors of
per-axis sigma miss it by sqrt(1.5) sigma RMS per axis (evenly spaced fixes; the robot's motion
adds millimetres). A first-order Gauss-Markov error of stationary sigma and correlation time
tau misses it by sigma sqrt((1 - rho)(3 - rho) / 2), rho = exp(-dt / tau), dt the fix interval:
slow errors move the neighbours with the fix. Taking sigma as the fixes' stated (fused) one,
the model every estimator fuses a correlated GPS with (``estimation.gps_correlation``), the
measured miss gives tau.

The rule: a miss under ``CORRELATED_SCATTER`` of the white one (tau over about 6 fix
intervals) means correlated errors, and the recommended ``correlation_time`` is that tau rounded
to whole seconds; otherwise 0 (white). A config whose value is 0 against a recommendation, or
more than ``AGREEMENT`` times off it, gets the advice (``FixScatter.advice``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Fix-to-fix scatter this far below what white errors of the stated sigma give means the errors
# are correlated in time (rl_husky_gps.bag: 0.12 m against 0.98 m)
CORRELATED_SCATTER = 1.0 / 3.0
# a config's correlation_time within this factor of the recommended one agrees with it (the
# estimate's spread: 20 % on 2000 misses, more on a short bag)
AGREEMENT = 2.0
MIN_FIXES = 10  # fewer usable fixes: no scatter to speak of


def scatter_correlation_time(rms: float, sigma: float, dt: float) -> float | None:
    """The correlation time (s) of a first-order Gauss-Markov error of stationary sigma whose
    fixes, ``dt`` s apart, miss the interpolation of their neighbours by ``rms`` per axis: that
    miss has variance sigma^2 (1 - rho)(3 - rho) / 2 with rho = exp(-dt / tau) (1.5 sigma^2 for
    white errors). None when the scatter is that of white errors or more, or none at all."""
    r = (rms / sigma) ** 2
    if not (0.0 < r < 1.5 and dt > 0.0):
        return None
    rho = 2.0 - math.sqrt(1.0 + 2.0 * r)
    if rho >= 1.0:  # no scatter to float precision: a noise-free track, no time to give
        return None
    return -dt / math.log(rho)


@dataclass(frozen=True)
class FixScatter:
    """The neighbour scatter of one GPS's fixes: ``rms`` (m per axis) of each fix minus the
    time interpolation of its neighbours, ``sigma`` (m per axis) the fixes' median stated one,
    ``dt`` (s) their median interval, ``n`` the fixes."""

    rms: float
    sigma: float
    dt: float
    n: int

    @property
    def white(self) -> float:
        """The miss (m per axis) white errors of the stated sigma give."""
        return math.sqrt(1.5) * self.sigma

    @property
    def correlated(self) -> bool:
        return self.rms < CORRELATED_SCATTER * self.white

    @property
    def correlation_time(self) -> float | None:
        """tau (s) of a Gauss-Markov error of the stated sigma with this scatter, or None."""
        return scatter_correlation_time(self.rms, self.sigma, self.dt)

    @property
    def recommended(self) -> int:
        """The GPS sensor's ``correlation_time`` (s) the rule gives: tau rounded (at least 1)
        when the errors are correlated, else 0 (fused as white)."""
        tau = self.correlation_time
        if not self.correlated or tau is None:
            return 0
        return max(1, round(tau))

    def describe(self) -> str:
        """The fact in one sentence: the scatter against white, and what it says."""
        text = (f"the interpolation of the neighbouring fixes predicts a fix to {self.rms:.2f} m "
                f"RMS per axis; white errors of the stated median sigma {self.sigma:.2f} m would "
                f"give {self.white:.2f} m")
        if not self.correlated:
            return text
        text += (": the errors are correlated in time (the stated covariance is their slow "
                 "wander), so a hold-out of single fixes rewards following the GPS; read it with "
                 "the GPS NIS and a longer outage (--gps-holdout window:T0:T1)")
        if self.recommended:
            text += (f". A first-order Gauss-Markov error of the stated sigma with these "
                     f"neighbours has a correlation time of {self.correlation_time:.0f} s "
                     f"(correlation_time: {self.recommended} in the suggested config)")
        return text

    def source(self) -> str:
        """Where the recommended value comes from, for a comment beside it in a config."""
        return (f"s: from the fixes' scatter ({self.n} fixes every {self.dt:.2g} s miss their "
                f"neighbours' interpolation by {self.rms:.2f} m per axis, white errors of the "
                f"stated {self.sigma:.2f} m would by {self.white:.2f} m): a Gauss-Markov error "
                f"of that sigma with tau {self.correlation_time:.1f} s (ddfuse.estimation."
                "gps_scatter; `ddfuse run` warns by the same rule)")

    def advice(self, topic: str, configured: float) -> str | None:
        """The warning for a GPS sensor on ``topic`` whose ``correlation_time`` is
        ``configured`` (s), when it disagrees with the recommendation (module docstring);
        None when it agrees."""
        rec = self.recommended
        if rec == 0 and (configured <= 0.0 or self.correlated):  # correlated: no time to give
            return None
        if configured > 0.0 and rec and 1.0 / AGREEMENT <= configured / rec <= AGREEMENT:
            return None
        facts = (f"{topic}: the neighbouring fixes predict a fix to {self.rms:.2f} m per axis, "
                 f"against {self.white:.2f} m for white errors of the stated sigma "
                 f"{self.sigma:.2f} m")
        if rec == 0:
            return (facts + f": the errors are not correlated over several fixes, but "
                    f"correlation_time is {configured:g} s, which discounts every fix as if "
                    "they were; set correlation_time: 0 under the GPS sensor")
        what = ("the fixes are fused as independent: every estimate follows the GPS's slow "
                "wander and is over-confident about it" if configured <= 0.0 else
                f"correlation_time is {configured:g} s")
        return (facts + f": a Gauss-Markov error of that sigma with a correlation time of "
                f"{self.correlation_time:.0f} s, but {what}; set correlation_time: {rec} under "
                "the GPS sensor (`ddfuse inspect` suggests the same)")


def fix_scatter(t: np.ndarray, xy: np.ndarray, var: np.ndarray) -> FixScatter | None:
    """The neighbour scatter of fixes at stamps ``t`` (N,) s, positions ``xy`` (N, 2) m in a
    local east/north frame, each with per-axis horizontal variance ``var`` (N,) m^2 (half the
    trace of its horizontal covariance, as fused). Fixes with a non-finite value or a variance
    of 0 or below are left out; None with fewer than ``MIN_FIXES`` left."""
    t = np.asarray(t, float)
    xy = np.asarray(xy, float).reshape(len(t), 2)
    var = np.asarray(var, float)
    ok = np.isfinite(t) & np.isfinite(xy).all(axis=1) & np.isfinite(var) & (var > 0.0)
    if ok.sum() < MIN_FIXES:
        return None
    order = np.argsort(t[ok], kind="stable")
    t, p, var = t[ok][order], xy[ok][order], var[ok][order]
    span = t[2:] - t[:-2]
    good = span > 0
    w = ((t[1:-1] - t[:-2])[good] / span[good])[:, None]
    miss = p[1:-1][good] - (p[:-2][good] + w * (p[2:][good] - p[:-2][good]))
    rms = math.sqrt(float((miss * miss).mean()))  # the mean over both axes: per axis
    return FixScatter(rms, math.sqrt(float(np.median(var))), float(np.median(np.diff(t))),
                      len(t))
