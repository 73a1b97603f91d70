"""A run's scores as typed records: what ``pipeline.score`` returns and metrics.json serialises.

``RunSummary`` holds the run (data span, GPS hold-out counts, outages, the GPS antenna model,
the data facts, warnings, wall times) and one ``EstimatorScores`` per track (ATE, RPE, NEES,
GPS hold-out, outage drift, NIS per sensor, calibration states). Each record's ``to_json()``
gives the dictionary metrics.json holds, with the keys and the order users already read
(docs/design/metrics-json.md says what each key means), and ``from_json(d)`` reads one
back: ``from_json(to_json(x)) == x``, and
``to_json(from_json(json.load(f)))`` is the file's content. ``from_json`` takes a partial
dictionary too (an older metrics.json, a hand-built one in a test): an absent key is None.

The records reuse the evaluation modules' own types where they exist: ``metrics.Stats``
(error statistics), ``metrics.Outage`` and ``metrics.OutageDrift`` (GPS outages),
``consistency.Consistency`` (NEES) and ``consistency.SensorNis`` (NIS per sensor).

Values are held as metrics.json holds them: floats rounded to 6 digits (``num``), None where
a value is not finite or cannot be computed (no truth, no hold-out); statistics in the unit
their key names (``heading_deg``: degrees). Timing fields (``decode_s``, ``runtime_s``,
``rtf``, ``update_ms``, ``wall_s``) differ between runs of the same bag, every other value
does not.

    from ddfuse.evaluation.pipeline import score
    s = score(result)                     # RunSummary
    s.estimators["ekf"].ate_rmse_m        # a field
    s.to_json()["estimators"]["ekf"]      # the metrics.json dictionary
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

from ddfuse.evaluation.consistency import Consistency, SensorNis
from ddfuse.evaluation.metrics import Outage, OutageDrift, Stats


def num(v) -> float | None:
    """A float as metrics.json holds it: rounded to 6 digits, None if absent or not finite."""
    return None if v is None or not math.isfinite(v) else round(float(v), 6)


def _rounded(v):
    if isinstance(v, tuple):  # a chi-square band
        return tuple(_rounded(x) for x in v)
    return num(v) if isinstance(v, float) else v


def rounded_record(r):
    """A copy of the flat dataclass ``r`` (Stats, Consistency, OutageDrift ...) with its floats
    (and those in tuple fields) ``num``-rounded, as metrics.json holds them."""
    return type(r)(**{f.name: _rounded(getattr(r, f.name)) for f in fields(r)})


def stats_of(s: Stats, k: float = 1.0) -> Stats | None:
    """``s`` times ``k`` (e.g. rad -> deg), rounded; None for an empty series."""
    return None if s.n == 0 else rounded_record(s.scaled(k))


def to_json(v):
    """The JSON value of ``v``: a record's ``to_json()``, containers walked, tuples as lists."""
    if hasattr(v, "to_json"):
        return v.to_json()
    if isinstance(v, dict):
        return {k: to_json(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [to_json(x) for x in v]
    return v


def _opt(read: Callable) -> Callable:
    """``read`` for a value that may be null."""
    return lambda v: None if v is None else read(v)


def read_each(read: Callable) -> Callable:
    """A list reader from an item reader (``Record.READ``)."""
    return _opt(lambda v: [read(x) for x in v])


def read_values(read: Callable) -> Callable:
    """A dict reader from a value reader (``Record.READ``; a null value stays None)."""
    return _opt(lambda v: {k: (None if x is None else read(x)) for k, x in v.items()})


class Record:
    """A record whose fields are metrics.json keys in order: ``to_json`` writes each (a field
    in ``OMIT_NONE`` only when set), ``from_json`` reads each through ``READ`` (a field not in
    it as it is), an absent key as the field's default."""

    READ: ClassVar[dict[str, Callable]] = {}
    OMIT_NONE: ClassVar[frozenset[str]] = frozenset()

    def to_json(self) -> dict:
        return {f.name: to_json(getattr(self, f.name)) for f in fields(self)
                if not (f.name in self.OMIT_NONE and getattr(self, f.name) is None)}

    @classmethod
    def from_json(cls, d: dict):
        kw = {}
        for f in fields(cls):
            if f.name in d:
                read = cls.READ.get(f.name)
                kw[f.name] = read(d[f.name]) if read and d[f.name] is not None else d[f.name]
        return cls(**kw)


_stats = _opt(Stats.from_json)


@dataclass(frozen=True)
class AteScore(Record):
    """ATE statistics after one alignment: position (m) and heading (deg)."""

    position_m: Stats | None = None
    heading_deg: Stats | None = None
    READ: ClassVar = {"position_m": _stats, "heading_deg": _stats}


@dataclass(frozen=True)
class AteScores(Record):
    """ATE against the truth: ``none`` (no alignment), ``se2`` and ``origin`` alignments (None
    where they cannot be formed), the number of associated ``pairs``, the association window
    ``max_diff_s`` and what the association alone costs (``association_m``)."""

    none: AteScore | None = None
    pairs: int | None = None
    max_diff_s: float | None = None
    association_m: Stats | None = None
    se2: AteScore | None = None
    origin: AteScore | None = None
    READ: ClassVar = {"none": AteScore.from_json, "association_m": _stats,
                      "se2": AteScore.from_json, "origin": AteScore.from_json}


@dataclass(frozen=True)
class RpeScore(Record):
    """RPE over pairs ``delta`` ``unit`` ('s' or 'm') apart: position (m) and heading (deg)
    statistics, and the pairs' actual mean spacing ``mean_delta``."""

    delta: float | None = None
    unit: str | None = None
    mean_delta: float | None = None
    position_m: Stats | None = None
    heading_deg: Stats | None = None
    READ: ClassVar = {"position_m": _stats, "heading_deg": _stats}


@dataclass(frozen=True)
class UpdateLatency(Record):
    """Wall time of an estimator's calls, ms: percentiles, mean, and the number of calls."""

    p50: float | None = None
    p99: float | None = None
    max: float | None = None
    mean: float | None = None
    n: int | None = None


@dataclass(frozen=True)
class CalibrationState(Record):
    """One calibration state at the end of the run, SI units; ``sigma`` None without one."""

    value: float | None = None
    sigma: float | None = None


@dataclass(frozen=True)
class FinalState(Record):
    """An estimator's calibration states (label -> state) at its last estimate, stamp ``t`` s."""

    t: float | None = None
    states: dict[str, CalibrationState] = field(default_factory=dict)
    READ: ClassVar = {"states": read_values(CalibrationState.from_json)}


@dataclass(frozen=True)
class EstimatorScores(Record):
    """One track's scores (metrics.json ``estimators.<track>``; docs/design/metrics-json.md)."""

    final_xy: tuple[float | None, float | None] | None = None
    samples: int | None = None
    ate_rmse_m: float | None = None
    ate_max_m: float | None = None
    ate_association_rmse_m: float | None = None
    rpe_rmse_m: float | None = None
    yaw_rmse_deg: float | None = None
    nees_mean: float | None = None
    gps_holdout_rmse_m: float | None = None
    gps_holdout_span_s: tuple[float | None, float | None] | None = None
    gps_residual_corr_s: float | None = None
    runtime_s: float | None = None
    rtf: float | None = None
    update_ms: UpdateLatency | None = None
    ate: AteScores | None = None
    rpe: dict[str, RpeScore | None] | None = None
    nees: Consistency | None = None
    gps_holdout_m: Stats | None = None
    # the withheld fixes' distance normalised by the track's position covariance plus the fix's
    # own (2 dof): whether the estimator's covariance covers its hold-out error
    gps_holdout_nees: Consistency | None = None
    gps_outages: list[OutageDrift] | None = None
    nis: dict[str, SensorNis] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)  # "sensor: reason" -> count
    events: list[str] = field(default_factory=list)
    events_total: int | None = None
    error: str | None = None
    final_state: FinalState | None = None
    pose_error: str = "world"
    rpe_note: str | None = None
    ate_common_rmse_m: float | None = None
    span_s: tuple[float | None, float | None] | None = None
    READ: ClassVar = {
        "final_xy": tuple, "gps_holdout_span_s": tuple, "span_s": tuple,
        "update_ms": UpdateLatency.from_json, "ate": AteScores.from_json,
        "rpe": read_values(RpeScore.from_json), "nees": Consistency.from_json,
        "gps_holdout_nees": Consistency.from_json,
        "gps_holdout_m": Stats.from_json, "gps_outages": read_each(OutageDrift.from_json),
        "nis": read_values(SensorNis.from_json), "final_state": FinalState.from_json}
    finish_s: float | None = None  # s in finish() alone, where ``ddfuse bench`` measured it
    OMIT_NONE: ClassVar = frozenset({"rpe_note", "finish_s"})


@dataclass(frozen=True)
class GpsAntenna(Record):
    """The GPS antenna model the hold-out is scored with (``pipeline.gps_antenna``): lever arm
    (x, y) m in the body frame, delay s, the gate's chi-square probability, a note."""

    lever_arm: tuple[float, float] = (0.0, 0.0)
    delay_s: float = 0.0
    gate: float | None = None
    note: str | None = None
    READ: ClassVar = {"lever_arm": tuple}


@dataclass(frozen=True)
class CommonSpan(Record):
    """Where ``ate_common_rmse_m`` is scored: ``stamps`` of track ``of`` in ``span_s``."""

    stamps: int | None = None
    of: str | None = None
    span_s: tuple[float | None, float | None] | None = None
    READ: ClassVar = {"span_s": tuple}


@dataclass(frozen=True)
class SensorFacts(Record):
    """A config sensor: name, topic, kind, what it is used for, messages per type."""

    name: str | None = None
    topic: str | None = None
    kind: str | None = None
    use: list[str] = field(default_factory=list)
    measurements: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class OffsetWindow(Record):
    """One window of a compass's heading-offset survey: [t0, t1] s, the offset (yaw minus GPS
    course) and its sigma, rad, the fixes, their extent m and fit residual m."""

    t0: float | None = None
    t1: float | None = None
    offset_rad: float | None = None
    sigma_rad: float | None = None
    fixes: int | None = None
    extent_m: float | None = None
    residual_m: float | None = None


@dataclass(frozen=True)
class HeadingOffset(Record):
    """A compass's heading offset measured from the GPS course without any estimator
    (``estimation.heading_survey.OffsetSurvey.to_dict()``): median and spread, rad, over
    windows of ``window_s`` s."""

    sensor: str | None = None
    median_rad: float | None = None
    spread_rad: float | None = None
    window_s: float | None = None
    windows: list[OffsetWindow] = field(default_factory=list)
    READ: ClassVar = {"windows": read_each(OffsetWindow.from_json)}


@dataclass(frozen=True)
class GpsBursts(Record):
    """A GPS topic whose fixes disagreed with the odometry's dead reckoning in several episodes
    (``estimation.gps_watch.GpsWatch.bursts``): errors in bursts, as multipath and NLOS give.
    ``episodes``; ``fixes`` flagged in them; ``largest_m`` the largest disagreement, m;
    ``longest_s`` the longest episode, s."""

    topic: str | None = None
    episodes: int | None = None
    fixes: int | None = None
    largest_m: float | None = None
    longest_s: float | None = None

    @classmethod
    def of_watch(cls, watch) -> list[GpsBursts]:
        """Each GPS topic the ``GpsWatch`` ``watch`` (None: not watched) found bursty."""
        if watch is None:
            return []
        return [cls(topic, len(eps), sum(e.fixes for e in eps), num(max(e.size_m for e in eps)),
                    num(max(e.end - e.start for e in eps)))
                for topic, eps in watch.bursts().items()]


@dataclass(frozen=True)
class DataFacts(Record):
    """What the report states about the data (``pipeline.data_facts``)."""

    sensors: list[SensorFacts] | None = None
    ground_truth_topic: str | None = None
    ground_truth_samples: int | None = None
    ground_truth_interval_s: float | None = None
    gps_fixes: int | None = None
    gps_fixes_withheld: int | None = None
    gps_fix_interval_s: float | None = None
    landmarks: int | None = None
    path_length_m: float | None = None
    path_length_from: str | None = None
    t0: float | None = None
    t1: float | None = None
    datum: list[float] | None = None
    heading_offsets: list[HeadingOffset] | None = None
    gps_bursts: list[GpsBursts] | None = None
    READ: ClassVar = {"sensors": read_each(SensorFacts.from_json),
                      "heading_offsets": read_each(HeadingOffset.from_json),
                      "gps_bursts": read_each(GpsBursts.from_json)}


@dataclass(frozen=True)
class WallTimes(Record):
    """``wall_s``: the job's wall time split, s (``pipeline.timing_split``)."""

    startup: float | None = None
    decode: float | None = None
    build: float | None = None
    estimators: dict[str, float | None] = field(default_factory=dict)
    runner: float | None = None
    metrics: float | None = None
    write: float | None = None
    total: float | None = None
    # the estimators fed in a side process (``side_run``): their times overlap the others' and
    # are not in ``total``; ``side_wait`` (in it) is the main process's wait for them after its loop
    side_process: list[str] = field(default_factory=list)
    side_wait: float | None = None


@dataclass(frozen=True)
class RunSummary(Record):
    """A run's results: metrics.json (docs/design/metrics-json.md). ``score`` fills the fields
    up to ``ate_common``; ``run_bag`` the run's settings and facts after it."""

    bag: str | None = None
    duration_s: float | None = None
    decode_s: float | None = None
    messages: int | None = None
    rejected_messages: dict[str, int] = field(default_factory=dict)
    has_ground_truth: bool | None = None
    gps_holdout_fixes: int | None = None
    gps_holdout_scored_fixes: int | None = None
    gps_holdout_outliers: int | None = None
    gps_holdout_interpolation_rmse_m: float | None = None
    gps_holdout_interpolation_outliers: int | None = None
    gps_outages: list[Outage] = field(default_factory=list)
    gps_antenna: GpsAntenna | None = None
    estimators: dict[str, EstimatorScores] = field(default_factory=dict)
    ate_common: CommonSpan | None = None
    config: str | None = None
    initial_pose: Any = None  # [x, y, yaw], 'first ground-truth pose' or None
    lag_s: float | None = None
    gps_model: str | None = None
    gps_model_option: bool | None = None  # True: --gps-model set gps_model, not the config
    estimators_requested: list[str] | None = None
    estimators_run: list[str] | None = None
    gps_holdout: str | None = None
    input_error: str | None = None
    interrupted: str | None = None
    data: DataFacts | None = None
    warnings: list[str] = field(default_factory=list)
    wall_s: WallTimes | None = None
    READ: ClassVar = {
        "gps_outages": read_each(Outage.from_json), "gps_antenna": GpsAntenna.from_json,
        "estimators": read_values(EstimatorScores.from_json), "ate_common": CommonSpan.from_json,
        "data": DataFacts.from_json, "wall_s": WallTimes.from_json}

    @property
    def t0(self) -> float:
        """The data's first stamp (s), 0 where unknown: what times on the page count from."""
        return (self.data.t0 if self.data else None) or 0.0
