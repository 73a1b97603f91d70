"""The main job: read a bag, run the estimators side by side, score them, write the results.

``run_bag`` decodes a bag as a stream, runs the selected estimators on it, scores them
(``score``) and writes ``OUTDIR/metrics.json``, every trajectory as ``OUTDIR/<track>.tum`` and
``.csv`` (and ``ground_truth.tum``/``.csv`` when there is truth), plus ``OUTDIR/run.npz`` with
what the report needs besides (``evaluation.results``).

``score(result)`` returns the run's scores as typed records (``evaluation.scores.RunSummary``:
per track ATE, RPE and NEES against the truth, the distance to withheld GPS fixes, the drift
over GPS outages, NIS per sensor, the calibration states at the end); metrics.json is
``RunSummary.to_json()``, and ``run_bag`` returns the ``RunSummary``. What each key holds, in
which unit and against what, is in docs/design/metrics-json.md. Values that cannot be computed
(no truth, no hold-out) are None (null in the JSON); ``decode_s``, ``runtime_s``, ``rtf``,
``update_ms`` and ``wall_s`` are timings, which differ between runs of the same bag; every
other value does not.

Every track is scored in the run's local frame without alignment, on the same withheld fixes
(those inside every track's span, gross GPS errors left out: ``_gross_outliers``) and ranked on
the common span (``_common_ate``); a fix is compared with the track's GPS antenna as the
estimators model it (``gps_antenna``). The hold-out rules and the measurements behind them:
docs/design/gps-holdout-scoring.md.
"""

from __future__ import annotations

import math
import os
import shutil
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
from ddfuse.estimation import chi2, gps_scatter, heading_survey, heap
from ddfuse.estimation.bags import BagStream
from ddfuse.estimation.config import DEFAULT_GATE, Config, with_gps_model
from ddfuse.estimation.errors import BagError, RunInterrupted
from ddfuse.estimation.interrupts import held_signals, interrupt_name
from ddfuse.estimation.measurements import Stream
from ddfuse.estimation.runner import (
    GpsTrack,
    RunResult,
    Trajectory,
    initial_pose,
    parse_holdout,
)
from ddfuse.evaluation import consistency, latency_stats, metrics, pair_scores
from ddfuse.evaluation import estimators as registry
from ddfuse.evaluation.atomic_files import OutputError
from ddfuse.evaluation.batch_cost import DEFAULT_MAX_SPAN_S, announce_solve, leave_out_notice
from ddfuse.evaluation.consistency import SensorNis
from ddfuse.evaluation.run_files import config_text_of, save_run, write_metrics, writing_run
from ddfuse.evaluation.scores import (
    AteScore,
    AteScores,
    CalibrationState,
    CommonSpan,
    DataFacts,
    EstimatorScores,
    FinalState,
    GpsAntenna,
    GpsBursts,
    HeadingOffset,
    RpeScore,
    RunSummary,
    SensorFacts,
    UpdateLatency,
    WallTimes,
    num,
    rounded_record,
    stats_of,
)
from ddfuse.evaluation.side_run import run_split, side_names

MAX_DIFF = 0.05  # s: association of estimate and truth stamps (truth at >= 10 Hz)
RPE_DELTAS = (("1s", 1.0, "s"), ("10m", 10.0, "m"))
EVENTS_KEPT = 20  # an estimator's first events kept in metrics.json (events_total: all)


def process_age() -> float | None:
    """Seconds since this process started (Linux: its start time in /proc, 10 ms
    resolution); None where that cannot be read."""
    try:
        with open("/proc/self/stat") as f:
            # field 22, counted after the command name (which may hold spaces) closes with ')'
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return None


def timing_split(*, startup: float | None, decode: float, build: float, loop: float,
                 loop_decode: float, runtimes: dict[str, float], scoring: float,
                 writing: float, side: tuple[str, ...] = (), side_wait: float = 0.0
                 ) -> WallTimes:
    """The ``wall_s`` of metrics.json, seconds rounded to 0.1 ms.

    In: ``startup`` (process age when run_bag began; None if unknown), ``decode`` (all of the
    stream's decoding: opening, priming, and the share in the loop), ``build`` (from run_bag's
    start to the loop, less the decoding in it), ``loop`` (wall time of ``runner.run``),
    ``loop_decode`` (its share of the decoding), ``runtimes`` (estimator -> time in its calls),
    ``scoring``, ``writing``. Out: those, plus ``runner`` (the loop less its decoding and the
    estimators' calls: the runner's own per-message work) and ``total`` (the sum: the wall time
    from the process's start to metrics.json). ``side``: the estimators fed in a side process
    (their runtimes overlap the loop: in neither ``runner`` nor ``total``), ``side_wait`` the
    part of ``loop`` spent waiting for them after the main process's own loop."""
    own = [v for k, v in runtimes.items() if k not in side]
    runner = loop - loop_decode - sum(own) - side_wait
    parts = [decode, build, runner, *own, side_wait, scoring, writing]
    total = sum(parts) + (startup or 0.0)

    def r4(v: float | None) -> float | None:
        return None if v is None else round(float(v), 4)

    return WallTimes(r4(startup), r4(decode), r4(build), {k: r4(v) for k, v in runtimes.items()},
                     r4(runner), r4(scoring), r4(writing), r4(total), list(side),
                     r4(side_wait) if side else None)


