"""Whether a sensor's innovations are white at the rate the tuning EKF fuses it, from one run's
innovation log (``ddfuse tune`` reports it after the search).

The likelihood of ``evaluation.tune`` assumes independent innovations. Under a right model an
EKF's innovations are white whatever the state's uncertainty, so their normalised values
z_k = nu_k / sqrt(S_k) (scalar innovations, in stream order, the gate's rejections left out)
have no autocorrelation. A sensor whose errors are correlated in time beyond what the model
states (an IMU's yaw from its own orientation filter: smooth from sample to sample, wandering
over seconds) leaves them correlated. Two figures say how much:

* rho_l, the autocorrelation at lag l samples; under white innovations rho_1 is N(0, 1 / n);
* the integrated autocorrelation time tau = 1 + 2 sum_{l >= 1} rho_l (samples; 1 for white:
  Sokal's window, the sum up to the first lag M >= ``SOKAL_C`` tau(M)): n samples carry the
  information of about n / tau independent ones.

And what it costs an estimator that fuses the sensor at a coarser spacing: the mean of m
consecutive normalised innovations has the variance g(m) / m, g(m) = 1 + 2 sum_{l < m}
(1 - l / m) rho_l, where white ones give 1 / m. A smoother that averages m samples per
keyframe into one factor is then over-confident about it by about g(m) (its NIS about g(m)
times the EKF's). Measured: docs/design/tuning.md, "Measured, session 24".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from ddfuse.estimation.config import Config
from ddfuse.estimation.measurements import GpsFix, Stream

__all__ = ["MIN_CORRELATION", "MIN_SAMPLES", "SOKAL_C", "Z_SCORE", "Whiteness", "autocorrelation",
           "coarse_factor", "integrated_time", "keyframe_spacing", "whiteness"]

MIN_CORRELATION = 0.1  # lag-1 correlation from which a sensor is reported as not white
Z_SCORE = 3.0  # ... and beyond what white innovations give by chance (rho_1 sqrt(n))
MIN_SAMPLES = 100  # fewer accepted scalar innovations of a sensor tell nothing
SOKAL_C = 5.0  # the autocorrelation's sum stops at the first lag M >= SOKAL_C tau(M)
MAX_LAG = 2000  # lags summed at most (the window stops long before on real sensors)


@dataclass(frozen=True)
class Whiteness:
    """One sensor kind's figures: ``n`` accepted scalar innovations, ``period`` (s, their
    median spacing), ``rho1`` the lag-1 autocorrelation of the normalised innovations, ``tau``
    the integrated autocorrelation time (samples), ``coarse`` ({m: g(m)}) the over-confidence
    of an average of m samples (module docstring)."""

    sensor: str
    kind: str
    n: int
    period: float
    rho1: float
    tau: float
    coarse: dict[int, float]

    @property
    def white(self) -> bool:
        """Whether the innovations pass as white: rho_1 under ``MIN_CORRELATION`` or within
        ``Z_SCORE`` standard errors of white innovations' 0."""
        return not (self.rho1 >= MIN_CORRELATION and self.rho1 * math.sqrt(self.n) >= Z_SCORE)

    def describe(self) -> str:
        """One line for tune's report."""
        head = (f"{self.sensor} {self.kind}: lag-1 correlation of the normalised innovations "
                f"{self.rho1:.2f} over {self.n} (white: within {Z_SCORE / math.sqrt(self.n):.2g})")
        if self.white:
            return head + ": white enough"
        text = (head + f"; integrated autocorrelation time {self.tau:.1f} samples "
                f"({self.tau * self.period:.2g} s): not white at its rate (the likelihood counts "
                f"its {self.n} samples as independent; they carry about {self.n / self.tau:.0f} "
                "samples' worth)")
        for m, g in sorted(self.coarse.items()):
            text += (f"; an average of {m} samples ({m * self.period:.2g} s, a smoother's "
                     f"keyframe) is over-confident about it by about {g:.1f}x")
        return text


