"""Drive any set of estimators over one time-ordered measurement stream.

Every estimator sees the same measurements in the same order (minus GPS fixes withheld for
scoring); the runner records each one's pose trajectory at a steady output rate, the wall time
of every ``process`` call, and, for estimators that also give a lagged (smoothed) output, that
trajectory as a second track named ``<name>_lagged``.
"""

from __future__ import annotations

import gc
import math
import time
from array import array
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from ddfuse.estimation import heap
from ddfuse.estimation.errors import ConfigError, error_line
from ddfuse.estimation.estimator import Estimate, Estimator, EstimatorLog
from ddfuse.estimation.interrupts import deliver, held_signals, interrupt_in, interrupt_name
from ddfuse.estimation.measurements import GpsFix, Stream, truth_at_start
from ddfuse.estimation.spill import SpilledColumn, release

_NAN6 = (math.nan,) * 6
TRACK_BLOCK = 8192  # rows of a spilling TrackBuilder written at a time (640 kB)
# the 3x3 positions of the 6 packed values (xx, xy, xyaw, yy, yyaw, yawyaw), row-major
_UNPACK = np.array((0, 1, 2, 1, 3, 4, 2, 4, 5))


def _pack(c) -> tuple[float, ...]:
    """The 6 distinct values of a 3x3 covariance, each off-diagonal the mean of its two (so an
    exactly symmetric matrix, as every estimator here gives, is kept bit for bit)."""
    v = np.asarray(c, float).ravel().tolist()
    return (v[0], (v[1] + v[3]) * 0.5, (v[2] + v[6]) * 0.5, v[4], (v[5] + v[7]) * 0.5, v[8])


def unpack_cov(packed: np.ndarray) -> np.ndarray:
    """(N, 6) packed covariances (see TrackBuilder) -> (N, 3, 3)."""
    return np.asarray(packed, float).reshape(-1, 6)[:, _UNPACK].reshape(-1, 3, 3)


