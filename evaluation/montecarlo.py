"""Monte Carlo consistency and accuracy runs on the simulator: ``ddfuse mc``.

For a simulator scenario and N seeds, each seed is simulated and written as a bag with its
config and landmark map (``evaluation.simulate``) in a temporary directory, read back like any
bag (``ddfuse.estimation.bags.read_stream``) and run through the normal runner
(``ddfuse.estimation.runner.run``) with the chosen estimators plus dead reckoning (``dr``: the same
stream's wheel odometry integrated alone). Per seed and estimator it records the position RMSE,
the dead-reckoning RMSE, the pose NEES and the runtime; across seeds it forms Bar-Shalom's
average NEES and its chi-square band. Seeds run on ``engine.Engine``: local processes (``jobs``)
or a Dask scheduler (``scheduler``).

Each seed's truth of what the filters have a prior for (wheel radius, track width, initial
pose) is drawn from that prior, as the NEES test presumes (``draw_truth``; ``fixed_truth``: one
truth for all seeds); errors are taken against the exact simulated truth at each estimate's
stamp. The NEES is of the pose (x m, y m, yaw rad; d = 3) in each estimator's own error
coordinates (``metrics.nees_series``); ANEES is the N-run average NEES eps_bar(k) over the
10 Hz ticks every run has, judged against the per-tick two-sided band
chi2.ppf([0.025, 0.975], N d) / N (``nees_band``; Bar-Shalom et al. 2001, sec. 5.4.2). The
drawn truth, the convention and why the band is not narrowed for the time average:
docs/design/monte-carlo-nees.md.

Library use (a notebook)::

    from ddfuse.evaluation.montecarlo import monte_carlo, to_markdown
    mc = monte_carlo("husky", seeds=range(20), estimators=["ekf", "ekf_igvc"], jobs=2)
    print(to_markdown(mc))
    mc.summary["ekf"].anees                 # typed: evaluation.montecarlo_results
    mc.to_json()                            # what mc_husky.json holds
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path

import numpy as np
from ddfuse.estimation import chi2
from ddfuse.evaluation.atomic_files import write_text
from ddfuse.evaluation.montecarlo_results import (
    CalibrationError,
    CalibrationSummary,
    EstimatorSummary,
    MonteCarloRun,
    SeedRun,
    SeedScores,
)

__all__ = ["nees_band", "run_seed", "aggregate", "monte_carlo", "to_markdown", "write_report"]

OUTPUT_RATE = 10.0  # Hz, estimates recorded by the runner and NEES ticks
POSE_DIM = 3  # x, y, yaw


def nees_band(n_runs: int, dim: int, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided ``prob`` acceptance interval of the N-run average NEES of a ``dim``-dimensional
    state: chi2.ppf((1 -+ prob) / 2, N dim) / N (Bar-Shalom sec. 5.4.2)."""
    if n_runs < 1 or dim < 1:
        raise ValueError(f"need n_runs >= 1 and dim >= 1, got {n_runs}, {dim}")
    a = 0.5 * (1.0 - prob)
    return chi2.ppf(a, n_runs * dim) / n_runs, chi2.ppf(1.0 - a, n_runs * dim) / n_runs


def default_estimators(cfg) -> list[str]:
    """Every EKF the config's sensors allow."""
    from ddfuse.evaluation import estimators as registry

    return [n for n, s in registry.SPECS.items() if n.startswith("ekf") and s.allowed(cfg)]


