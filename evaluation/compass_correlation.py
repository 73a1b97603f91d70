"""A heading sensor's time-correlated error measured from the data: the ``correlation_time``
(and the stationary sigma) that ``ddfuse inspect`` suggests and ``ddfuse tune`` sets.

An IMU's yaw is its orientation filter's output: from one sample to the next it hardly moves,
while over seconds it wanders. The reference is the gyro: its integral is smooth and, over a
window of ``WINDOW_S`` seconds, wrong only by a constant bias and a scale (least-squares fitted
per window and taken off), so the heading minus the gyro's integral is the compass's error up
to the gyro's small white noise. Its structure function

    D(L) = E[(r(t + L) - r(t))^2] = 2 sigma^2 (1 - exp(-L / tau)) + q L,

over lags L from one sample period to a quarter window, pairs within one window only, is fitted
for a first-order Gauss-Markov error (sigma rad, tau s: the ``correlation_time`` model of
``estimation.heading_correlation``) beside a random walk of density q (rad^2/s: what the
sensor's ``heading_offset_walk`` and the gyro's own noise model). The structure function needs
no window-length choice for its demeaning (an autocorrelation's 1/e time does: the detrending
of each window is a high-pass, and that time then grows with the window).

Its wander by time scale, sqrt(D(L) / L) at the shortest and the longest lag (rad/sqrt(s)),
is what a random walk would state as its density at that scale: equal for a walk, falling with
the lag for a white error, growing for a drift whose rate wanders (an orientation filter's yaw
against its magnetometer). A walk fitted to the samples one by one (``ddfuse tune``'s
likelihood) takes the shortest scale's; over a GPS outage the longest scale's is the one that
moves the heading.

``measure`` returns the fit, or None with the reason when there is no gyro, too few samples, or
the Gauss-Markov part is not identified: tau at the shortest lag or sigma under the samples'
own scatter without a walk (a white error), or tau beyond a quarter of the longest lag or a walk
alone (a wander slower than the lags show: the walk's).
Figures: docs/design/tuning.md ("Measured, session 22").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from ddfuse.estimation.config import Config
from ddfuse.estimation.measurements import GyroYawRate, Heading, Stream

__all__ = ["CompassCorrelation", "drifts", "measure"]

WINDOW_S = 60.0  # s: the gyro's bias and scale are taken as constant over a window
MIN_SAMPLES = 200  # heading samples with a gyro reference, at least
N_LAGS = 25  # lags, geometrically spaced from one sample period to a quarter window
# the level of D must show within the lags: tau at most the largest lag / LEVEL_SPAN (D is at
# 98 % of its level at 4 tau). A walk whose windows are detrended looks like a Gauss-Markov
# error of a tau near a tenth of the window, which this rejects.
LEVEL_SPAN = 4.0
# the longest lag's wander over the shortest's beyond which the error is not one walk: a walk
# with the samples' white scatter on top gives under 1 (the scatter shows at the shortest lag)
DRIFT_RATIO = 2.0


@dataclass(frozen=True)
class CompassCorrelation:
    """The fit of ``measure`` for one heading sensor: ``tau`` (s) and ``sigma`` (rad) of the
    Gauss-Markov part, ``walk`` (rad/sqrt(s)) of the random walk beside it, ``white`` (rad)
    the sample-to-sample scatter (the differences' RMS / sqrt 2), ``n`` samples used; ``tau``
    None when not identified (``reason`` says why). ``wander`` (rad/sqrt(s), rad/sqrt(s), s):
    sqrt(D(L) / L) at the shortest and the longest lag, and that lag (module docstring); None
    when too few lags were measured."""

    sensor: str
    tau: float | None
    sigma: float
    walk: float
    white: float
    n: int
    reason: str = ""
    wander: tuple[float, float, float] | None = None

    def describe(self) -> str:
        """One line for inspect's table / tune's note."""
        if self.tau is None:
            return f"{self.sensor}: correlation time not measured ({self.reason})"
        return (f"{self.sensor}: yaw error against the gyro's integral is Gauss-Markov, "
                f"sigma {self.sigma:.4f} rad, correlation time {self.tau:.1f} s (samples' "
                f"own scatter {self.white:.4f} rad; beside a walk of {self.walk:.4f} "
                f"rad/sqrt(s); {self.n} samples)")


def _model(lag, s2, tau, q):
    return 2.0 * s2 * -np.expm1(-lag / tau) + q * lag


def measure(cfg: Config, stream: Stream, sensor: str,
            window: float = WINDOW_S) -> CompassCorrelation | None:
    """The correlation of heading sensor ``sensor``'s samples in ``stream`` (module
    docstring); None when the config has no gyro (an IMU using ``yaw_rate``) to measure it
    against or the sensor has no samples."""
    from scipy.optimize import curve_fit

    gyros = {s.name for s in cfg.of_kind("imu") if "yaw_rate" in s.use}
    h = [(m.t, m.yaw) for m in stream.measurements if type(m) is Heading and m.sensor == sensor]
    if not gyros or not h:
        return None
    # the heading sensor's own gyro when it has one, else the first
    gyro = sensor if sensor in gyros else sorted(gyros)[0]
    g = [(m.t, m.yaw_rate) for m in stream.measurements
         if type(m) is GyroYawRate and m.sensor == gyro]
    th, yh = np.array(h, float).T
    if len(g) < 2:
        return CompassCorrelation(sensor, None, 0.0, 0.0, 0.0, len(th), "no gyro samples")
    tg, wg = np.array(g, float).T
    inside = (th >= tg[0]) & (th <= tg[-1])
    th, yh = th[inside], np.unwrap(yh[inside])
    ig = np.concatenate(([0.0], np.cumsum(0.5 * (wg[1:] + wg[:-1]) * np.diff(tg))))
    gi = np.interp(th, tg, ig)
    d = yh - gi
    k = np.floor((th - th[0]) / window).astype(int) if len(th) else np.zeros(0, int)
    res = np.full(len(th), np.nan)
    for w in np.unique(k):
        i = k == w
        if i.sum() < MIN_SAMPLES // 4:
            continue
        A = np.column_stack((np.ones(i.sum()), th[i] - th[i].mean(), gi[i]))
        res[i] = d[i] - A @ np.linalg.lstsq(A, d[i], rcond=None)[0]
    ok = np.isfinite(res)
    n = int(ok.sum())
    if n < MIN_SAMPLES:
        return CompassCorrelation(sensor, None, 0.0, 0.0, 0.0, n,
                                  f"{n} samples with a gyro reference, under {MIN_SAMPLES}")
    dt = float(np.median(np.diff(th)))
    same1 = (k[1:] == k[:-1]) & ok[1:] & ok[:-1]
    white = float(np.sqrt(np.mean((res[1:] - res[:-1])[same1] ** 2) / 2.0))
    top = max(2, int(window / 4.0 / dt))
    lags, D = [], []
    for L in np.unique(np.round(np.geomspace(1, top, N_LAGS)).astype(int)):
        same = (k[L:] == k[:-L]) & ok[L:] & ok[:-L]
        if same.sum() >= MIN_SAMPLES // 4:
            lags.append(L * dt)
            D.append(float(np.mean((res[L:] - res[:-L])[same] ** 2)))
    lags_a, D_a = np.array(lags), np.array(D)
    if len(lags_a) < 5 or not (D_a > 0.0).all():
        return CompassCorrelation(sensor, None, 0.0, 0.0, white, n, "too few lags to fit")
    lo_tau, hi_tau = lags_a[0], lags_a[-1]
    wander = (math.sqrt(D_a[0] / lo_tau), math.sqrt(D_a[-1] / hi_tau), float(hi_tau))
    try:
        (s2, tau, q), _ = curve_fit(_model, lags_a, D_a, p0=(0.5 * D_a[-1], 0.1 * hi_tau, 0.0),
                                    bounds=((0.0, 0.1 * lo_tau, 0.0), (np.inf, 10.0 * hi_tau,
                                                                       np.inf)),
                                    sigma=D_a)  # relative errors: every lag counts alike
    except (RuntimeError, ValueError) as e:
        return CompassCorrelation(sensor, None, 0.0, 0.0, white, n, f"fit failed: {e}",
                                  wander)
    sigma, walk = math.sqrt(s2), math.sqrt(q)
    walked = walk * math.sqrt(hi_tau) > white  # the walk's share at the longest lag shows
    if tau <= lo_tau or (sigma <= white and not walked):
        return CompassCorrelation(sensor, None, sigma, walk, white, n,
                                  "the error is white from one sample to the next", wander)
    if tau >= hi_tau / LEVEL_SPAN or sigma <= white:
        return CompassCorrelation(sensor, None, sigma, walk, white, n, (
            f"the error keeps growing over {hi_tau:.0f} s of lag, like a walk or a drift (the "
            f"heading offset's walk models that{_faster(wander)})"), wander)
    return CompassCorrelation(sensor, float(tau), sigma, walk, white, n, wander=wander)


def drifts(wander: tuple[float, float, float] | None) -> bool:
    """Whether ``wander`` grows with the lag by more than ``DRIFT_RATIO``: a drift whose rate
    wanders, faster at long lags than any one walk density states."""
    return wander is not None and wander[1] > DRIFT_RATIO * wander[0]


def _faster(wander: tuple[float, float, float] | None) -> str:
    if not drifts(wander):
        return ""
    short, long_, lag = wander
    return (f", as a walk only to a point: it wanders at {short:.2g} rad/sqrt(s) from one "
            f"sample to the next and at {long_:.2g} over {lag:.0f} s")