class TrackBuilder:
    """Estimates appended one at a time, kept as compact columns (stamp, pose, and the 6
    distinct values of the symmetric 3x3 pose covariance: 10 floats each) instead of objects
    with their state arrays: a 2 h run at 10 Hz is 5.8 MB. ``last`` is the last Estimate
    appended, whole (its state too). Indexing gives Estimates with t, pose and pose_cov (the
    last one: ``last`` itself). With ``spill_to`` (a path prefix) the columns' full blocks go
    to files between messages (``spill``) and ``trajectory`` maps them: memory flat however
    long the run."""

    __slots__ = ("_t", "_pose", "_cov", "last", "_spill")

    def __init__(self, spill_to: str | Path | None = None) -> None:
        self.last: Estimate | None = None
        # ``spill_to``: a file name prefix; the columns' full blocks go to <prefix>.t/.pose/.cov
        # (``spill``), the arrays below being the SpilledColumns' tails
        self._spill = None if spill_to is None else tuple(
            SpilledColumn(f"{spill_to}.{c}", "d", k * TRACK_BLOCK)
            for c, k in (("cov", 6), ("pose", 3), ("t", 1)))
        if self._spill is None:
            self._t, self._pose, self._cov = array("d"), array("d"), array("d")
        else:
            self._cov, self._pose, self._t = (c.tail for c in self._spill)

    def spill(self) -> None:
        """Write the full blocks of a spilling builder's columns to their files (the stamps
        last: they count the rows); nothing for one in memory."""
        if self._spill is not None and len(self._t) >= TRACK_BLOCK:
            for c in self._spill:
                c.spill(force=True)

    def append(self, e: Estimate) -> None:
        c = e.pose_cov
        packed = _NAN6 if c is None else _pack(c)
        # The stamp goes in last: it is what counts a row, so a Ctrl-C between these lines
        # leaves a pose or covariance without its stamp, which the readers cut off.
        self._cov.extend(packed)
        self._pose.extend(e.pose)
        self._t.append(e.t)
        self.last = e

    def extend(self, estimates: Iterable[Estimate]) -> None:
        for e in estimates:
            self.append(e)

    def extend_columns(self, t: np.ndarray, pose: np.ndarray, pose_cov: np.ndarray,
                       last: Estimate) -> None:
        """Append N estimates at once: stamps ``t`` (N,) s, poses (N, 3) and their covariances
        (N, 3, 3), as ``append`` of each would (``last``: the N-th, whole)."""
        v = np.asarray(pose_cov, float).reshape(-1, 9)
        packed = np.column_stack((v[:, 0], (v[:, 1] + v[:, 3]) * 0.5, (v[:, 2] + v[:, 6]) * 0.5,
                                  v[:, 4], (v[:, 5] + v[:, 7]) * 0.5, v[:, 8]))
        self._cov.extend(packed.ravel().tolist())
        self._pose.extend(np.asarray(pose, float).ravel().tolist())
        self._t.extend(np.asarray(t, float).tolist())
        self.last = last

    def __len__(self) -> int:
        return len(self._t) + (self._spill[2].spilled if self._spill is not None else 0)

    def __bool__(self) -> bool:
        return len(self) > 0

    def __getitem__(self, i: int) -> Estimate:
        n = len(self)
        if self._spill is not None and self._spill[2].spilled:
            tr = self.trajectory()  # a spilled row is read from the files
            if isinstance(i, slice):
                return [self[j] for j in range(n)[i]]
            i = range(n)[i]
            if i == n - 1 and self.last is not None and self.last.t == tr.t[i]:
                return self.last
            return Estimate(float(tr.t[i]), tuple(tr.pose[i].tolist()),
                            tr.cov_at(slice(i, i + 1))[0])
        if isinstance(i, slice):
            return [self[j] for j in range(n)[i]]
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError("track index out of range")
        if i == n - 1 and self.last is not None and self.last.t == self._t[i]:
            return self.last
        return Estimate(self._t[i], tuple(self._pose[3 * i:3 * i + 3]),
                        unpack_cov(np.array(self._cov[6 * i:6 * i + 6]))[0])

    def __iter__(self):
        return (self[i] for i in range(len(self._t)))

    def trajectory(self) -> Trajectory:
        """The columns as a Trajectory, sharing their memory (no copy: appending to the builder
        afterwards is an error); its ``cov`` is unpacked to (N, 3, 3) when first read. A
        spilling builder's whole columns are memory-mapped from its files
        (``Trajectory.release``)."""
        if self._spill is not None and self._spill[2].spilled:
            (cov, mc), (pose, mp), (t, mt) = (c.mapped() for c in self._spill)
            n = len(t)
            return _PackedTrajectory(t, pose[:3 * n].reshape(n, 3),
                                     packed=cov[:6 * n].reshape(n, 6), maps=(mt, mp, mc))
        n = len(self._t)
        if not n:
            return Trajectory(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)))
        return _PackedTrajectory(np.frombuffer(self._t, float),
                                 np.frombuffer(self._pose, float)[:3 * n].reshape(n, 3),
                                 packed=np.frombuffer(self._cov, float)[:6 * n].reshape(n, 6))


def _no_cov(n: int) -> np.ndarray:
    """(n, 3, 3) NaN, read-only, all one element."""
    return np.broadcast_to(np.float64(np.nan), (n, 3, 3))


@dataclass
class Trajectory:
    """Poses over time in the local frame: ``t`` (N,) s, ``pose`` (N, 3) as (x m, y m, yaw rad),
    ``cov`` (N, 3, 3) world-frame pose covariance (NaN where an estimator gives none)."""

    t: np.ndarray
    pose: np.ndarray
    cov: np.ndarray

    @classmethod
    def from_estimates(cls, estimates: Iterable[Estimate]) -> Trajectory:
        if isinstance(estimates, TrackBuilder):
            return estimates.trajectory()
        est = list(estimates)
        if not est:
            return cls(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)))
        return cls(np.array([e.t for e in est]), np.array([e.pose for e in est], dtype=float),
                   np.array([e.pose_cov if e.pose_cov is not None else np.full((3, 3), np.nan)
                             for e in est], dtype=float))

    @classmethod
    def from_ground_truth(cls, truth) -> Trajectory:
        """From a list of GroundTruthPose, or from a stream's truth arrays (``t`` (N,),
        ``pose`` (N, 3)) given as a tuple. The truth has no covariance: ``cov`` is NaN, a
        read-only view of one value (no memory per sample)."""
        if isinstance(truth, tuple):
            t, pose = truth
            return cls(np.asarray(t, float), np.asarray(pose, float).reshape(-1, 3),
                       _no_cov(len(t)))
        n = len(truth)
        return cls(np.array([g.t for g in truth]),
                   np.array([(g.x, g.y, g.yaw) for g in truth], dtype=float).reshape(n, 3),
                   _no_cov(n))

    def __len__(self) -> int:
        return len(self.t)

    def cov_at(self, index) -> np.ndarray:
        """``cov[index]`` (``index`` a slice or an integer array): what a reader of part of
        the covariances asks for, which a packed track unpacks for those rows only."""
        return self.cov[index]

    def release(self) -> None:
        """Drop from this process's memory the pages of a track read from its spill files
        (``TrackBuilder(spill_to=)``), once a reader is done with them (they are read again
        when next touched); nothing for a track held in memory."""


