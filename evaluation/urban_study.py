"""The urban GPS study (issue 31): the ``urban`` scenario over seeds, every estimator, the
smoother and batch under each GPS model of ``gps.model``. A script, not a test; its table is
docs/results/urban.md.

    python examples/urban_study.py --seeds 0-19 --models default,cauchy --json urban.json
    python examples/urban_study.py --json urban.json --table

Per seed and estimator: position RMSE against the truth (m, at the 10 Hz outputs), the final
position error (m), the mean pose NEES (d = 3) and the GPS fixes the estimator rejected or took
for outliers; per seed the raw fixes' horizontal RMSE (m). CPU seconds (``time.process_time``)
per estimator run are recorded, not wall time.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import replace

import numpy as np

EKFS = ("ekf", "ekf_igvc")
SMOOTHERS = ("smoother", "batch")  # 'smoother' gives the smoother and smoother_lagged tracks


def _score(sim, r, pose_error):
    from ddfuse.evaluation.montecarlo import _truth_errors

    pos, _, nees = _truth_errors(sim, r.trajectory, pose_error)
    rej = {f"{k[0]}: {k[1]}" if isinstance(k, tuple) else str(k): int(v)
           for k, v in r.log.rejected.items()}
    return {"rmse_m": float(np.sqrt(np.mean(pos * pos))) if len(pos) else math.nan,
            "final_m": float(pos[-1]) if len(pos) else math.nan,
            "nees": float(np.mean(nees)) if len(nees) else math.nan,
            "rejected": rej, "error": r.error}


def run_seed(seed: int, models: list[str], duration: float | None = None,
             scenario: str = "urban", estimators: list[str] | None = None) -> dict:
    """One seed of ``scenario``: the EKFs and dead reckoning under the config's own model, the
    smoother and batch per GPS model, and the EKFs again under each robust one (their model:
    ekf_baseline/gps_robust.py); ``estimators``: only these (None: all)."""
    from ddfuse.estimation.runner import run
    from ddfuse.evaluation import estimators as registry
    from ddfuse.evaluation.montecarlo import OUTPUT_RATE, seed_data

    sim, cfg, stream, pose, _ = seed_data(scenario, seed, duration)
    g = sim.gps
    e = g.enu[:, :2] - g.true_enu[:, :2]
    out = {"seed": seed, "raw_gps_rmse_m": float(np.sqrt(np.mean(np.sum(e * e, axis=1)))),
           "fixes": int(len(g.t)),
           "environment": ({str(k): int(np.sum(g.environment == k)) for k in range(4)}
                           if g.environment is not None else None),
           "runs": {}}
    jobs = [("", cfg, list(EKFS) + ["dr"])]
    for m in models:
        c = replace(cfg, gps=replace(cfg.gps, model=m))
        jobs.append((m, c, list(SMOOTHERS) + (list(EKFS) if c.gps.robust else [])))
    for model, c, names in jobs:
        names = [n for n in names if estimators is None or n in estimators]
        if not names:
            continue
        built = registry.build(c, stream, registry.select(c, names), pose=pose)
        t0 = time.process_time()
        result = run(stream, built, output_rate=OUTPUT_RATE)
        cpu = time.process_time() - t0
        for name, r in result.runs.items():
            s = _score(sim, r, getattr(built.get(name), "pose_error", "world"))
            s["cpu_s_all"] = cpu
            s["notes"] = [n for n in r.log.messages if "disagree" in n or "agrees" in n][:6]
            out["runs"][f"{name}[{model}]" if model else name] = s
    return out


def table(results: list[dict]) -> str:
    """The markdown table of docs/results/urban.md: per estimator (and model) over the seeds,
    the mean position RMSE, its mean ratio to the seed's raw GPS RMSE and to the seed's best
    EKF (any EKF run of the seed, under any model), the largest final error over the RMSE, the
    mean of the per-seed mean NEES (d = 3), the
    fixes rejected or taken for outliers per seed, and the runs that stopped."""
    names = sorted({n for r in results for n in r["runs"]}, key=lambda n: (
        n.split("[")[0] != "dr", "[" in n, n.split("[")[-1], n))
    raw = np.array([r["raw_gps_rmse_m"] for r in results])
    best_ekf = np.array([min(v["rmse_m"] for n, v in r["runs"].items()
                             if n.split("[")[0] in EKFS) for r in results])
    rows = ["| estimator [gps.model] | RMSE m (mean, max) | / raw GPS | / best EKF | "
            "final / RMSE (max) | NEES mean (median) | GPS rejected or outliers / seed | "
            "stopped |", "|---|---|---|---|---|---|---|---|"]
    for n in names:
        rm = np.array([r["runs"][n]["rmse_m"] for r in results if n in r["runs"]])
        fin = np.array([r["runs"][n]["final_m"] for r in results if n in r["runs"]])
        ne = np.array([r["runs"][n]["nees"] for r in results if n in r["runs"]])
        has = np.array([n in r["runs"] for r in results])
        rej = [sum(v for k, v in r["runs"][n]["rejected"].items()
                   if k.split(": ")[-1] in ("gate", "outlier")) for r in results if n in r["runs"]]
        stopped = sum(1 for r in results if n in r["runs"] and r["runs"][n]["error"])
        rows.append(
            f"| {n} | {np.nanmean(rm):.2f}, {np.nanmax(rm):.2f} | "
            f"{np.nanmean(rm / raw[has]):.2f} | {np.nanmean(rm / best_ekf[has]):.2f} | "
            f"{np.nanmax(fin / rm):.2f} | {_nees_cell(ne)} | "
            f"{np.mean(rej):.0f} | {stopped} |")
    head = (f"{len(results)} seeds ({', '.join(str(r['seed']) for r in results)}); raw GPS "
            f"RMSE {raw.mean():.2f} m mean ({raw.min():.2f}-{raw.max():.2f}).")
    return head + "\n\n" + "\n".join(rows) + "\n"


def _nees_cell(ne: np.ndarray) -> str:
    """'mean (median)' of the seeds' NEES; '-' where no seed has one (dead reckoning's is NaN
    when it states no covariance)."""
    ne = ne[np.isfinite(ne)]
    return f"{ne.mean():.1f} ({np.median(ne):.1f})" if len(ne) else "-"


def merge(results: list[dict]) -> list[dict]:
    """The records of several studies joined per seed (their runs together), by seed."""
    out: dict[int, dict] = {}
    for r in results:
        if r["seed"] in out:
            out[r["seed"]]["runs"].update(r["runs"])
        else:
            out[r["seed"]] = {**r, "runs": dict(r["runs"])}
    return [out[s] for s in sorted(out)]


def run_study(seeds: list[int], models: list[str], path: str, duration: float | None = None,
              scenario: str = "urban", done=None, estimators: list[str] | None = None
              ) -> list[dict]:
    """``run_seed`` for each seed not yet in the JSON file ``path``, the file rewritten after
    every seed (an interrupted study keeps its seeds); ``done(seed)`` is called after each.
    Returns every seed's record."""
    results = []
    try:
        with open(path) as f:
            results = json.load(f)
    except (OSError, ValueError):
        pass
    have = {r["seed"] for r in results}
    for seed in seeds:
        if seed in have:
            continue
        results.append(run_seed(seed, models, duration, scenario, estimators))
        with open(path, "w") as f:
            json.dump(results, f, indent=1)
        if done is not None:
            done(seed)
    return results