def _truth_errors(sim, tr, pose_error: str = "world"
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Against the exact truth at each estimate's stamp: the position error (m) of every sample,
    and the output tick indices and pose NEES of the samples with a usable covariance, in the
    estimator's error coordinates ``pose_error`` (``metrics.nees_series``)."""
    from ddfuse.estimation.runner import Trajectory
    from ddfuse.evaluation import metrics

    t_rel = tr.t - sim.t0
    x, y, yaw, _, _ = sim.truth.at(np.clip(t_rel, 0.0, sim.duration))
    ref = Trajectory(tr.t.copy(), np.column_stack([x, y, yaw]), np.full((len(tr), 3, 3), np.nan))
    pos = metrics.pose_errors(tr, ref, max_diff=1e-9).position
    i_nees, nees = metrics.nees_samples(tr, ref, max_diff=1e-9, pose_error=pose_error)
    ticks = np.rint(t_rel[i_nees] * OUTPUT_RATE).astype(np.int64)
    return pos, ticks, nees


def draw_truth(sc, seed: int):
    """The run's truth of what the filters are given priors for, drawn from those priors:
    (scenario with its true wheel radius and track width drawn from N(nominal, geometry_std^2)
    when it states geometry_std, initial pose error (dx m, dy m, dyaw rad) drawn from
    N(0, diag(GIVEN_POSE_STD)^2)). Deterministic per seed (its own random stream)."""
    from dataclasses import replace

    from ddfuse.ekf_baseline import GIVEN_POSE_STD
    from ddfuse.evaluation.simulate import Geometry, _rng

    rng = _rng(seed, "mc_truth")
    z = rng.standard_normal(5)
    if sc.geometry_std is not None:
        g, sd = sc.nominal_geometry, sc.geometry_std
        sc = replace(sc, true_geometry=Geometry(g.wheel_radius + sd.wheel_radius * z[0],
                                                g.track_width + sd.track_width * z[1]))
    s0, s2 = GIVEN_POSE_STD
    return sc, (s0 * z[2], s0 * z[3], s2 * z[4])


def calibration_truth(sim) -> dict[str, object]:
    """What the filters' calibration states should end at, from the simulation: the odometry
    scales k_v, k_w of its true geometry, and with an IMU its heading offset (rad) and the gyro
    bias as a function of the time since the start (rad/s; it walks)."""
    sc = sim.scenario
    g, ng = sc.true_geometry, sc.nominal_geometry
    kv = g.wheel_radius / ng.wheel_radius
    truth: dict[str, object] = {"k_v": kv, "k_w": kv * ng.track_width / g.track_width}
    if sc.imu is not None and sim.imu is not None:
        truth["hoff"] = sc.imu.heading_offset
        t, b = np.asarray(sim.imu.t), np.asarray(sim.imu.bias)
        truth["bg"] = lambda t_rel: float(np.interp(t_rel, t, b))
    return truth


def _calibration_errors(sim, final) -> dict[str, CalibrationError]:
    """Per calibration state an estimator ends the run with (``pipeline.calibration_entries``
    of its final state): the error against the simulation's truth and that error over the
    estimator's sigma."""
    from ddfuse.estimation.estimator import wrap_angle
    from ddfuse.evaluation.pipeline import calibration_entries

    truth = calibration_truth(sim)
    out = {}
    for label, value, sigma in calibration_entries(final):
        true = truth.get(label)
        if true is None or not math.isfinite(value):
            continue
        if callable(true):
            true = true(final.t - sim.t0)
        err = wrap_angle(value - true) if label == "hoff" else value - true
        out[label] = CalibrationError(err, err / sigma if sigma else None)
    return out


def seed_data(scenario: str, seed: int, duration: float | None = None,
              fixed_truth: bool = False) -> tuple:
    """What one Monte Carlo seed runs on: (sim, config, stream, initial pose, initial pose
    error). ``scenario`` simulated with ``seed`` (its true geometry and the initial pose error
    drawn per seed by ``draw_truth`` unless ``fixed_truth``), written as a bag in a temporary
    directory and read back as a user's bag would be; the pose is the config's initial pose
    plus that error (m, m, rad), None when the config has none."""
    from ddfuse.estimation.bags import read_stream
    from ddfuse.estimation.config import load_config
    from ddfuse.estimation.runner import initial_pose
    from ddfuse.evaluation.simulate import get_scenario, simulate, write_bag

    sc = get_scenario(scenario, duration)
    err0 = (0.0, 0.0, 0.0)
    if not fixed_truth:
        sc, err0 = draw_truth(sc, seed)
    sim = simulate(sc, seed=seed)
    with tempfile.TemporaryDirectory(prefix="ddfuse-mc-") as d:
        bag, cfg_path, _ = write_bag(sim, Path(d) / f"{scenario}-{seed}.bag")
        cfg = load_config(cfg_path)
        stream = read_stream(bag, cfg)
    pose = initial_pose(cfg.initial_pose, stream)
    if pose is not None:
        pose = (pose[0] + err0[0], pose[1] + err0[1], pose[2] + err0[2])
    return sim, cfg, stream, pose, err0


def run_seed(scenario: str, seed: int, estimators: list[str] | None = None,
             duration: float | None = None, fixed_truth: bool = False,
             lag: float | None = None) -> SeedRun:
    """Simulate ``scenario`` with ``seed``, write and read it back as a bag in a temporary
    directory, run ``estimators`` (default: every EKF its config allows) and dead reckoning.

    Unless ``fixed_truth``, the true geometry and the initial pose error are drawn per seed
    (``draw_truth``); with it, every seed has the scenario's true geometry and every estimator
    starts at the exact true pose.

    Returns the seed's ``SeedRun``: per estimator the RMSE, mean NEES, runtime, error, the
    per-sample output tick indices and NEES (for the across-run average) and the final
    calibration states' errors (``_calibration_errors``)."""
    from ddfuse.estimation.runner import run
    from ddfuse.evaluation import estimators as registry

    sim, cfg, stream, pose, err0 = seed_data(scenario, seed, duration, fixed_truth)
    names = registry.names_list(estimators) if estimators else default_estimators(cfg)
    chosen = registry.select(cfg, names)
    if "dr" not in chosen:
        chosen.append("dr")
    built = registry.build(cfg, stream, chosen, lag=lag, pose=pose)
    result = run(stream, built, output_rate=OUTPUT_RATE)
    g = sim.scenario.true_geometry
    scores = {}
    for name, r in result.runs.items():
        tr = r.trajectory
        if len(tr) == 0:
            scores[name] = SeedScores(rmse_m=math.nan, nees_mean=math.nan, runtime_s=r.runtime_s,
                                      error=r.error or "no output", ticks=[], nees=[])
            continue
        pose_error = getattr(built.get(name), "pose_error", "world")
        pos, ticks, nees = _truth_errors(sim, tr, pose_error)
        scores[name] = SeedScores(
            pose_error=pose_error,
            rmse_m=float(np.sqrt(np.mean(pos * pos))),
            nees_mean=float(nees.mean()) if len(nees) else math.nan,
            runtime_s=r.runtime_s,
            error=r.error,
            ticks=ticks.tolist(),
            nees=nees.tolist(),
            calibration=_calibration_errors(sim, r.final_state))
    return SeedRun(seed, scenario, sim.duration, [g.wheel_radius, g.track_width], list(err0),
                   scores, scores["dr"].rmse_m)


def _seed_job(args) -> SeedRun:
    scenario, seed, estimators, duration, fixed_truth, lag = args
    t0 = time.perf_counter()
    res = run_seed(scenario, seed, estimators, duration, fixed_truth, lag)
    return replace(res, wall_s=time.perf_counter() - t0)


def _bin_means(series: dict[int, float], width: int) -> dict[int, float]:
    """{tick: nees} -> {tick // width: mean nees in that bin}."""
    bins: dict[int, list[float]] = {}
    for k, v in series.items():
        bins.setdefault(k // width, []).append(v)
    return {b: float(np.mean(v)) for b, v in bins.items()}


def _calibration_summary(per_run: list[dict[str, CalibrationError]]
                         ) -> dict[str, CalibrationSummary]:
    """Per calibration state over the runs that have it (``aggregate`` passes those that did not
    fail): n, the mean and RMS of the final error, and the RMS of error / sigma (about 1 for a
    consistent estimator)."""
    labels = list(dict.fromkeys(label for c in per_run for label in c))
    out = {}
    for label in labels:
        err = np.array([c[label].error for c in per_run if label in c])
        z = np.array([c[label].z for c in per_run if label in c and c[label].z is not None])
        out[label] = CalibrationSummary(len(err), float(err.mean()),
                                        float(np.sqrt(np.mean(err**2))),
                                        float(np.sqrt(np.mean(z**2))) if len(z) else None)
    return out


def aggregate(per_seed: list[SeedRun], prob: float = 0.95) -> dict[str, EstimatorSummary]:
    """Across-seed statistics per estimator (the NEES convention: docs/design/monte-carlo-nees.md):
    runs, rmse_mean/max (m), dr_rmse_mean (m), ratio (DR RMSE / RMSE, of the means) and
    ratio_min (the worst seed), anees, band, anees_in_band, frac_ticks_in_band, runtime_mean (s),
    the per-seed RMSE and mean NEES, and the errors raised."""
    names = sorted({n for r in per_seed for n in r.estimators})
    out: dict[str, EstimatorSummary] = {}
    for name in names:
        rows = [(r, r.estimators[name]) for r in per_seed if name in r.estimators]
        rmse = np.array([e.rmse_m for _, e in rows])
        dr = np.array([r.dr_rmse_m for r, _ in rows])
        entry = EstimatorSummary(
            runs=len(rows),
            seeds=[r.seed for r, _ in rows],
            rmse_m=rmse.tolist(),
            rmse_mean=float(np.mean(rmse)),
            rmse_max=float(np.max(rmse)),
            dr_rmse_mean=float(np.mean(dr)),
            ratio=float(np.mean(dr) / np.mean(rmse)),
            ratio_min=float(np.min(dr / rmse)),
            runtime_mean=float(np.mean([e.runtime_s for _, e in rows])),
            nees_mean_per_seed=[e.nees_mean for _, e in rows],
            errors=[e.error for _, e in rows if e.error],
            dim=POSE_DIM,
            # a run that broke down ends with meaningless states (k_w -9e20): left out
            calibration=_calibration_summary([e.calibration or {} for _, e in rows
                                              if not e.error]))
        # N-run average NEES per tick, over the ticks every run has
        series = [dict(zip(e.ticks, e.nees, strict=True)) for _, e in rows]
        common = sorted(set.intersection(*(set(s) for s in series))) if series else []
        shortest = min((len(x) for x in series), default=0)
        if series and len(common) < 0.5 * shortest:
            # Samples off the 10 Hz grid (the lagged and batch tracks are at keyframes, at GPS
            # stamps that differ per seed): the ticks are then 1 s bins, each run contributing
            # the mean of its NEES samples in the bin. The mean is unchanged; the spread of a
            # bin's value shrinks, so the per-tick in-band fraction is only indicative there.
            series = [_bin_means(x, int(OUTPUT_RATE)) for x in series]
            common = sorted(set.intersection(*(set(x) for x in series)))
        if name != "dr" and common:
            eps_bar = np.array([np.mean([s[k] for s in series]) for k in common])
            lo, hi = nees_band(len(rows), POSE_DIM, prob)
            anees = float(eps_bar.mean())
            entry = replace(
                entry, anees=anees, band=[lo, hi], anees_in_band=bool(lo <= anees <= hi),
                frac_ticks_in_band=float(np.mean((eps_bar >= lo) & (eps_bar <= hi))),
                ticks=len(common))
        else:
            entry = replace(entry, ticks=0)
        out[name] = entry
    return out


def monte_carlo(scenario: str, seeds: Iterable[int], estimators: list[str] | None = None, *,
                duration: float | None = None, jobs: int | None = None,
                prob: float = 0.95, fixed_truth: bool = False,
                lag: float | None = None, scheduler: str | None = None,
                engine=None) -> MonteCarloRun:
    """Run ``seeds`` of ``scenario`` on ``engine`` (an entered ``engine.Engine``; default one
    made from ``scheduler`` and ``jobs``: a Dask scheduler, else ``jobs`` local processes,
    default os.cpu_count(); 1 runs in this process) and aggregate: the settings, ``per_seed``
    (``run_seed``'s results without the NEES series), ``summary`` (``aggregate``) and the NEES
    convention in words. A seed that fails raises ValueError naming it."""
    from ddfuse.evaluation.engine import Engine

    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("monte_carlo: no seeds")
    from ddfuse.evaluation.simulate import get_scenario

    get_scenario(scenario, duration)  # a bad scenario or duration fails here, not in a worker
    if jobs is not None and jobs < 1:
        raise ValueError(f"jobs: expected at least 1 process, got {jobs}")
    args = [(scenario, s, estimators, duration, fixed_truth, lag) for s in seeds]
    if engine is None:
        jobs = min(jobs or os.cpu_count() or 1, len(args))
        with Engine(scheduler, jobs) as own:
            return monte_carlo(scenario, seeds, estimators, duration=duration, prob=prob,
                               fixed_truth=fixed_truth, lag=lag, engine=own)
    per_seed: list[SeedRun | None] = [None] * len(args)
    for o in engine.map(_seed_job, args):
        if o.error is not None:
            raise ValueError(f"seed {seeds[o.index]}: {o.error}")
        per_seed[o.index] = o.value
    return MonteCarloRun(
        scenario, seeds, per_seed[0].duration_s, estimators, fixed_truth, lag,
        [r.lean() for r in per_seed], aggregate(per_seed, prob),
        "pose (x, y, yaw), d = 3; ANEES = mean over 10 Hz ticks of the N-run average NEES; "
        f"band = chi2.ppf([{(1 - prob) / 2:g}, {1 - (1 - prob) / 2:g}], N d) / N (Bar-Shalom "
        "et al. 2001, sec. 5.4.2), the per-tick band")


def _f(v, spec: str = ".3f") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def _run_settings(mc: MonteCarloRun) -> str:
    """How the runs were made, beyond scenario, seeds and duration: where the truth came from
    (--fixed-truth) and the smoother's lag (--lag, s)."""
    from ddfuse.evaluation.simulate import SMOOTHER_LAG

    if mc.fixed_truth:
        truth = ("Truth fixed (--fixed-truth): every seed has the scenario's true geometry and "
                 "starts the estimators at the exact true pose.")
    else:
        truth = ("Truth drawn per seed from the priors the config states: the true wheel radius "
                 "and track width, and the initial pose error the estimators start with.")
    lag = mc.lag_s
    lag_text = (f"Smoother lag {lag:g} s (--lag)." if lag is not None else
                f"Smoother lag {SMOOTHER_LAG:g} s (the simulated config's).")
    return f"{truth} {lag_text}"


def _error_lines(mc: MonteCarloRun) -> list[str]:
    """One list item per run that stopped with an error, with its seed (from ``per_seed`` when
    the run has it, else the summary's errors without seeds)."""
    found = []
    for r in mc.per_seed or []:
        for name, e in sorted(r.estimators.items()):
            if e.error:
                found.append((name, f"seed {r.seed}", e.error))
    if not mc.per_seed:
        found = [(name, "a seed", err) for name in sorted(mc.summary)
                 for err in mc.summary[name].errors]
    # one line each: an error text may carry newlines (a traceback's last lines)
    return [f"- {name}, {where}: {' '.join(str(err).split())}" for name, where, err in found]


def to_markdown(mc: MonteCarloRun) -> str:
    """The summary as a markdown table (one row per estimator, dead reckoning last), with the
    run settings above it, the runs that stopped with an error listed below it (their rows are
    marked *), and the calibration states' final errors."""
    s = mc.summary
    lines = [
        f"Scenario `{mc.scenario}`, {len(mc.seeds)} seeds "
        f"({mc.seeds[0]}..{mc.seeds[-1]}), {mc.duration_s:g} s each. "
        f"{_run_settings(mc)} NEES: {mc.nees_convention}.",
        "",
        "| estimator | runs | ANEES | 95% band | in band | ticks in band | RMSE mean m | "
        "RMSE max m | DR RMSE m | DR / RMSE | worst seed DR / RMSE | runtime s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in sorted(s, key=lambda n: (n == "dr", n)):
        e = s[name]
        band = f"[{e.band[0]:.3f}, {e.band[1]:.3f}]" if e.band else "-"
        inb = "-" if e.anees_in_band is None else ("yes" if e.anees_in_band else "NO")
        frac = "-" if e.frac_ticks_in_band is None else f"{100 * e.frac_ticks_in_band:.0f}%"
        ratio = "-" if name == "dr" else _f(e.ratio, ".1f")
        worst = "-" if name == "dr" else _f(e.ratio_min, ".1f")
        label = f"{name} *" if e.errors else name
        lines.append(
            f"| {label} | {e.runs} | {_f(e.anees)} | {band} | {inb} | {frac} | "
            f"{_f(e.rmse_mean)} | {_f(e.rmse_max)} | {_f(e.dr_rmse_mean)} | "
            f"{ratio} | {worst} | {_f(e.runtime_mean, '.2f')} |")
    errors = _error_lines(mc)
    if errors:
        # Below the table, not as a row in it: a one-cell row breaks the 12-column table.
        lines += ["", "\\* Runs that stopped with an error: the row's figures include what such "
                  "a run estimated before it stopped; the calibration table leaves those runs "
                  "out.", ""]
        lines += errors
    cal = [(name, label, c) for name in sorted(s) for label, c in
           (s[name].calibration or {}).items()]
    if cal:
        geometry = ("the scenario's true geometry, the same in every seed (--fixed-truth)"
                    if mc.fixed_truth else "the geometry drawn for each seed")
        lines += ["", "Calibration states at the end of each run against the simulation's truth: "
                  "k_v, k_w, the odometry's speed and yaw-rate scale factors (k_v = r / r_nominal, "
                  f"k_w = k_v L_nominal / L for wheel radius r, track width L) of {geometry}; "
                  "hoff, the IMU's heading offset (rad); bg, the gyro bias (rad/s) "
                  "at the time of the final state. RMS of error / sigma is about 1 for a "
                  "consistent estimator; the two-sided 95% range for "
                  f"{len(mc.seeds)} runs is "
                  f"[{math.sqrt(chi2.ppf(0.025, len(mc.seeds)) / len(mc.seeds)):.2f}, "
                  f"{math.sqrt(chi2.ppf(0.975, len(mc.seeds)) / len(mc.seeds)):.2f}].",
                  "", "| estimator | state | runs | error mean | error RMS | RMS error / sigma |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {name} | {label} | {c.n} | {c.error_mean:+.2e} | "
                  f"{c.error_rms:.2e} | {_f(c.z_rms, '.2f')} |" for name, label, c in cal]
    return "\n".join(lines) + "\n"


def report_stem(mc: MonteCarloRun) -> str:
    """``mc_<scenario>``, with ``_fixed-truth`` and ``_lag<S>`` when the run says so: runs of
    one scenario with other settings into one directory do not overwrite each other."""
    stem = f"mc_{mc.scenario}"
    if mc.fixed_truth:
        stem += "_fixed-truth"
    if mc.lag_s is not None:
        stem += f"_lag{mc.lag_s:g}"
    return stem


def write_report(mc: MonteCarloRun, outdir: str | Path) -> tuple[Path, Path]:
    """Write ``<stem>.json`` and ``<stem>.md`` into ``outdir`` (``report_stem``)."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    j = outdir / f"{report_stem(mc)}.json"
    m = outdir / f"{report_stem(mc)}.md"
    write_text(j, json.dumps(mc.to_json(), indent=2, default=float) + "\n")
    write_text(m, to_markdown(mc))
    return j, m