class _PackedTrajectory(Trajectory):
    """A Trajectory whose covariances stay packed (TrackBuilder's 6 values per pose) until
    ``cov`` is first read: a run that ends holds 10 floats per pose, not 13 (``cov_at``, which
    scoring and the writers read through, unpacks only the rows asked for). Otherwise a
    Trajectory like any other (``cov`` can be read and set)."""

    def __init__(self, t: np.ndarray, pose: np.ndarray, cov: np.ndarray | None = None, *,
                 packed: np.ndarray | None = None, maps: tuple = ()) -> None:
        self.t, self.pose = t, pose
        self._cov, self._packed = cov, packed
        self._maps = maps  # the memory maps the columns are read from, if spilled

    def release(self) -> None:
        release(self._maps)

    @property
    def cov(self) -> np.ndarray:
        if self._cov is None:
            self._cov, self._packed = unpack_cov(self._packed), None
        return self._cov

    @cov.setter
    def cov(self, value: np.ndarray) -> None:
        self._cov, self._packed = value, None

    def cov_at(self, index) -> np.ndarray:
        if self._cov is None:  # unpacked for these rows, not kept: the packed ones stay
            return unpack_cov(self._packed[index])
        return self._cov[index]


@dataclass
class EstimatorRun:
    """One estimator's outputs from one run."""

    name: str
    trajectory: Trajectory
    # wall time of each process() call, s (float32): an array, or a SpilledColumn
    # (run(spill_dir=)) read by blocks (np.asarray gives it whole)
    update_s: np.ndarray | SpilledColumn
    runtime_s: float  # total wall time in process/estimate/finish, s
    log: EstimatorLog
    error: str | None = None  # set when the estimator raised; the trajectory holds what it had
    # the whole state at the end (Estimator.final_state, else the last sample's), or None
    final_state: Estimate | None = None


@dataclass
class GpsTrack:
    """Every GPS fix of a run, in stream order, as arrays: ``t`` (G,) s, ``xy`` (G, 2) m local
    ENU, ``cov`` (G, 2, 2) m^2, ``withheld`` (G,) bool (held out from every estimator); the
    fixes as the estimators were given them (for ``estimates.mcap``): ``lla`` (G, 3) (lat deg,
    lon deg, alt m), ``enu_cov`` (G, 3, 3) m^2 (east, north, up), ``status`` (G,) int
    (NavSatStatus.status); None where the track was built without them."""

    t: np.ndarray
    xy: np.ndarray
    cov: np.ndarray
    withheld: np.ndarray
    lla: np.ndarray | None = None
    enu_cov: np.ndarray | None = None
    status: np.ndarray | None = None

    @property
    def held_t(self) -> np.ndarray:
        return self.t[self.withheld]

    @property
    def held_xy(self) -> np.ndarray:
        return self.xy[self.withheld]

    @property
    def used_t(self) -> np.ndarray:
        return self.t[~self.withheld]

    def __len__(self) -> int:
        return len(self.t)