def autocorrelation(z: np.ndarray, max_lag: int) -> np.ndarray:
    """rho_1 .. rho_max_lag of ``z`` (its mean taken off), by FFT; (max_lag,)."""
    z = np.asarray(z, float) - float(np.mean(z))
    n = len(z)
    size = 1 << int(math.ceil(math.log2(2 * n)))
    f = np.fft.rfft(z, size)
    acov = np.fft.irfft(f * np.conj(f), size)[:max_lag + 1]
    return acov[1:] / acov[0] if acov[0] > 0.0 else np.zeros(max_lag)


def integrated_time(rho: np.ndarray) -> float:
    """1 + 2 sum rho_l, summed up to Sokal's window (module docstring), samples."""
    tau = 1.0
    for m in range(1, len(rho) + 1):
        tau = 1.0 + 2.0 * float(np.sum(rho[:m]))
        if m >= SOKAL_C * tau:
            break
    return max(tau, 1.0 / len(rho) if len(rho) else 1.0)


def coarse_factor(rho: np.ndarray, m: int) -> float:
    """g(m): the variance of the mean of ``m`` consecutive normalised innovations over white
    ones' (module docstring)."""
    lags = np.arange(1, min(m, len(rho) + 1))
    return float(1.0 + 2.0 * np.sum((1.0 - lags / m) * rho[:len(lags)]))


def whiteness(innovations, spans: dict[tuple[str, str], float] | None = None
              ) -> list[Whiteness]:
    """Per (sensor, kind) of scalar innovations in the log ``innovations`` (an iterable of
    ``Innovation``, in log order) with at least ``MIN_SAMPLES`` accepted ones, its
    ``Whiteness``. ``spans``: (sensor, kind) -> a spacing (s) at which another estimator fuses
    it (a smoother's keyframe interval): g(m) for m = that spacing over the sensor's period."""
    by: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for e in innovations:
        if not e.accepted or e.residual is None:  # (None: folded out of a short log)
            continue
        r = np.asarray(e.residual, float).ravel()
        if r.size != 1:
            continue
        s = float(np.asarray(e.cov, float).ravel()[0])
        if not s > 0.0:
            continue
        by.setdefault((e.sensor, e.kind), []).append((e.t, float(r[0]) / math.sqrt(s)))
    out = []
    for (sensor, kind), rows in by.items():
        if len(rows) < MIN_SAMPLES:
            continue
        a = np.asarray(rows, float)
        ok = np.isfinite(a[:, 1])
        a = a[ok]
        if len(a) < MIN_SAMPLES:
            continue
        dt = np.diff(a[:, 0])
        period = float(np.median(dt[dt > 0.0])) if np.any(dt > 0.0) else math.nan
        rho = autocorrelation(a[:, 1], min(MAX_LAG, len(a) // 4))
        coarse = {}
        span = (spans or {}).get((sensor, kind))
        if span and period > 0.0 and span > 1.5 * period:
            m = int(round(span / period))
            coarse[m] = coarse_factor(rho, m)
        out.append(Whiteness(sensor, kind, len(a), period, float(rho[0]), integrated_time(rho),
                             coarse))
    return out


def keyframe_spacing(cfg: Config, stream: Stream) -> float:
    """The smoother's keyframe spacing on ``stream`` (s): with ``smoother.keyframe: gps`` and GPS
    fixes, their median spacing, at most the gap ``smoother.keyframe_rate`` closes; else
    1 / ``keyframe_rate``. The smoothers average the heading samples of each interval into one
    factor, so this is the spacing at which they fuse a compass."""
    gap = 1.0 / cfg.smoother.keyframe_rate
    if cfg.smoother.keyframe != "gps":
        return gap
    t = np.array([m.t for m in stream.measurements if type(m) is GpsFix])
    d = np.diff(t)
    d = d[d > 0.0]
    return min(float(np.median(d)), gap) if len(d) else gap
