"""Filter consistency: NIS per sensor, NEES, chi-square bands and a Pass / Warn / Fail verdict.

Pure math on arrays (no I/O, no plotting). A consistent estimator's normalised errors are
chi-square distributed: the NIS r^T S^-1 r of an m-dimensional innovation with m degrees of
freedom, the pose NEES with 3 (2 when the reference has no heading). So about 5% of the values
fall outside the two-sided 95% band [chi2(0.025, m), chi2(0.975, m)], and their mean is m.

Verdict (``verdict``), from n >= ``MIN_SAMPLES`` values, each judged against the band of its own
dimension:

* Pass: at most 10% outside the band AND mean / expected mean in [0.5, 2];
* Warn: at most 25% outside AND the ratio in [0.25, 4];
* Fail: anything else. Too many values above the band (ratio > 1) means the estimator is
  over-confident (its covariance too small for its errors, or the sensor's noise is understated);
  too many below (ratio < 1) means it is pessimistic (noise overstated).

The thresholds are deliberately wider than the 5% a perfect filter gives: real sensors are never
exactly Gaussian and white, and samples close in time are correlated, so a few more outside the
band is normal; 10% is twice the nominal rate, 25% five times. The mean ratio catches a filter
whose values sit inside the band but all at one end of it.

The fraction outside the band counts every innovation, those the gate rejected too (a rejected
one is above the band): leaving them out would hide a filter that rejects a sensor because it is
itself wrong. The mean counts the accepted ones only: one outlier 40 sigma off (a GPS multipath
jump, which the gate exists to reject) adds 1600 to a sum whose expectation per value is the
dimension, so with rejected ones included a 2 % rate of such outliers made a correct filter's
mean 18 times the expected one (simulated gps-outage) and the verdict 'over-confident'. A
filter that rejects valid data still fails on the fraction: 10 % wrongly rejected is 10 %
outside.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field, fields

import numpy as np
from ddfuse.estimation import chi2
from ddfuse.estimation.estimator import NIS_BAND_P, InnovationLog

BAND_P = NIS_BAND_P  # two-sided probability of the band
PASS_OUTSIDE, WARN_OUTSIDE = 0.10, 0.25
PASS_RATIO, WARN_RATIO = (0.5, 2.0), (0.25, 4.0)
MIN_SAMPLES = 20


def chi2_band(dof: float, n_avg: int = 1, p: float = BAND_P) -> tuple[float, float]:
    """Two-sided ``p`` band of the average of ``n_avg`` independent chi-square(``dof``) values
    (the band of a single value when ``n_avg`` is 1; of a Monte Carlo average over ``n_avg``
    runs otherwise: chi2(n dof) / n)."""
    a = (1.0 - p) / 2.0
    k = n_avg * dof
    return chi2.ppf(a, k) / n_avg, chi2.ppf(1.0 - a, k) / n_avg


def verdict(outside: float, ratio: float, n: int) -> str | None:
    """'Pass', 'Warn' or 'Fail' from the fraction outside the band and mean / expected (module
    docstring); None with fewer than MIN_SAMPLES values."""
    if n < MIN_SAMPLES or not np.isfinite(ratio):
        return None
    if outside <= PASS_OUTSIDE and PASS_RATIO[0] <= ratio <= PASS_RATIO[1]:
        return "Pass"
    if outside <= WARN_OUTSIDE and WARN_RATIO[0] <= ratio <= WARN_RATIO[1]:
        return "Warn"
    return "Fail"


@dataclass
class Consistency:
    """Summary of chi-square distributed values (NIS or NEES) of known dimensions.

    ``dof``: the dimension when all values share one, else the mean dimension; ``expected``: the
    mean dimension (a consistent estimator's mean); ``band``: the 95% band of one value when
    all share a dimension, else None; ``below``/``above``/``outside``: fractions of values
    below / above / outside the band of their own dimension."""

    n: int
    dof: float
    mean: float
    expected: float
    ratio: float
    band: tuple[float, float] | None
    below: float
    above: float
    outside: float
    verdict: str | None

    def as_dict(self) -> dict:
        return asdict(self)

    def brief(self) -> str:
        """'6.88 Fail': the mean and the verdict (the mean alone without one), for one line."""
        return f"{self.mean:.2f} {self.verdict}" if self.verdict else f"{self.mean:.2f}"

    def to_json(self) -> dict:
        """``as_dict`` with the band as a list, as metrics.json holds it."""
        d = asdict(self)
        d["band"] = None if self.band is None else list(self.band)
        return d

    @classmethod
    def from_json(cls, d: dict) -> Consistency:
        """From ``to_json``'s dictionary (an absent key: None)."""
        kw = {f.name: d.get(f.name) for f in fields(cls)}
        kw["band"] = None if kw["band"] is None else tuple(kw["band"])
        return cls(**kw)


def summarize(values: np.ndarray, dofs: np.ndarray | int,
              accepted: np.ndarray | None = None) -> Consistency:
    """Consistency of ``values`` (N,), each chi-square with ``dofs`` (N,) or a common dof.
    ``accepted`` (N,) bool, for innovations: the mean (and the dimension it is compared with)
    over the accepted ones only, the fractions outside the band over all (module docstring)."""
    v = np.asarray(values, float)
    d = np.broadcast_to(np.asarray(dofs, float), v.shape)
    ok = np.isfinite(v)
    acc = None if accepted is None else np.asarray(accepted, bool)[ok]
    v, d = v[ok], d[ok]
    n = len(v)
    if n == 0:
        nan = float("nan")
        return Consistency(0, nan, nan, nan, nan, None, nan, nan, nan, None)
    lo, hi = np.empty(n), np.empty(n)
    for dim in np.unique(d):
        sel = d == dim
        lo[sel], hi[sel] = chi2_band(float(dim))
    below, above = float(np.mean(v < lo)), float(np.mean(v > hi))
    m = acc if acc is not None and acc.any() else np.ones(n, bool)
    expected = float(d[m].mean())
    mean = float(v[m].mean())
    ratio = mean / expected
    single = len(np.unique(d)) == 1
    return Consistency(n, float(d[0]) if single else expected, mean, expected, ratio,
                       (float(lo[0]), float(hi[0])) if single else None, below, above,
                       below + above, verdict(below + above, ratio, n))


@dataclass
class InnovationTable:
    """An estimator's innovation log as arrays (N,): stamp s, sensor name, measurement kind,
    NIS, innovation dimension, and whether the gate accepted it.

    ``folded``: for a long run's log (``estimation.estimator.InnovationLog``), the exact counts
    of the entries that are no longer held one by one, (sensor, kind, dim) -> [count, accepted,
    finite count, NIS sum, below band, above band]; the arrays then hold a thinned subset of
    those entries (for plots) followed by every recent one. ``nis_by_sensor`` counts both."""

    t: np.ndarray
    sensor: np.ndarray  # str
    kind: np.ndarray  # str
    nis: np.ndarray
    dim: np.ndarray  # int
    accepted: np.ndarray  # bool
    folded: dict = field(default_factory=dict)
    n_thinned: int = 0  # leading entries of the arrays that stand for folded ones

    @classmethod
    def from_innovations(cls, innovations: Iterable) -> InnovationTable:
        """From an ``ddfuse.estimation.estimator.InnovationLog`` or ``Innovation`` records."""
        if isinstance(innovations, InnovationLog):
            c = innovations.columns()
            return cls(c["t"], c["sensor"], c["kind"], c["nis"], c["dim"], c["accepted"],
                       innovations.folded_by_group(), len(c["t"]) - len(innovations._t))
        inn = list(innovations)
        return cls(np.array([i.t for i in inn], float),
                   np.array([i.sensor for i in inn], dtype=str),
                   np.array([i.kind for i in inn], dtype=str),
                   np.array([i.nis for i in inn], float),
                   np.array([len(np.atleast_1d(i.residual)) for i in inn], int),
                   np.array([bool(i.accepted) for i in inn], bool))

    def __len__(self) -> int:
        return len(self.t)

    def groups(self) -> dict[str, np.ndarray]:
        """Label 'sensor kind' -> boolean mask, in order of first appearance."""
        out: dict[str, np.ndarray] = {}
        # the earliest entry not yet in a group starts the next: a mask per group and nothing
        # per entry (a long log has ~30 000 of them and a handful of groups)
        left = np.ones(len(self.t), bool)
        while left.any():
            i = int(left.argmax())
            s, k = self.sensor[i], self.kind[i]
            mask = (self.sensor == s) & (self.kind == k)
            out[f"{s} {k}"] = mask
            left &= ~mask
        return out


@dataclass
class SensorNis:
    """NIS consistency and gate counts of one sensor's measurements of one kind."""

    sensor: str
    kind: str
    accepted: int
    rejected: int
    nis: Consistency

    def as_dict(self) -> dict:
        return {"sensor": self.sensor, "kind": self.kind, "accepted": self.accepted,
                "rejected": self.rejected, **self.nis.as_dict()}

    def to_json(self) -> dict:
        """metrics.json's ``nis`` entry: the counts and the consistency in one dictionary."""
        return {"sensor": self.sensor, "kind": self.kind, "accepted": self.accepted,
                "rejected": self.rejected, **self.nis.to_json()}

    @classmethod
    def from_json(cls, d: dict) -> SensorNis:
        return cls(d.get("sensor"), d.get("kind"), d.get("accepted"), d.get("rejected"),
                   Consistency.from_json(d))


def _summarize_counts(per_dim: dict[int, list]) -> Consistency:
    """``summarize`` from per-dimension [finite count, NIS sum, below, above, accepted finite
    count, their NIS sum]."""
    n = sum(v[0] for v in per_dim.values())
    if n == 0:
        nan = float("nan")
        return Consistency(0, nan, nan, nan, nan, None, nan, nan, nan, None)
    below = sum(v[2] for v in per_dim.values()) / n
    above = sum(v[3] for v in per_dim.values()) / n
    n_acc = sum(v[4] for v in per_dim.values())
    c, s = (4, 5) if n_acc else (0, 1)
    expected = sum(d * v[c] for d, v in per_dim.items()) / (n_acc or n)
    mean = sum(v[s] for v in per_dim.values()) / (n_acc or n)
    ratio = mean / expected
    dims = [d for d, v in per_dim.items() if v[0]]
    single = len(dims) == 1
    band = chi2_band(float(dims[0])) if single else None
    return Consistency(n, float(dims[0]) if single else expected, mean, expected, ratio, band,
                       below, above, below + above, verdict(below + above, ratio, n))


def nis_by_sensor(table: InnovationTable) -> dict[str, SensorNis]:
    """Per 'sensor kind' (e.g. '/fix gps'): NIS consistency of its innovations (``summarize``
    with the gate's decisions) and how many the gate accepted and rejected (the folded ones
    of a long run's log included)."""
    out = {}
    held = np.arange(len(table.t)) >= table.n_thinned
    labels = {f"{s} {k}": (s, k) for s, k, _ in table.folded}
    for label, sel in table.groups().items():
        labels.setdefault(label, (str(table.sensor[sel][0]), str(table.kind[sel][0])))
    groups = table.groups()
    for label, (sensor, kind) in labels.items():
        sel = groups.get(label, np.zeros(len(table.t), bool))
        folded = {d: v for (s, k, d), v in table.folded.items() if (s, k) == (sensor, kind)}
        if not folded:
            acc = int(table.accepted[sel].sum())
            out[label] = SensorNis(sensor, kind, acc, int(sel.sum()) - acc,
                                   summarize(table.nis[sel], table.dim[sel],
                                             table.accepted[sel]))
            continue
        sel = sel & held
        acc = int(table.accepted[sel].sum()) + sum(v[1] for v in folded.values())
        count = int(sel.sum()) + sum(v[0] for v in folded.values())
        per_dim = {d: [v[2], v[3], v[4], v[5], v[6], v[7]] for d, v in folded.items()}
        v, dims, accd = table.nis[sel], table.dim[sel], table.accepted[sel]
        ok = np.isfinite(v)
        v, dims, accd = v[ok], dims[ok], accd[ok]
        for d in np.unique(dims).tolist():
            x = v[dims == d]
            xa = x[accd[dims == d]]
            lo, hi = chi2_band(float(d))
            a = per_dim.setdefault(int(d), [0, 0.0, 0, 0, 0, 0.0])
            a[0] += len(x)
            a[1] += float(x.sum())
            a[2] += int((x < lo).sum())
            a[3] += int((x > hi).sum())
            a[4] += len(xa)
            a[5] += float(xa.sum())
        out[label] = SensorNis(sensor, kind, acc, count - acc, _summarize_counts(per_dim))
    return out


def average_nees(runs: Sequence[np.ndarray]) -> np.ndarray:
    """Element-wise mean over Monte Carlo runs of per-time NEES arrays (each (N_k,), the same
    time grid), truncated to the shortest run. Its band is ``chi2_band(dof, len(runs))``."""
    if not runs:
        return np.zeros(0)
    n = min(len(r) for r in runs)
    return np.mean(np.stack([np.asarray(r, float)[:n] for r in runs]), axis=0)