def _ate_score(position: metrics.Stats, heading: metrics.Stats) -> AteScore:
    return AteScore(stats_of(position), stats_of(heading, math.degrees(1)))


def _truth_scores(tr: Trajectory, truth: Trajectory, pose_error: str = "world") -> dict:
    """ATE (three alignments), RPE and NEES of one track against the truth: the
    ``EstimatorScores`` fields they fill (none without an associated pair). The ATE, its
    association error and the NEES walk the associated pairs a block at a time
    (``pair_scores``)."""
    m: dict = {}
    i, j = metrics.associate(tr.t, truth.t, MAX_DIFF)
    if len(i) == 0:
        return m
    pos, head = pair_scores.ape_stats(tr, truth, i, j)
    m["ate_rmse_m"] = num(pos.rmse)
    m["ate_max_m"] = num(pos.max)
    m["yaw_rmse_deg"] = num(math.degrees(head.rmse)) if head.n else None
    assoc = pair_scores.association_stats(tr, truth, i, j)
    m["ate_association_rmse_m"] = num(assoc.rmse)
    aligned = {}
    for how in ("se2", "origin"):
        try:
            aligned[how] = _ate_score(*pair_scores.ape_stats(tr, truth, i, j, how))
        except ValueError:  # too few distinct positions, or a truth without heading
            aligned[how] = None
    m["ate"] = AteScores(_ate_score(pos, head), pos.n, MAX_DIFF, stats_of(assoc), **aligned)
    if np.isfinite(truth.pose[:, 2]).any():
        rpe = {}
        for key, delta, unit in RPE_DELTAS:
            rpos, yaw = metrics.rpe(tr, truth, delta, MAX_DIFF, unit=unit, pairs=(i, j))
            # the pairs' actual spacing: a keyframe track's 1 s pairs are 1.2 s apart
            rpe[key] = RpeScore(delta, unit, num(
                metrics.rpe_mean_delta(tr, truth, delta, MAX_DIFF, unit=unit, pairs=(i, j))),
                stats_of(rpos), stats_of(yaw, math.degrees(1))) if rpos.n else None
        m["rpe"] = rpe
        m["rpe_rmse_m"] = rpe["1s"].position_m.rmse if rpe["1s"] else None
    else:
        # Position-only truth (NavSatFix): the RPE compares relative poses, the estimate's
        # displacement in its own start frame against the truth's in the truth's, which needs
        # the truth's heading. Left out with the reason, not nulls beside a pair count.
        m["rpe"], m["rpe_rmse_m"] = None, None
        m["rpe_note"] = "the ground truth has no heading (position only): no RPE"
    ns = metrics.nees_series(tr, truth, MAX_DIFF, pose_error, pairs=(i, j))
    if len(ns.value):
        c = consistency.summarize(ns.value, ns.dof)
        m["nees_mean"] = num(c.mean)
        m["nees"] = rounded_record(c)
    return m


def _outage_scores(tr: Trajectory, outages: list[metrics.Outage], truth: Trajectory | None,
                   hold_t: np.ndarray, hold_xy: np.ndarray, hold_cov: np.ndarray,
                   antenna: GpsAntenna) -> list[metrics.OutageDrift] | None:
    """Drift per metre over each outage, against the truth if there is one, else against the
    fixes withheld in it (through block means of them: ``metrics.outage_drift``, with their
    covariances ``hold_cov``; the track's antenna, ``gps_antenna``). None when there are no
    outages."""
    if not outages:
        return None
    out = []
    for o in outages:
        if truth is not None:
            d = metrics.outage_drift(tr, o, truth.t, truth.pose[:, :2], "truth")
        else:
            xy, inside = metrics.antenna_xy(tr, hold_t, antenna.lever_arm, antenna.delay_s)
            xy[~inside] = np.nan
            d = metrics.outage_drift(tr, o, hold_t, hold_xy, "withheld GPS", ref_cov=hold_cov,
                                     est_xy=xy)
        out.append(rounded_record(d) if d else metrics.OutageDrift(o.t0, o.t1))
    return out


CALIBRATION = ("bg", "hoff", "k_v", "k_w")  # state names (a sensor may follow after ':')