class _GpsRecorder:
    __slots__ = ("t", "xy", "cov", "held", "lla", "status")

    def __init__(self) -> None:
        self.t, self.xy, self.cov, self.held = array("d"), array("d"), array("d"), array("B")
        self.lla, self.status = array("d"), array("b")

    def add(self, f: GpsFix, withheld: bool) -> None:
        xy = f.enu[:2] if f.enu is not None else (math.nan, math.nan)
        cov = np.asarray(f.cov, float).ravel().tolist()
        # The stamp goes in last (it counts the rows; see TrackBuilder.append).
        self.xy.extend(xy)
        self.cov.extend(cov)
        self.held.append(withheld)
        self.lla.extend((f.lat, f.lon, f.alt))
        self.status.append(f.status)
        self.t.append(f.t)

    def track(self) -> GpsTrack:
        n = len(self.t)
        cov = np.array(self.cov[:9 * n], float).reshape(n, 3, 3)
        return GpsTrack(np.array(self.t, float), np.array(self.xy[:2 * n], float).reshape(n, 2),
                        cov[:, :2, :2].copy(), np.array(self.held[:n], bool),
                        np.array(self.lla[:3 * n], float).reshape(n, 3), cov,
                        np.array(self.status[:n], np.int8))


@dataclass
class RunResult:
    stream: object  # the Stream or ddfuse.estimation.bags.BagStream that was run
    runs: dict[str, EstimatorRun]
    gps: GpsTrack
    truth: Trajectory | None = None
    messages: int = 0  # measurements fed (withheld fixes included)
    interrupted: str | None = None  # Ctrl-C ended the run early (run(interruptible=True))
    # each compass's heading offset against the GPS course (ddfuse.estimation.heading_survey), where
    # the caller measured it during the run (ddfuse.evaluation.pipeline.run_bag)
    offset_surveys: list | None = None


class Holdout:
    """Which GPS fixes to withhold: ``every:K`` (every K-th fix) or ``window:T0:T1`` (fixes with
    T0 <= t - t_start < T1, seconds). Decides fix by fix as the stream goes
    (``withhold(fix, t_start)``), or for a whole list (called with (fixes, t_start) -> the
    withheld indices)."""

    def __init__(self, kind: str, a: float, b: float = 0.0) -> None:
        self.kind, self.a, self.b = kind, a, b
        self.seen = 0

    def withhold(self, fix: GpsFix, t_start: float) -> bool:
        i = self.seen
        self.seen += 1
        if self.kind == "every":
            k = int(self.a)
            return i % k == k - 1
        return self.a <= fix.t - t_start < self.b

    def __call__(self, fixes: list[GpsFix], t_start: float) -> set[int]:
        sel = Holdout(self.kind, self.a, self.b)
        return {i for i, f in enumerate(fixes) if sel.withhold(f, t_start)}


def parse_holdout(spec: str | None) -> Holdout | None:
    """``every:K`` (withhold every K-th fix) or ``window:T0:T1`` (withhold fixes with
    T0 <= t - t_start < T1, seconds); None for no hold-out. ValueError for anything else."""
    if not spec:
        return None
    parts = spec.split(":")
    try:
        if parts[0] == "every" and len(parts) == 2:
            k = int(parts[1])
            if k < 2:
                raise ValueError
            return Holdout("every", k)
        if parts[0] == "window" and len(parts) == 3:
            a, b = float(parts[1]), float(parts[2])
        else:
            raise ValueError
    except ValueError:
        pass
    else:
        if not (math.isfinite(a) and a >= 0.0):
            raise ValueError(f"--gps-holdout: window:T0:T1 needs T0 >= 0 (seconds from the "
                             f"bag's first message), got T0 = {parts[1]} in {spec!r}")
        if not b > a:
            raise ValueError(f"--gps-holdout: window:T0:T1 needs T0 < T1 (seconds from the "
                             f"bag's first message), got T0 = {parts[1]}, T1 = {parts[2]} in "
                             f"{spec!r}")
        return Holdout("window", a, b)
    raise ValueError(f"--gps-holdout: expected every:K (K >= 2) or window:T0:T1, got {spec!r}")


# m^2 / rad^2: a pose variance above this (a sigma of 1e8 m) says the filter kept nothing; its
# arithmetic is past what float64 holds together (the covariance then turns indefinite)
MAX_POSE_VARIANCE = 1e16


