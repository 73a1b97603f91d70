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
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from estimation.estimator import Estimate, Estimator, EstimatorLog
from estimation.measurements import GpsFix, GroundTruthPose, Stream


@dataclass
class Trajectory:
    """Poses over time in the local frame: ``t`` (N,) s, ``pose`` (N, 3) as (x m, y m, yaw rad),
    ``cov`` (N, 3, 3) world-frame pose covariance (NaN where an estimator gives none)."""

    t: np.ndarray
    pose: np.ndarray
    cov: np.ndarray

    @classmethod
    def from_estimates(cls, estimates: Iterable[Estimate]) -> Trajectory:
        est = list(estimates)
        if not est:
            return cls(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)))
        return cls(np.array([e.t for e in est]), np.array([e.pose for e in est], dtype=float),
                   np.array([e.pose_cov if e.pose_cov is not None else np.full((3, 3), np.nan)
                             for e in est], dtype=float))

    @classmethod
    def from_ground_truth(cls, truth: list[GroundTruthPose]) -> Trajectory:
        n = len(truth)
        return cls(np.array([g.t for g in truth]),
                   np.array([(g.x, g.y, g.yaw) for g in truth], dtype=float).reshape(n, 3),
                   np.full((n, 3, 3), np.nan))

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class EstimatorRun:
    """One estimator's outputs from one run."""

    name: str
    trajectory: Trajectory
    update_s: np.ndarray  # wall time of each process() call, s
    runtime_s: float  # total wall time in process/estimate/finish, s
    log: EstimatorLog
    error: str | None = None  # set when the estimator raised; the trajectory holds what it had


@dataclass
class RunResult:
    stream: Stream
    runs: dict[str, EstimatorRun]
    holdout: list[GpsFix] = field(default_factory=list)  # fixes withheld from every estimator
    truth: Trajectory | None = None


def parse_holdout(spec: str | None) -> Callable[[list[GpsFix], float], set[int]] | None:
    """``every:K`` (withhold every K-th fix) or ``window:T0:T1`` (withhold fixes with
    T0 <= t - t_start < T1, seconds). Returns a selector (fixes, t_start) -> withheld indices."""
    if not spec:
        return None
    parts = spec.split(":")
    try:
        if parts[0] == "every" and len(parts) == 2:
            k = int(parts[1])
            if k < 2:
                raise ValueError
            return lambda fixes, t0: {i for i in range(len(fixes)) if i % k == k - 1}
        if parts[0] == "window" and len(parts) == 3:
            a, b = float(parts[1]), float(parts[2])
            if not b > a:
                raise ValueError
            return lambda fixes, t0: {i for i, f in enumerate(fixes) if a <= f.t - t0 < b}
    except ValueError:
        pass
    raise ValueError(f"--gps-holdout: expected every:K (K >= 2) or window:T0:T1, got {spec!r}")


def initial_pose(cfg_initial, stream: Stream) -> tuple[float, float, float] | None:
    """Resolve the config's initial_pose: 'ground_truth' -> the first truth pose at or after the
    first measurement; a tuple -> itself; None -> None (each estimator's default)."""
    if cfg_initial == "ground_truth":
        if not stream.ground_truth:
            return None
        t0 = stream.t0
        g = next((g for g in stream.ground_truth if g.t >= t0 - 1e-9), stream.ground_truth[-1])
        return (g.x, g.y, g.yaw if math.isfinite(g.yaw) else 0.0)
    return cfg_initial