def calibration_entries(e) -> list[tuple[str, float, float | None]]:
    """(label, value, sigma or None) of each calibration state of Estimate ``e`` (its
    ``state``, ``state_cov``, ``state_names``), in the order of CALIBRATION; ``bg:<sensor>``
    is labelled ``bg`` where it is the estimator's only one."""
    if e is None or e.state is None or not e.state_names:
        return []
    kinds = [n.split(":", 1)[0] for n in e.state_names]
    sd = (np.sqrt(np.clip(np.diagonal(e.state_cov), 0.0, None))
          if e.state_cov is not None else None)
    return [(kind if kinds.count(kind) == 1 else name, float(e.state[i]),
             float(sd[i]) if sd is not None else None)
            for kind in CALIBRATION
            for i, (name, k) in enumerate(zip(e.state_names, kinds, strict=True)) if k == kind]


def calibration_states(e) -> FinalState | None:
    """``calibration_entries`` of Estimate ``e`` as metrics.json holds them (``final_state``),
    or None without any."""
    entries = calibration_entries(e)
    if not entries:
        return None
    return FinalState(num(e.t), {label: CalibrationState(num(v), num(sd))
                                 for label, v, sd in entries})


def _residual_corr(tr: Trajectory, t: np.ndarray, xy: np.ndarray, antenna: GpsAntenna
                   ) -> float | None:
    """Correlation time (s) of the used GPS fixes' residuals to track ``tr``'s antenna
    (``metrics.correlation_time``)."""
    est, inside = metrics.antenna_xy(tr, t, antenna.lever_arm, antenna.delay_s)
    return metrics.correlation_time(t[inside], (xy - est)[inside])


def gps_correlation_warnings(cfg: Config, gps: GpsTrack, watch=None) -> list[str]:
    """The advice of ``ddfuse.estimation.gps_scatter`` (the rule `inspect` suggests a GPS
    sensor's ``correlation_time`` by) when the config's value disagrees with what the run's GPS
    fixes ``gps`` (withheld ones too: the data's, whatever the hold-out) give. With more than
    one GPS sensor the fixes are not told apart by receiver: no advice; nor where the stream's
    ``watch`` (``GpsWatch``) found the GPS bursty: the scatter is then the bursts', measured
    against a stated sigma they belie (urban: 'set correlation_time: 0' for errors that wander
    over 10 s), and its own warning names the model for them."""
    sensors = cfg.of_kind("gps")
    if len(sensors) != 1 or len(gps) == 0:
        return []
    if watch is not None and watch.bursty(sensors[0].topic):
        return []
    scatter = gps_scatter.fix_scatter(gps.t, gps.xy, np.trace(gps.cov, axis1=1, axis2=2) / 2.0)
    advice = scatter.advice(sensors[0].topic, sensors[0].correlation_time) if scatter else None
    return [advice] if advice else []


def _interpolation_rmse(used_t, used_xy, hold_t, hold_xy) -> float | None:
    e = metrics.interpolation_errors(used_t, used_xy, hold_t, hold_xy)
    return num(float(np.sqrt(np.mean(e * e)))) if len(e) else None


def _pose_error(r) -> str:
    """The coordinates of EstimatorRun ``r``'s pose error, as its estimates carry them
    (``Estimate.pose_error`` of its ``final_state``: the last estimate, or the estimator's
    own final state); 'world' for a run without a final state (no state vector, no estimate)."""
    return getattr(r.final_state, "pose_error", None) or "world"


def gps_antenna(cfg: Config | None) -> GpsAntenna:
    """The GPS antenna model every track's hold-out is scored with, as the estimators fuse the
    fixes: lever arm (x, y) m (body frame), delay s (a fix is the antenna that long before its
    stamp), the gate's chi-square probability or None, a note or None. The run's
    fixes do not say which GPS sensor took them: with several whose lever arm or delay differ,
    neither is applied and the note says so. No config: none applied."""
    gps = [s for s in (cfg.sensors if cfg is not None else []) if s.kind == "gps"]
    if not gps:
        return GpsAntenna(gate=DEFAULT_GATE, note=None if cfg is not None
                          else "no config: no lever arm or delay applied")
    models = {(tuple(s.lever_arm), s.delay) for s in gps}
    gates = {s.gate for s in gps}
    gate = gates.pop() if len(gates) == 1 else max((g for g in gates if g), default=None)
    if len(models) > 1:
        return GpsAntenna(gate=gate, note="GPS sensors with different lever arms or delays: "
                          "neither applied")
    (lever, delay), = models
    return GpsAntenna((float(lever[0]), float(lever[1])), float(delay), gate)