def broken(e: Estimate) -> str | None:
    """What is wrong with estimate ``e`` if it is not a number a filter can give (a position
    or heading not finite, a pose variance negative or above MAX_POSE_VARIANCE: the covariance
    has lost positive definiteness or all meaning), else None. NaN variances mean 'no
    covariance' (dead reckoning). Checked at every output tick, outside the timings."""
    c = e.pose_cov  # item by item: whole-array numpy is slower here (docs/design/performance.md)
    d = (float(c[0, 0]), float(c[1, 1]), float(c[2, 2]))
    if math.isfinite(e.pose[0] + e.pose[1] + e.pose[2]) and not any(
            v < 0.0 or v > MAX_POSE_VARIANCE for v in d):  # NaN: both False
        return None
    return (f"pose ({e.pose[0]:.3g}, {e.pose[1]:.3g}, {e.pose[2]:.3g}), pose variances "
            f"({d[0]:.3g}, {d[1]:.3g}, {d[2]:.3g}): the covariance lost positive "
            "definiteness or all meaning; the config's noise values may be far from the data's "
            "(with sigmas of 1e-9 no recovery from a gate lock-out can reconcile the sensors; a "
            "process noise far above the robot's motion, robot.slip or twist_walk, swamps them)")


def _never_started(log: EstimatorLog, fixes_withheld: int = 0, fixes_fed: int = 0,
                   cfg=None) -> str:
    """The error of an estimator that was fed measurements and gave no estimate at all;
    ``fixes_withheld`` / ``fixes_fed``: the run's GPS fixes held out from it / given to it;
    ``cfg``: its Config, if it has one (``Estimator.cfg``), to name what it waited for."""
    waiting = sum(n for (_, why), n in log.rejected.items() if why == "before_init")
    text = "no estimate: it never started"
    if waiting:
        text += f" ({waiting} measurements came before it could)"
    if log.messages:
        text += f"; its last note: {log.messages[-1]}"
    if fixes_withheld and not fixes_fed:
        # an estimator that starts from the GPS course (a compass with an estimated offset
        # gives no heading) waits for fixes forever
        return text + (f"; all {fixes_withheld} GPS fixes were withheld (--gps-holdout), and "
                       "it takes its start (its heading) from the GPS course")
    if not waiting:
        return text
    return text + "; " + _start_hint(cfg, fixes_fed)


def _start_hint(cfg, fixes_fed: int) -> str:
    """What an estimator that counted measurements 'before_init' was waiting for, by its
    config's start (``UnicycleEkf``'s modes): the truth, a compass heading, a GPS fix."""
    if cfg is None or cfg.initial_pose == "ground_truth":
        # the usual cause when an estimator is built by hand from a config
        return ("with initial_pose: ground_truth an EKF waits for a GroundTruthPose measurement "
                "unless it is given initial_pose (evaluation.estimators.build passes the "
                "stream's first truth pose)")
    give = "initial_pose: [x, y, yaw] in the config starts it from a known pose"
    gps = ", ".join(s.topic for s in cfg.of_kind("gps"))
    compass = ", ".join(s.topic for s in cfg.heading_sensors()
                        if isinstance(s.heading_offset, float))
    if gps and not fixes_fed:
        return f"it takes its start position from the first GPS fix, and no fix of {gps} " \
               f"reached it; {give}"
    if compass:
        return (f"it takes its start heading from the orientation of {compass} (heading_offset "
                f"given), and none reached it (see the topic's rejected messages); {give}")
    return f"no measurement it can start from reached it; {give}"


def initial_pose(cfg_initial, stream) -> tuple[float, float, float] | None:
    """Resolve the config's initial_pose: 'ground_truth' -> the truth pose at the first
    measurement (``measurements.truth_at_start``); a tuple -> itself; None -> None (each
    estimator's default).

    ``stream`` is a Stream, or a BagStream primed (``BagStream.prime``) so that its start and
    the truth there are known."""
    if cfg_initial == "ground_truth":
        first = getattr(stream, "first_truth", None)
        if first is not None:  # a BagStream: it found the pose while priming
            g = first()
            if g is None:
                return None
        else:
            gt = stream.ground_truth
            if not gt:
                return None
            g = truth_at_start(np.array([g.t for g in gt]),
                               np.array([(g.x, g.y, g.yaw) for g in gt]), stream.t0)
        if not math.isfinite(g.yaw):
            # a NavSatFix truth: heading 0 would start every estimator confidently wrong
            raise ConfigError(
                "initial_pose: ground_truth: the ground truth has no heading (a NavSatFix truth "
                "gives position only); use a pose topic (Odometry, PoseStamped) as "
                "ground_truth, give initial_pose: [x, y, yaw], or leave initial_pose out (the "
                "heading then comes from the GPS course or a compass)")
        return (g.x, g.y, g.yaw)
    return cfg_initial


