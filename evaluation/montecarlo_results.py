"""A Monte Carlo run's results as typed records: what ``montecarlo.monte_carlo`` returns and
``mc_<scenario>.json`` serialises.

``MonteCarloRun`` holds the settings, one ``SeedRun`` per seed (per estimator a ``SeedScores``:
position RMSE m against the exact truth, mean pose NEES, runtime s, the calibration states'
final errors) and per estimator the across-seed ``EstimatorSummary`` (average NEES and its
chi-square band, RMSE against dead reckoning's, the calibration summary). The NEES convention
is in docs/design/monte-carlo-nees.md.

``to_json()`` gives the dictionaries the JSON file holds, keys in the order users already
read; ``from_json(d)`` reads one back (an absent key: None). A key a record leaves out where
it does not apply (an estimator that produced no output has no ``pose_error`` and no
``calibration``; ``per_seed`` entries carry no ``ticks``/``nees`` series) is left out of
``to_json`` as well.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import ClassVar

from ddfuse.evaluation.scores import Record, read_each, read_values


@dataclass(frozen=True)
class CalibrationError(Record):
    """A calibration state's final error against the simulated truth (SI), and that error
    over the estimator's sigma (``z``; None without a sigma)."""

    error: float | None = None
    z: float | None = None


@dataclass(frozen=True)
class SeedScores(Record):
    """One estimator on one seed. ``ticks``/``nees``: the output tick indices (10 Hz) and
    NEES of its samples, for the across-seed average (None once dropped: ``lean``)."""

    pose_error: str | None = None
    rmse_m: float | None = None
    nees_mean: float | None = None
    runtime_s: float | None = None
    error: str | None = None
    ticks: list[int] | None = None
    nees: list[float] | None = None
    calibration: dict[str, CalibrationError] | None = None
    READ: ClassVar = {"calibration": read_values(CalibrationError.from_json)}
    OMIT_NONE: ClassVar = frozenset({"pose_error", "ticks", "nees", "calibration"})


@dataclass(frozen=True)
class SeedRun(Record):
    """One seed: its drawn truth (``true_geometry`` [wheel radius, track width] m,
    ``initial_error`` [dx m, dy m, dyaw rad]), every estimator's scores, dead reckoning's RMSE
    (m) and the seed's wall time (s, where measured)."""

    seed: int | None = None
    scenario: str | None = None
    duration_s: float | None = None
    true_geometry: list[float] | None = None
    initial_error: list[float] | None = None
    estimators: dict[str, SeedScores] = field(default_factory=dict)
    dr_rmse_m: float | None = None
    wall_s: float | None = None
    READ: ClassVar = {"estimators": read_values(SeedScores.from_json)}
    OMIT_NONE: ClassVar = frozenset({"wall_s"})

    def lean(self) -> SeedRun:
        """Without the per-sample NEES series (what ``MonteCarloRun.per_seed`` keeps)."""
        return replace(self, estimators={n: replace(e, ticks=None, nees=None)
                                         for n, e in self.estimators.items()})


@dataclass(frozen=True)
class CalibrationSummary(Record):
    """A calibration state over the runs that did not fail: how many, the mean and RMS of the
    final error, the RMS of error / sigma (about 1 for a consistent estimator)."""

    n: int | None = None
    error_mean: float | None = None
    error_rms: float | None = None
    z_rms: float | None = None


@dataclass(frozen=True)
class EstimatorSummary(Record):
    """One estimator across the seeds (``montecarlo.aggregate``): RMSE per seed, mean and max
    (m), dead reckoning's mean RMSE and the ratios to it, mean runtime (s), the errors raised,
    the ANEES over ``ticks`` common ticks with its ``band`` (None for dead reckoning)."""

    runs: int | None = None
    seeds: list[int] = field(default_factory=list)
    rmse_m: list[float] = field(default_factory=list)
    rmse_mean: float | None = None
    rmse_max: float | None = None
    dr_rmse_mean: float | None = None
    ratio: float | None = None
    ratio_min: float | None = None
    runtime_mean: float | None = None
    nees_mean_per_seed: list[float] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    dim: int | None = None
    calibration: dict[str, CalibrationSummary] = field(default_factory=dict)
    anees: float | None = None
    band: list[float] | None = None
    anees_in_band: bool | None = None
    frac_ticks_in_band: float | None = None
    ticks: int | None = None
    READ: ClassVar = {"calibration": read_values(CalibrationSummary.from_json)}


@dataclass(frozen=True)
class MonteCarloRun(Record):
    """A Monte Carlo run (``montecarlo.monte_carlo``): its settings, the seeds' results and
    the per-estimator summary."""

    scenario: str | None = None
    seeds: list[int] = field(default_factory=list)
    duration_s: float | None = None
    estimators_requested: list[str] | None = None
    fixed_truth: bool | None = None
    lag_s: float | None = None
    per_seed: list[SeedRun] = field(default_factory=list)
    summary: dict[str, EstimatorSummary] = field(default_factory=dict)
    nees_convention: str | None = None
    READ: ClassVar = {"per_seed": read_each(SeedRun.from_json),
                      "summary": read_values(EstimatorSummary.from_json)}