def _gross_outliers(result: RunResult, t: np.ndarray, xy: np.ndarray, cov: np.ndarray,
                    antenna: GpsAntenna, *, used: bool = False) -> np.ndarray:
    """Mask of the fixes (``t``, ``xy``, ``cov`` (M, 2, 2)) that are gross GPS errors: every
    track's chi-square gate (``antenna['gate']``, 2 dof, ``metrics.gate_nis``) rejects them,
    and so does the same gate against the used fixes on either side, interpolated in time,
    where no outage lies between them (``_beside_fixes``). The second test is what makes it
    the GPS's error and not the tracks': in a window outage every track may have drifted
    beyond its own sigma, and those fixes are exactly what the score is for
    (docs/design/gps-holdout-scoring.md).
    ``used``: the fixes are the used ones themselves (all of them, in order), each tested
    against its neighbours. None with the gate off."""
    gate = antenna.gate
    live = [r.trajectory for r in result.runs.values() if len(r.trajectory) > 1]
    if not gate or not live or not len(t):
        return np.zeros(len(t), bool)
    limit = float(chi2.ppf(gate, 2))  # ddfuse.estimation.chi2: scipy.stats's values, not its import
    out = _beside_fixes(result, t, xy, cov, limit, used)
    for tr in live:
        if not out.any():
            break
        nis = metrics.gate_nis(tr, t, xy, cov, antenna.lever_arm, antenna.delay_s)
        tr.release()  # a spilled track's pages, read again by the next reader
        out &= ~(nis <= limit)  # NaN (no estimate there) does not vouch for the fix
    return out