def run(stream: Stream, estimators: dict[str, Estimator], *, output_rate: float = 10.0,
        holdout: str | None = None, progress: Callable[[float], None] | None = None
        ) -> RunResult:
    """Feed every measurement of ``stream`` to every estimator, in time order.

    The estimate of each estimator is recorded whenever the stream crosses the next tick of
    ``output_rate`` (Hz). An estimator that raises is stopped there and keeps what it had; the
    others go on. GPS fixes selected by ``holdout`` are withheld from all estimators."""
    select = parse_holdout(holdout)
    withheld: list[GpsFix] = []
    skip: set[int] = set()
    if select is not None:
        fixes = [m for m in stream.measurements if isinstance(m, GpsFix)]
        idx = select(fixes, stream.t0)
        withheld = [f for i, f in enumerate(fixes) if i in idx]
        skip = {id(f) for f in withheld}

    names = list(estimators)
    est_list = [estimators[n] for n in names]
    outputs: list[list[Estimate]] = [[] for _ in names]
    timings: list[list[float]] = [[] for _ in names]
    totals = [0.0] * len(names)
    errors: list[str | None] = [None] * len(names)
    alive = [True] * len(names)
    period = 1.0 / output_rate
    meas = stream.measurements
    clock = time.perf_counter
    # The decoded stream and the growing logs are millions of long-lived objects: a full
    # garbage collection walks them all, inside whichever update it interrupts (0.1-0.9 s
    # spikes on a 2 h bag). So the stream is frozen (skipped by the collector), automatic
    # collection is off during the loop, and _feed collects only the young generations
    # between messages (the estimators make little cyclic garbage).
    gc_was_enabled = gc.isenabled()
    gc.freeze()
    gc.disable()
    try:
        _feed(meas, skip, est_list, alive, errors, outputs, timings, totals, period, progress)
    finally:
        if gc_was_enabled:
            gc.enable()
        gc.unfreeze()
    runs: dict[str, EstimatorRun] = {}
    for i, (name, est) in enumerate(zip(names, est_list, strict=True)):
        t_a = clock()
        if alive[i]:
            try:
                est.finish()
                last = est.estimate()
                if last is not None and (not outputs[i] or last.t > outputs[i][-1].t):
                    outputs[i].append(last)
            except Exception as exc:
                errors[i] = f"{type(exc).__name__} in finish: {exc}"
        totals[i] += clock() - t_a
        upd = np.array(timings[i])
        # An offline estimator (the batch) gives its whole trajectory only at the end.
        final = getattr(est, "final_estimates", None)
        track = final() if callable(final) else outputs[i]
        runs[name] = EstimatorRun(name, Trajectory.from_estimates(track), upd, totals[i],
                                  est.log, errors[i])
        lagged = getattr(est, "lagged_estimates", None)
        lagged = lagged() if callable(lagged) else None
        if lagged is not None:
            runs[f"{name}_lagged"] = EstimatorRun(
                f"{name}_lagged", Trajectory.from_estimates(lagged), upd, totals[i], est.log,
                errors[i])
    if progress is not None:
        progress(1.0)
    truth = Trajectory.from_ground_truth(stream.ground_truth) if stream.ground_truth else None
    return RunResult(stream, runs, withheld, truth)


def _feed(meas, skip, est_list, alive, errors, outputs, timings, totals, period, progress
          ) -> None:
    """The measurement loop of :func:`run` (see there)."""
    clock = time.perf_counter
    n = len(meas)
    next_tick = -math.inf
    for k, m in enumerate(meas):
        if k % 1000 == 0:
            if k % 5000 == 0:
                gc.collect(1)
            if progress is not None:
                progress(k / max(n, 1))
        if id(m) in skip:
            continue
        record = m.t >= next_tick
        if record:
            # The next tick on the grid, or one period after a gap; never m.t itself, which
            # recorded the same stamp again for each message sharing it (IMU fields).
            next_tick = next_tick + period if next_tick + period > m.t else m.t + period
        for i, est in enumerate(est_list):
            if not alive[i]:
                continue
            t_a = clock()
            try:
                est.process(m)
                e = est.estimate() if record else None
            except Exception as exc:  # one estimator failing must not end the run
                alive[i] = False
                errors[i] = f"{type(exc).__name__} at t={m.t:.3f}: {exc}"
                est.log.note(m.t, f"stopped: {errors[i]}")
                continue
            dt = clock() - t_a
            timings[i].append(dt)
            totals[i] += dt
            if e is not None:
                outputs[i].append(e)