def run(stream, estimators: dict[str, Estimator], *, output_rate: float = 10.0,
        holdout: str | None = None, progress: Callable[[float], None] | None = None,
        interruptible: bool = False,
        observers: Iterable[Callable[[object], None]] = (),
        spill_dir: str | Path | None = None) -> RunResult:
    """Feed every measurement of ``stream`` to every estimator, in the stream's order: the
    order of arrival (read_stream and BagStream give stamp order; a list built to test late
    delivery may hold older stamps after newer ones, which each estimator handles as it does
    live: the smoother places them by stamp within its lag).

    ``stream`` is a Stream (its list of measurements) or an ``ddfuse.estimation.bags.BagStream``
    (measurements decoded as they are fed: memory does not grow with the bag). The estimate of
    each estimator is recorded whenever the stream crosses the next tick of ``output_rate``
    (Hz). An estimator that raises is stopped there and keeps what it had; the others go on.
    GPS fixes selected by ``holdout`` are withheld from all estimators. A BagStream that breaks
    off (a truncated bag) ends the run there; its ``error`` says why.

    ``interruptible``: Ctrl-C (KeyboardInterrupt) ends the feeding there, and each estimator is
    finished with what it had (the one interrupted inside an update is stopped, as one that
    raised; one interrupted inside its ``finish``, e.g. the batch's whole-run solve, keeps
    nothing more): the result says so in ``interrupted``. Otherwise Ctrl-C propagates.

    ``observers`` are called with every measurement (withheld fixes too), outside the
    estimators' timings: what a run learns about the data besides the estimates.

    ``spill_dir`` (an existing directory): each estimator's per-call timings and output track
    are written there in blocks as they grow (``ddfuse.estimation.spill``: ``update_s.<k>.f32``
    and ``track.<k>.t/.pose/.cov``, k its position in ``estimators``); its
    ``EstimatorRun.update_s`` is that ``SpilledColumn`` and its trajectory is memory-mapped
    from the files (``Trajectory.release``). The caller removes the files when done with
    them. Without it both stay in memory."""
    if not (output_rate > 0.0 and math.isfinite(output_rate)):
        raise ValueError(f"output_rate: expected Hz > 0, got {output_rate!r}")
    for n, e in estimators.items():
        if getattr(e, "_run_finished", False):
            raise ValueError(f"estimator {n!r} was already run to its end (its finish() was "
                             "called): build a new one for another run")
    select = parse_holdout(holdout)
    names = list(estimators)
    est_list = [estimators[n] for n in names]
    outputs = [TrackBuilder(None if spill_dir is None else Path(spill_dir) / f"track.{k}")
               for k in range(len(names))]
    columns = ([SpilledColumn(Path(spill_dir) / f"update_s.{k}.f32") for k in range(len(names))]
               if spill_dir is not None else [])
    timings = [c.tail for c in columns] or [array("f") for _ in names]
    totals = [0.0] * len(names)
    errors: list[str | None] = [None] * len(names)
    alive = [True] * len(names)
    period = 1.0 / output_rate
    clock = time.perf_counter
    gps = _GpsRecorder()
    if isinstance(stream, Stream):
        meas: Iterable = stream.measurements
        n = len(stream.measurements)
        fraction = None
    else:
        meas = stream
        n = 0
        fraction = getattr(stream, "fraction", None)
    # The growing logs hold many long-lived objects: a full garbage collection walks them
    # all, inside whichever update it interrupts. So automatic collection is off during the
    # loop, and _feed collects only the young generations between messages (the estimators
    # make little cyclic garbage); a list-based stream is frozen (skipped by the collector).
    # Figures: docs/design/performance.md
    gc_was_enabled = gc.isenabled()
    gc.freeze()
    gc.disable()
    stop: list[str] = []
    try:
        fed = _feed(meas, n, fraction, select, gps, est_list, alive, errors, outputs, timings,
                    totals, period, progress, stop if interruptible else None, tuple(observers),
                    columns)
    finally:
        if gc_was_enabled:
            gc.enable()
        gc.unfreeze()
    runs: dict[str, EstimatorRun] = {}
    # an estimator that solves another's online run at the end (``source``: the batch sharing
    # the smoother's) stops where that one stopped
    index = {id(e): k for k, e in enumerate(est_list)}
    sources = [index.get(id(getattr(e, "source", None))) for e in est_list]
    for i, (name, est) in enumerate(zip(names, est_list, strict=True)):
        t_a = clock()
        src = sources[i]
        if alive[i] and src is not None and src != i and errors[src] is not None:
            alive[i] = False
            errors[i] = f"stopped with {names[src]}, whose online run it solves: {errors[src]}"
            est.log.note(est_list[src].newest_t, f"stopped: {errors[i]}")
        if alive[i]:
            try:
                est.finish()
                last = est.estimate()
                if last is not None and (not outputs[i] or last.t > outputs[i].last.t):
                    bad = broken(last)
                    if bad:
                        errors[i] = f"numerical breakdown at the end: {bad}"
                    else:
                        outputs[i].append(last)
            except (Exception, KeyboardInterrupt) as exc:
                ki = interrupt_in(exc)
                if ki is None:
                    errors[i] = f"{type(exc).__name__} in finish: {error_line(exc)}"
                elif not interruptible:
                    raise ki from None
                else:
                    errors[i] = f"interrupted ({interrupt_name(ki)}) in finish"
                    stop.append(f"{name} interrupted in finish")
        totals[i] += clock() - t_a
        est._run_finished = True  # fed to its end: another run() of it is refused
        # gathering what the estimator gave is not cut short: an interrupt is held (noted in
        # ``interrupted`` after it, or raised if not interruptible)
        with held_signals() as held:
            _gather(runs, name, est, outputs, i, columns[i] if columns else timings[i],
                    totals[i], errors, fed, gps)
        if held and interruptible:
            stop.append(f"interrupted ({interrupt_name(held[0])}) while the results were gathered")
        elif held:
            deliver(held)
    heap.trim()
    if progress is not None:
        progress(1.0)
    truth = None
    arrays = getattr(stream, "truth_arrays", None)
    if callable(arrays):
        t, pose = arrays()
        truth = Trajectory.from_ground_truth((t, pose)) if len(t) else None
    elif stream.ground_truth:
        truth = Trajectory.from_ground_truth(stream.ground_truth)
    return RunResult(stream, runs, gps.track(), truth, fed, "; ".join(stop) or None)