def _beside_fixes(result: RunResult, t: np.ndarray, xy: np.ndarray, cov: np.ndarray,
                  limit: float, used: bool) -> np.ndarray:
    """Mask of the fixes (``t``, ``xy``, ``cov`` (M, 2, 2)) that the used fixes just before and
    after them, interpolated in time, put beyond the chi-square ``limit``: the fix's covariance
    and half its own again for the interpolated pair. A pair with an outage between them
    (``metrics.gps_outages``' rule: max(5 s, 5 median intervals of all fixes)) tests
    nothing. ``used``: ``t`` are the used fixes themselves, each against its two neighbours."""
    used_t = np.asarray(result.gps.used_t, float)
    if len(used_t) < (3 if used else 2):
        return np.zeros(len(t), bool)
    used_xy = result.gps.xy[~result.gps.withheld]
    span = max(5.0, 5.0 * float(np.median(np.diff(np.asarray(result.gps.t, float)))))
    if used:
        j1 = np.clip(np.arange(len(t)) + 1, 2, len(used_t) - 1)
        j0 = j1 - 2
    else:
        j1 = np.clip(np.searchsorted(used_t, t), 1, len(used_t) - 1)
        j0 = j1 - 1
    t0, t1 = used_t[j0], used_t[j1]
    ok = (t0 <= t) & (t <= t1) & (t1 - t0 < span)
    if used:
        ok[[0, -1]] = False  # the first and last fix have a neighbour on one side only
    w = np.where(t1 > t0, (t - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0)[:, None]
    d = xy[:, :2] - ((1.0 - w) * used_xy[j0, :2] + w * used_xy[j1, :2])
    c = 1.5 * cov[:, :2, :2]
    det = c[:, 0, 0] * c[:, 1, 1] - c[:, 0, 1] * c[:, 1, 0]
    nis = (c[:, 1, 1] * d[:, 0] ** 2 - (c[:, 0, 1] + c[:, 1, 0]) * d[:, 0] * d[:, 1]
           + c[:, 0, 0] * d[:, 1] ** 2) / np.where(det > 0.0, det, np.nan)
    return ok & (nis > limit)


def score(result: RunResult, decode_s: float = 0.0,
          pose_errors: dict[str, str] | None = None, cfg: Config | None = None) -> RunSummary:
    """The scores of a run (``scores.RunSummary``; ``score(result).to_json()`` is the metrics
    dictionary: docs/design/metrics-json.md), up to ``ate_common``. ``pose_errors``: per track the
    coordinates of its pose error (``Estimator.pose_error``), for the NEES; a track not in it
    takes the one its estimates carry (``_pose_error``), so ``score(result)`` on a RunResult
    of ``runner.run`` scores each estimator in its own coordinates, as ``run_bag`` does.
    ``cfg``: the config whose GPS lever arm and delay the hold-out scores apply
    (``gps_antenna``; default the stream's own, a BagStream's)."""
    stream = result.stream
    duration = stream.duration
    # score a fix as the estimators fuse it: the antenna at t - delay, lever arm applied (a
    # perfect track otherwise scores the lever arm, 0.5 m, or the motion over the delay)
    antenna = gps_antenna(cfg if cfg is not None else getattr(stream, "cfg", None))
    lever, delay = antenna.lever_arm, antenna.delay_s
    truth = result.truth
    hold_t, hold_xy = result.gps.held_t, result.gps.held_xy
    hold_cov = result.gps.cov[result.gps.withheld]
    n_held = len(hold_t)
    # Every track is scored on the same withheld fixes: those inside every track's span (a
    # filter that starts after its heading is known has no estimate at the first ones, and a
    # ranking over different fixes would compare different things).
    covered = np.ones(n_held, bool)
    for r in result.runs.values():
        if len(r.trajectory) > 1:
            covered &= metrics.antenna_xy(r.trajectory, hold_t, lever, delay)[1]
            r.trajectory.release()
    # No fix inside every span (one track ends before another starts): each track could only be
    # scored on its own fixes, a ranking of different things. Then no track gets a hold-out
    # score (gps_holdout_rmse_m), only its statistics over its own fixes (gps_holdout_m).
    common_fixes = bool(covered.any())
    own_t, own_xy = hold_t, hold_xy
    n_outliers = 0
    if common_fixes:
        hold_t, hold_xy, hold_cov = hold_t[covered], hold_xy[covered], hold_cov[covered]
        # A gross GPS error (20-60 m multipath) no estimator comes near dominates every track's
        # RMSE alike (docs/design/gps-holdout-scoring.md). Left out for every track, counted
        # and said: fixes that every track's GPS gate
        # (the sensor's chi-square probability, on the fix's and the track's own covariance)
        # and the used fixes beside them would reject (``_gross_outliers``).
        out_mask = _gross_outliers(result, hold_t, hold_xy, hold_cov, antenna)
        n_outliers = int(out_mask.sum())
        if n_outliers < len(hold_t):
            keep = ~out_mask
            hold_t, hold_xy, hold_cov = hold_t[keep], hold_xy[keep], hold_cov[keep]
    used_t = result.gps.used_t
    used_xy = result.gps.xy[~result.gps.withheld]
    # the reference interpolates the used fixes: a gross error among them (one 30 m fix puts
    # 15 m on the withheld fixes beside it) is left out of it by the same two tests, and counted
    ref_out = (_gross_outliers(result, used_t, used_xy, result.gps.cov[~result.gps.withheld],
                               antenna, used=True) if n_held else np.zeros(len(used_t), bool))
    outages = metrics.gps_outages(used_t, stream.t1) if len(used_t) else []
    ests = {}
    for name, r in result.runs.items():
        ests[name] = _track_scores(r, duration, truth, (pose_errors or {}).get(name),
                                   common_fixes, (hold_t, hold_xy, hold_cov), (own_t, own_xy),
                                   (used_t, used_xy), outages, antenna)
        r.trajectory.release()
    # a run that stopped with an error is not ranked: it must not cut everyone's span
    common = _common_ate({n: r.trajectory for n, r in result.runs.items() if r.error is None},
                         truth)
    for name, e in ests.items():
        tr = result.runs[name].trajectory
        ests[name] = replace(e, ate_common_rmse_m=common[0].get(name) if common else None,
                             span_s=(num(tr.t[0]), num(tr.t[-1])) if len(tr) else None)
    return RunSummary(
        bag=stream.source,
        duration_s=num(duration),
        decode_s=num(decode_s),
        messages=result.messages,
        rejected_messages={f"{topic}: {reason}": n
                           for (topic, reason), n in stream.rejected.items()},
        has_ground_truth=truth is not None,
        gps_holdout_fixes=int(result.gps.withheld.sum()),
        gps_holdout_scored_fixes=int(len(hold_t)) if common_fixes else 0,
        gps_holdout_outliers=n_outliers,
        gps_holdout_interpolation_rmse_m=_interpolation_rmse(
            used_t[~ref_out], used_xy[~ref_out], hold_t, hold_xy),
        gps_holdout_interpolation_outliers=int(ref_out.sum()),
        gps_outages=[rounded_record(o) for o in outages],
        gps_antenna=antenna,
        estimators=ests,
        ate_common=common[1] if common else None)


def _track_scores(r, duration: float, truth: Trajectory | None, pose_error: str | None,
                  common_fixes: bool, held: tuple, own: tuple, used: tuple,
                  outages: list[metrics.Outage], antenna: GpsAntenna) -> EstimatorScores:
    """EstimatorRun ``r``'s scores (``score``): ``held`` (t, xy, cov) the withheld fixes it is
    scored on, ``own`` (t, xy) all withheld fixes (where there are no ``common_fixes``),
    ``used`` (t, xy) the fixes the estimators received."""
    tr = r.trajectory
    hold_t, hold_xy, hold_cov = held
    m: dict = {}
    # the coordinates the NEES is scored in (the report's NEES plot reads them back)
    m["pose_error"] = pose_error or _pose_error(r)
    if truth is not None and len(tr):
        m.update(_truth_scores(tr, truth, m["pose_error"]))
    if len(hold_t) and len(tr) > 1:
        e = metrics.holdout_errors(tr, *((hold_t, hold_xy) if common_fixes else own),
                                   antenna.lever_arm, antenna.delay_s)
        if len(e):
            m["gps_holdout_m"] = stats_of(metrics.Stats.of(e))
            if common_fixes:
                m["gps_holdout_rmse_m"] = m["gps_holdout_m"].rmse
                nees = metrics.gate_nis(tr, hold_t, hold_xy, hold_cov, antenna.lever_arm,
                                        antenna.delay_s)
                if np.isfinite(nees).any():
                    m["gps_holdout_nees"] = rounded_record(consistency.summarize(nees, 2))
            else:  # the fixes it was scored on: its own span's
                m["gps_holdout_span_s"] = (num(tr.t[0]), num(tr.t[-1]))
    if len(tr) > 1:
        m["gps_outages"] = _outage_scores(tr, outages, truth, hold_t, hold_xy, hold_cov,
                                          antenna)
        m["gps_residual_corr_s"] = num(_residual_corr(tr, *used, antenna))
    return EstimatorScores(
        final_xy=(num(tr.pose[-1, 0]), num(tr.pose[-1, 1])) if len(tr) else None,
        samples=len(tr),
        runtime_s=num(r.runtime_s),
        rtf=num(duration / r.runtime_s) if r.runtime_s > 0 else None,
        update_ms=_update_latency(r.update_s),
        nis={label: SensorNis(s.sensor, s.kind, s.accepted, s.rejected, rounded_record(s.nis))
             for label, s in consistency.nis_by_sensor(
                 consistency.InnovationTable.from_innovations(r.log.innovations)).items()},
        rejected={f"{s}: {why}": n for (s, why), n in r.log.rejected.items()},
        events=r.log.messages[:EVENTS_KEPT],
        events_total=len(r.log.messages),  # the report says 'first 20 of N'
        error=r.error,
        final_state=calibration_states(r.final_state),
        **m)



def _update_latency(update_s) -> UpdateLatency | None:
    """p50, p99, max and mean (ms) and the count of the per-call timings ``update_s`` (s: an
    array or a ``SpilledColumn``), read a block at a time (``latency_stats``: the percentiles
    exact, the mean summed in float64); None without any."""
    if not len(update_s):
        return None

    def blocks():
        return (b * 1e3 for b in latency_stats.blocks_of(update_s))

    p50, p99, top = latency_stats.percentiles(blocks, (50, 99, 100))
    mean, n = latency_stats.mean(blocks())
    return UpdateLatency(num(p50), num(p99), num(top), num(mean), n)


def _common_ate(tracks: dict[str, Trajectory], truth: Trajectory | None
                ) -> tuple[dict[str, float], CommonSpan] | None:
    """Each track's position RMSE against the truth on one time span and one set of stamps,
    what the verdict ranks on. Each track's own ATE averages over its own span and stamps:
    a track that starts late (a filter waiting for its heading) skips the first seconds, often
    the worst; one that stopped early keeps only its first ones; a lagged track exists only at
    its keyframes (at the fixes), the filters at 10 Hz also between fixes. The span is the
    intersection of the tracks' and the truth's spans, the stamps those of the track with the
    fewest samples in it, each track and the truth linearly interpolated there. Returns
    ({track: rmse}, CommonSpan(n stamps, of track, span (t0, t1))); None with fewer than two
    tracks, no truth, or no common span."""
    live = {n: tr for n, tr in tracks.items() if len(tr) > 1}
    if truth is None or len(truth) < 2 or len(live) < 2:
        return None
    lo = max([tr.t[0] for tr in live.values()] + [truth.t[0]])
    hi = min([tr.t[-1] for tr in live.values()] + [truth.t[-1]])
    inside = {n: tr.t[(tr.t >= lo) & (tr.t <= hi)] for n, tr in live.items()}
    base = min(inside, key=lambda n: len(inside[n]))
    t = inside[base]
    if len(t) < 2:
        return None
    g, _ = metrics.interpolate_xy(truth, t)
    rmse = {}
    for n, tr in live.items():
        xy, _ = metrics.interpolate_xy(tr, t)
        tr.release()
        rmse[n] = num(float(np.sqrt(np.mean(np.sum((xy - g) ** 2, axis=1)))))
    return rmse, CommonSpan(int(len(t)), base, (num(lo), num(hi)))


def offset_surveys(result: RunResult, cfg: Config,
                   recorder: heading_survey.OffsetRecorder | None = None
                   ) -> list[heading_survey.OffsetSurvey]:
    """Each compass's heading offset against the GPS course (``ddfuse.estimation.heading_survey``):
    from ``recorder`` where it watched the run (a BagStream keeps no measurements), else what
    the result holds (``RunResult.offset_surveys``), else from the run's Stream."""
    if recorder is None and result.offset_surveys is not None:
        return result.offset_surveys
    if recorder is None:
        if not isinstance(result.stream, Stream):
            return []
        recorder = heading_survey.recorder_for(cfg)
        for m in result.stream.measurements:
            recorder.add(m)
    return recorder.surveys()


def data_facts(result: RunResult, cfg: Config,
               surveys: list[heading_survey.OffsetSurvey] | None = None) -> DataFacts:
    """What the report states about the data: per sensor topic, kind and message counts; GPS
    fixes used and withheld, their median interval (s); landmarks; path length (from the truth,
    else the GPS fixes); each compass's measured heading offset (``surveys``, default
    ``offset_surveys`` of the run's Stream)."""
    if surveys is None:
        surveys = offset_surveys(result, cfg)
    stream = result.stream
    counts = (Counter((m.sensor, type(m).__name__) for m in stream.measurements)
              if isinstance(stream, Stream) else stream.type_counts())
    sensors = []
    for s in cfg.sensors:
        per_type = {t: n for (name, t), n in counts.items() if name == s.name}
        sensors.append(SensorFacts(s.name, s.topic, s.kind, list(s.use), per_type))
    gps = result.gps
    if result.truth is not None and len(result.truth) > 1:
        length, source = metrics.path_length(result.truth.pose[:, :2]), "ground truth"
    elif len(gps) > 1:
        # through the fixes' block medians: a polyline through the noisy fixes themselves was
        # 4 times the path (metrics.fix_path_length)
        length, source = metrics.fix_path_length(gps.t, gps.xy, gps.cov), "GPS fixes"
    else:
        length, source = None, None
    return DataFacts(
        sensors=sensors, ground_truth_topic=cfg.ground_truth_topic,
        ground_truth_samples=len(result.truth) if result.truth is not None else 0,
        ground_truth_interval_s=num(float(np.median(np.diff(result.truth.t))))
        if result.truth is not None and len(result.truth) > 1 else None,
        gps_fixes=len(gps), gps_fixes_withheld=int(gps.withheld.sum()),
        gps_fix_interval_s=num(float(np.median(np.diff(gps.t)))) if len(gps) > 1 else None,
        landmarks=len(stream.landmarks),
        path_length_m=num(length) if length is not None else None,
        path_length_from=source, t0=stream.t0, t1=stream.t1,
        datum=list(stream.datum) if stream.datum else None,
        heading_offsets=[HeadingOffset.from_json(sv.to_dict()) for sv in surveys],
        gps_bursts=GpsBursts.of_watch(getattr(stream, "watch", None)))


def run_bag(bag: str | Path, cfg: Config, outdir: str | Path, *, names: list[str] | None = None,
            lag: float | None = None, holdout: str | None = None,
            progress: Callable[[str, float], None] | None = None,
            reorder_window: float | None = None,
            notice: Callable[[str], None] | None = None,
            side_process: bool = False, gps_model: str | None = None) -> RunSummary:
    """Decode ``bag`` as a stream (``ddfuse.estimation.bags.BagStream``: memory bounded however long
    the bag), run the selected estimators on it, write results into ``outdir``; returns the
    run's ``RunSummary`` (written as metrics.json: its ``to_json()``). ``reorder_window`` (s)
    overrides the config's. The default set (``names`` None) leaves the batch out of a bag
    spanning more than ``batch_cost.DEFAULT_MAX_SPAN_S``; ``notice`` is told so (and why it leaves
out an estimator the sensors nearly allow: ``estimators.left_out``), or, before the
    batch's whole-run solve, that it is the slow part and how long it should take, when that is
    long (``batch_cost``).

    On a damaged or truncated bag the results of what could be read are written, then BagError
    is raised with ``results_written`` set. While it runs, ``outdir``/.ddfuse-spill holds the
    loop's growing records (tracks and per-call timings, ``runner.run(spill_dir=)``): memory
    stays flat with the bag's length; it is removed once the results are written (or the run
    fails), and a killed run's is removed by the next run into ``outdir``.

    ``side_process``: the estimators on their Python reference path (a cold kernel cache) are
    fed in a forked second process beside the others (``ddfuse.evaluation.side_run``), when the
    machine has a second CPU; the results are the same. ``gps_model`` replaces the config's
    ``gps.model`` for every estimator (``ddfuse run --gps-model``; recorded with
    ``gps_model_option``)."""
    clock = time.perf_counter
    t_enter, startup = clock(), process_age()
    outdir = Path(outdir)
    cfg = with_gps_model(cfg, gps_model)
    chosen = registry.select(cfg, names)
    parse_holdout(holdout)  # a bad spec fails before any decoding
    if names is None and notice is not None:
        for text in registry.left_out(cfg):
            notice(text)
    stream = BagStream(bag, cfg, reorder_window=reorder_window).prime()
    span = stream.recorded_span
    if names is None and "batch" in chosen and span is not None and span > DEFAULT_MAX_SPAN_S:
        chosen = [n for n in chosen if n != "batch"]
        if notice is not None:
            notice(leave_out_notice(span, chosen))
    outdir.mkdir(parents=True, exist_ok=True)
    pose = initial_pose(cfg.initial_pose, stream)
    lag = lag if lag is not None else cfg.smoother.lag
    ests = registry.build(cfg, stream, chosen, lag=lag, pose=pose, tracks=names or None)
    if notice is not None and "batch" in ests:
        announce_solve(ests["batch"], notice)
    decode_before = stream.decode_s
    t_built = clock()
    offsets = heading_survey.recorder_for(cfg)
    spill = _spill_dir(outdir)  # the loop's timings, until the results are written
    try:
        result, side, side_wait = run_split(
            lambda: BagStream(bag, cfg, reorder_window=reorder_window).prime(), stream, ests,
            side_names(ests) if side_process else [], holdout=holdout, spill_dir=spill,
            observer=offsets.add,
            progress=(lambda f: progress("decode + estimate", f)) if progress else None,
            notice=notice)
        t_ran = clock()
        input_error = stream.error
        if input_error is not None and not result.messages:
            raise BagError(input_error)
        decode_s = stream.decode_s
        runtimes = {n: result.runs[n].runtime_s for n in ests if n in result.runs}
        if names:  # keep only the tracks asked for ('smoother_lagged' alone drops 'smoother')
            result.runs = {k: v for k, v in result.runs.items() if k in set(names)}
        # an interrupt while the results are scored and written is held until they are complete
        # (a second one acts at once): the run was over, its results are whole
        with held_signals() as held:
            out = score(result, decode_s,
                        {n: getattr(e, "pose_error", "world") for n, e in ests.items()}, cfg=cfg)
            surveys = result.offset_surveys = offset_surveys(result, cfg, offsets)
            out = replace(
                out, config=str(cfg.path) if cfg.path else None,
                initial_pose=("first ground-truth pose" if cfg.initial_pose == "ground_truth"
                              else list(pose) if pose else None),
                lag_s=lag, gps_model=cfg.gps.model, gps_model_option=gps_model is not None,
                estimators_requested=list(names) if names else None, estimators_run=chosen,
                gps_holdout=holdout, input_error=input_error, interrupted=result.interrupted,
                data=data_facts(result, cfg, surveys))
            # the reader's (a topic mostly dropped or silent), then the compass offset's
            out = replace(out, warnings=[*stream.warnings,
                                         *heading_survey.config_warnings(surveys, cfg),
                                         *gps_correlation_warnings(
                                             cfg, result.gps, getattr(stream, "watch", None))])
            config_text = config_text_of(cfg)
            heap.trim()  # scoring's temporaries, before the writers' own
            t_scored = clock()
            with writing_run(outdir, f"ddfuse run of {bag}", result):
                save_run(result, outdir, config_text, frames=(cfg.local_frame, cfg.base_frame),
                         tf=cfg.node.tf)
                out = replace(out, wall_s=timing_split(
                    startup=startup, decode=decode_s, build=t_built - t_enter - decode_before,
                    loop=t_ran - t_built, loop_decode=decode_s - decode_before, runtimes=runtimes,
                    scoring=t_scored - t_ran, writing=clock() - t_scored, side=side,
                    side_wait=side_wait))
                write_metrics(outdir, out.to_json())
        if result.interrupted:
            raise RunInterrupted(f"{result.interrupted}; the results of what was processed are in "
                                 f"{outdir}")
        if held:
            raise RunInterrupted(f"interrupted ({interrupt_name(held[0])}) while the results were "
                                 f"written; they are complete, in {outdir}")
        if input_error:
            err = BagError(f"{input_error}; results for the {stream.duration:.1f} s that could be "
                           f"read are in {outdir}")
            err.results_written = True
            raise err
        return out
    finally:
        shutil.rmtree(spill, ignore_errors=True)


SPILL_DIR = ".ddfuse-spill"  # in the output directory, during a run (``_spill_dir``)


def _spill_dir(outdir: Path) -> Path:
    """``outdir``/SPILL_DIR, made empty: where the loop writes its growing records in blocks
    (``runner.run(spill_dir=)``) until the results are written; what a killed run left there
    is removed. OSError -> OutputError naming it."""
    path = outdir / SPILL_DIR
    shutil.rmtree(path, ignore_errors=True)
    try:
        path.mkdir()
    except OSError as e:
        raise OutputError.of(path, e) from None
    return path


def write_outputs(result: RunResult, outdir: Path, summary: RunSummary,
                  config_text: str | None = None, cfg: Config | None = None) -> None:
    """metrics.json (``summary``), the trajectories (TUM, CSV), estimates.mcap (in ``cfg``'s
    frames, else map/base_link) and run.npz into ``outdir`` (complete, or marked incomplete:
    ``run_files.writing_run``)."""
    frames = (cfg.local_frame, cfg.base_frame) if cfg is not None else ("map", "base_link")
    with writing_run(outdir, "ddfuse.evaluation.pipeline.write_outputs", result):
        save_run(result, outdir, config_text, frames=frames,
                 tf=cfg.node.tf if cfg is not None else None)
        write_metrics(outdir, summary.to_json())
