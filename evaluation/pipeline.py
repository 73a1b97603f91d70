"""The main job: read a bag, run the estimators side by side, score them, write the results.

``run_bag`` returns the metrics dictionary that ``OUTDIR/metrics.json`` holds and writes every
trajectory as ``OUTDIR/<track>.tum`` and ``.csv`` (and ``ground_truth.tum`` when there is truth).
Values that cannot be computed (no truth, no hold-out) are None.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from estimation.bags import read_stream
from estimation.config import Config
from estimation.errors import BagError
from estimation.runner import RunResult, initial_pose, run
from evaluation import estimators as registry
from evaluation import metrics
from evaluation.export import write_csv, write_tum


def _num(v) -> float | None:
    return None if v is None or not math.isfinite(v) else round(float(v), 6)


def score(result: RunResult, decode_s: float = 0.0) -> dict:
    """The metrics dictionary of a run (see module docstring)."""
    stream = result.stream
    duration = stream.duration
    hold_t = np.array([f.t for f in result.holdout])
    hold_xy = np.array([f.enu[:2] for f in result.holdout]).reshape(-1, 2)
    out: dict = {
        "bag": stream.source,
        "duration_s": _num(duration),
        "decode_s": _num(decode_s),
        "messages": len(stream.measurements),
        "rejected_messages": {f"{topic}: {reason}": n
                              for (topic, reason), n in stream.rejected.items()},
        "has_ground_truth": result.truth is not None,
        "gps_holdout_fixes": len(result.holdout),
        "estimators": {},
    }
    for name, r in result.runs.items():
        tr = r.trajectory
        m: dict = {
            "final_xy": [_num(tr.pose[-1, 0]), _num(tr.pose[-1, 1])] if len(tr) else None,
            "samples": len(tr),
            "ate_rmse_m": None, "ate_max_m": None, "rpe_rmse_m": None, "yaw_rmse_deg": None,
            "nees_mean": None, "gps_holdout_rmse_m": None,
            "runtime_s": _num(r.runtime_s),
            "rtf": _num(duration / r.runtime_s) if r.runtime_s > 0 else None,
            "update_ms": {k: _num(float(np.percentile(r.update_s, q)) * 1e3)
                          for k, q in (("p50", 50), ("p99", 99), ("max", 100))}
            if len(r.update_s) else None,
            "rejected": {f"{s}: {why}": n for (s, why), n in r.log.rejected.items()},
            "events": r.log.messages[:20],
            "error": r.error,
        }
        if result.truth is not None and len(tr):
            err = metrics.pose_errors(tr, result.truth)
            if len(err.t):
                m["ate_rmse_m"] = _num(metrics.Stats.of(err.position).rmse)
                m["ate_max_m"] = _num(float(err.position.max()))
                yaw = err.dyaw[np.isfinite(err.dyaw)]
                m["yaw_rmse_deg"] = _num(math.degrees(metrics.Stats.of(yaw).rmse)) if len(
                    yaw) else None
                m["rpe_rmse_m"] = _num(metrics.rpe(tr, result.truth, 1.0)[0].rmse)
                n = metrics.nees(tr, result.truth)
                m["nees_mean"] = _num(float(n.mean())) if len(n) else None
        if len(hold_t) and len(tr) > 1:
            e = metrics.holdout_errors(tr, hold_t, hold_xy)
            m["gps_holdout_rmse_m"] = _num(metrics.Stats.of(e).rmse) if len(e) else None
        out["estimators"][name] = m
    return out


def run_bag(bag: str | Path, cfg: Config, outdir: str | Path, *, names: list[str] | None = None,
            lag: float | None = None, holdout: str | None = None,
            progress: Callable[[str, float], None] | None = None) -> dict:
    """Decode ``bag``, run the selected estimators, write results into ``outdir``; returns the
    metrics dictionary (also written as metrics.json)."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    chosen = registry.select(cfg, names)
    t_a = time.perf_counter()
    input_error = None
    try:
        stream = read_stream(bag, cfg, progress=(lambda f: progress("decode", f)) if progress
                             else None)
    except BagError as e:
        # A truncated or damaged bag: estimate on what was read, write it, then report.
        if e.partial is None or not e.partial.measurements:
            raise
        stream, input_error = e.partial, str(e)
    decode_s = time.perf_counter() - t_a
    pose = initial_pose(cfg.initial_pose, stream)
    lag = lag if lag is not None else cfg.smoother.lag
    ests = {n: registry.SPECS[n].build(cfg, stream, pose, lag) for n in chosen}
    result = run(stream, ests, holdout=holdout,
                 progress=(lambda f: progress("estimate", f)) if progress else None)
    if names:  # keep only the tracks asked for ('smoother_lagged' alone drops 'smoother')
        result.runs = {k: v for k, v in result.runs.items() if k in set(names)}
    out = score(result, decode_s)
    out["config"] = str(cfg.path) if cfg.path else None
    out["initial_pose"] = ("first ground-truth pose" if cfg.initial_pose == "ground_truth"
                           else list(pose) if pose else None)
    out["lag_s"] = lag
    out["gps_holdout"] = holdout
    out["input_error"] = input_error
    write_outputs(result, outdir, out)
    if input_error:
        raise BagError(f"{input_error}; results for the {stream.duration:.1f} s that could be "
                       f"read are in {outdir}")
    return out


def write_outputs(result: RunResult, outdir: Path, metrics_dict: dict) -> None:
    for name, r in result.runs.items():
        if len(r.trajectory):
            write_tum(outdir / f"{name}.tum", r.trajectory)
            write_csv(outdir / f"{name}.csv", r.trajectory)
    if result.truth is not None:
        write_tum(outdir / "ground_truth.tum", result.truth)
    (outdir / "metrics.json").write_text(json.dumps(metrics_dict, indent=2) + "\n")