def _gather(runs: dict, name: str, est: Estimator, outputs: list, i: int,
            timing: array | SpilledColumn, total: float, errors: list, fed: int,
            gps: _GpsRecorder) -> None:
    """The EstimatorRun(s) of estimator ``i`` of :func:`run` (its output track, or the batch's
    final one; its lagged track too) into ``runs``."""
    est.log.innovations.compact()
    if isinstance(timing, SpilledColumn):
        timing.close()
        upd = timing
    else:  # a view of the compact array, not a copy
        upd = np.frombuffer(timing, np.float32) if len(timing) else np.zeros(0, np.float32)
    # An offline estimator (the batch) gives its whole trajectory only at the end.
    final = getattr(est, "final_estimates", None)
    track = final() if callable(final) else outputs[i]
    if not track and errors[i] is None and fed:
        held = int(np.count_nonzero(np.frombuffer(gps.held, np.uint8)))
        errors[i] = _never_started(est.log, held, len(gps.held) - held,
                                   getattr(est, "cfg", None))
    runs[name] = EstimatorRun(name, Trajectory.from_estimates(track), upd, total,
                              est.log, errors[i], _final_state(est, track))
    outputs[i] = None
    lagged = getattr(est, "lagged_estimates", None)
    lagged = lagged() if callable(lagged) else None
    if lagged is not None:
        runs[f"{name}_lagged"] = EstimatorRun(
            f"{name}_lagged", Trajectory.from_estimates(lagged), upd, total, est.log,
            errors[i], _final_state(est, lagged))


