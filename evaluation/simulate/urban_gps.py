"""The urban GPS error model: open sky, street canyons with multipath bursts and NLOS jumps,
bridges. Statistics and their defaults: docs/design/urban_gps.md.

Everything is drawn per nominal fix time (s since the start), in the local ENU frame (m),
from the GPS stream's generator after its ordinary draws, so a scenario without
``GpsSpec.urban`` draws exactly what it drew before. The receiver's stated covariance is
``GpsSpec.horizontal_std`` whatever the environment: it stays optimistic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ddfuse.evaluation.simulate.scenarios import UrbanGpsSpec
from ddfuse.evaluation.simulate.sensors import gauss_markov

OPEN, CANYON, MULTIPATH, NLOS = 0, 1, 2, 3  # environment of a fix (UrbanErrors.label)


@dataclass
class UrbanErrors:
    """Per nominal fix: horizontal error (n, 2) m added to the truth, the environment label
    (n,) (OPEN, CANYON, MULTIPATH, NLOS; the worst that applies), and whether the antenna is
    under a bridge (n,) bool: no fix."""

    error: np.ndarray
    label: np.ndarray
    bridge: np.ndarray


def _stretches(rng: np.random.Generator, duration: float, u: UrbanGpsSpec
               ) -> list[tuple[float, float]]:
    """Canyon stretches (start, end) s: open and canyon alternate, starting in the open, each
    stretch exponentially long; the open mean makes ``canyon_fraction`` of the time canyon."""
    if u.canyon_fraction <= 0.0:
        return []
    open_mean = u.canyon_mean_s * (1.0 - u.canyon_fraction) / u.canyon_fraction
    out, t, canyon = [], 0.0, False
    while t < duration:
        d = rng.exponential(u.canyon_mean_s if canyon else max(open_mean, 1e-3))
        if canyon:
            out.append((t, min(t + d, duration)))
        t += d
        canyon = not canyon
    return out


def _events(rng: np.random.Generator, spans: list[tuple[float, float]], rate: float,
            length: tuple[float, float]) -> list[tuple[float, float]]:
    """Poisson events at ``rate`` (1/s) inside ``spans``, each lasting uniform ``length`` s."""
    ev = []
    for a, b in spans:
        t = a + rng.exponential(1.0 / rate) if rate > 0 else b
        while t < b:
            ev.append((t, t + rng.uniform(*length)))
            t += rng.exponential(1.0 / rate)
    return ev


def urban_errors(tm: np.ndarray, duration: float, u: UrbanGpsSpec,
                 rng: np.random.Generator) -> UrbanErrors:
    """The urban errors at nominal fix times ``tm`` (n,) s of a run of ``duration`` s."""
    n = len(tm)
    canyons = _stretches(rng, duration, u)
    in_canyon = np.zeros(n, bool)
    for a, b in canyons:
        in_canyon |= (tm >= a) & (tm < b)
    # the receiver's ordinary error: a slow wander, larger in a canyon
    std = np.where(in_canyon, u.canyon_std, u.open_std)[:, None]
    err = gauss_markov(tm, rng.standard_normal((n, 2)), 1.0, u.base_tau_s) * std
    label = np.where(in_canyon, CANYON, OPEN)
    # multipath: a reflected path's offset, held over the burst with a wobble of a fifth of it
    wobble = gauss_markov(tm, rng.standard_normal((n, 2)), 1.0, u.burst_tau_s)
    for a, b in _events(rng, canyons, u.burst_rate, u.burst_length_s):
        mag, ang = rng.uniform(*u.burst_range), rng.uniform(-np.pi, np.pi)
        sel = (tm >= a) & (tm < b) & in_canyon
        off = mag * np.array((np.cos(ang), np.sin(ang)))
        err[sel] += off + 0.2 * mag * wobble[sel]
        label[sel] = MULTIPATH
    # NLOS: a fix of the reflected signal alone, a jump held for a few fixes
    start = rng.uniform(size=n) < u.nlos_prob
    count = rng.geometric(1.0 / max(u.nlos_mean_fixes, 1.0), size=n)
    mags = rng.uniform(*u.nlos_range, size=n)
    angs = rng.uniform(-np.pi, np.pi, size=n)
    for k in np.flatnonzero(start & in_canyon):
        sel = slice(k, min(k + int(count[k]), n))
        err[sel, 0] += mags[k] * np.cos(angs[k])
        err[sel, 1] += mags[k] * np.sin(angs[k])
        label[sel] = NLOS
    bridge = np.zeros(n, bool)
    for a, b in _events(rng, [(0.0, duration)], u.bridge_rate, u.bridge_length_s):
        bridge |= (tm >= a) & (tm < b)
    return UrbanErrors(err, label, bridge)