def _final_state(est: Estimator, track) -> Estimate | None:
    """The estimator's whole state at the end of the run: its own ``final_state()``, else the
    last output sample (a TrackBuilder keeps that one whole), if it has a state vector."""
    hook = getattr(est, "final_state", None)
    try:
        e = hook() if callable(hook) else None
    except Exception:  # a broken hook is not worth losing the run's outputs over
        e = None
    if e is None:
        e = getattr(track, "last", None) if track is not None else None
    return e if e is not None and e.state is not None else None


def _feed(meas, n, fraction, select, gps, est_list, alive, errors, outputs, timings, totals,
          period, progress, stop: list[str] | None = None, observers: tuple = (),
          columns: list[SpilledColumn] | tuple = ()) -> int:
    """The measurement loop of :func:`run` (see there); returns how many measurements came.
    With ``stop`` (a list), Ctrl-C ends the loop and says where in ``stop``. ``columns``: the
    spilled timing columns whose tails are ``timings``, spilled between messages."""
    clock = time.perf_counter
    next_tick = -math.inf
    t_start = None
    est_logs = [est.log for est in est_list]
    k = -1
    done = 0  # measurements every estimator has had
    t_m = math.nan
    busy = None  # the estimator inside an update
    try:
        for k, m in enumerate(meas):
            if k % 1000 == 0:
                # between messages, outside the timed updates: compact the innovation logs
                # (read through the log each time: a compiled filter's log drains its kernels'
                # buffer into the store on that read)
                for lg in est_logs:
                    lg.innovations.compact()
                for c in columns:
                    c.spill()
                for o in outputs:
                    if o is not None:
                        o.spill()
                if k % 5000 == 0:
                    gc.collect(1)
                    heap.trim()  # the temporaries' free gaps between the growing records
                if progress is not None:
                    progress(fraction() if fraction is not None else k / max(n, 1))
            t_m = m.t
            if t_start is None:
                t_start = t_m
            for ob in observers:
                ob(m)
            if isinstance(m, GpsFix):
                held = select is not None and select.withhold(m, t_start)
                gps.add(m, held)
                if held:
                    done = k + 1
                    continue
            record = t_m >= next_tick
            if record:
                # The next tick on the grid, or one period after a gap; never m.t itself,
                # which recorded the same stamp again for each message sharing it (IMU fields).
                next_tick = next_tick + period if next_tick + period > t_m else t_m + period
            for i, est in enumerate(est_list):
                if not alive[i]:
                    continue
                busy = i
                t_a = clock()
                try:
                    est.process(m)
                    e = est.estimate() if record else None
                except Exception as exc:  # one estimator failing must not end the run
                    if (ki := interrupt_in(exc)) is not None:
                        raise ki from None  # Ctrl-C inside compiled code: an interrupt
                    alive[i] = False
                    errors[i] = f"{type(exc).__name__} at t={t_m:.3f}: {error_line(exc)}"
                    est.log.note(t_m, f"stopped: {errors[i]}")
                    continue
                dt = clock() - t_a
                timings[i].append(dt)
                totals[i] += dt
                if e is not None:
                    last = outputs[i].last
                    if last is not None and e.t <= last.t:
                        # nothing newer since the last tick (a smoother waiting for its first
                        # odometry sample): a track's stamps only increase, so its samples
                        # never share one (evo and the metrics' interpolation need that)
                        continue
                    bad = broken(e)
                    if bad:  # never recorded: the track keeps what it had
                        alive[i] = False
                        errors[i] = f"numerical breakdown at t={t_m:.3f}: {bad}"
                        est.log.note(t_m, f"stopped: {errors[i]}")
                        continue
                    outputs[i].append(e)
            busy = None
            done = k + 1
    except KeyboardInterrupt as exc:
        if stop is None:
            raise
        at = f"{t_m - t_start:.3f} s after the first measurement" if t_start is not None \
            else "before the first measurement"
        how = interrupt_name(exc)
        if busy is not None:  # inside an update: that estimator's state is half-updated
            alive[busy] = False
            errors[busy] = f"interrupted ({how}) inside an update, {at}"
        stop.append(f"interrupted ({how}) after {done} measurements, {at}")
        return done
    return k + 1
