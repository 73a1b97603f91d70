"""``ddfuse run --tune``: tune the config's noise values on the bag, then run the comparison
twice, with the config as given and with the tuned one (the same values for every estimator:
one config each time).

The output directory ``OUT`` holds, where a user looks first, the tuned config's run: its
usual results (metrics.json, tracks, run.npz, report.html), ``tuned.yaml`` (the tuned config,
as ``ddfuse tune -o`` writes it) and ``tuning.json`` (what the tuning found: ``tuning_json``);
``OUT/shipped/`` holds the given config's run, a complete output directory of its own. The
report of ``OUT`` has the section "What tuning changed" (``evaluation.report_tuning``), which
reads ``tuning.json`` and ``shipped/metrics.json`` beside its own results.

Tuning that applies nothing (no value informed by the data: a bag too short or too static; a
bag that cannot be read whole; a search that failed) is no error: the run goes on once, with
the config as given, into ``OUT``, no ``tuned.yaml`` and no ``shipped/``, and ``tuning.json``
says why (``why_not``). Ctrl-C during the tuning leaves nothing written; tuned.yaml and
tuning.json are written together or not at all (``held_signals``).
"""

from __future__ import annotations

import datetime
import json
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from ddfuse.estimation.config import Config, parse_config_text, with_gps_model
from ddfuse.estimation.errors import BagError, DdfuseError
from ddfuse.estimation.interrupts import deliver, held_signals, interrupt_name
from ddfuse.evaluation.atomic_files import remove, write_text
from ddfuse.evaluation.pipeline import run_bag
from ddfuse.evaluation.scores import RunSummary, num
from ddfuse.evaluation.tune import MIN_INFORMATION, Check, TuneResult, check, tune
from ddfuse.evaluation.tuning_files import SHIPPED_DIR, TUNED_CONFIG, TUNING_FILE, read_tuning

__all__ = ["SHIPPED_DIR", "TUNED_CONFIG", "TUNING_FILE", "TunedRuns", "Tuning", "read_tuning",
           "run_tuned", "tune_on_bag", "tuning_json"]


Progress = Callable[[str, float], None]


@dataclass
class Tuning:
    """What tuning on a bag gave. ``result``: the search's (None when it could not run);
    ``before`` / ``after``: the tuning estimator run with the config's values and the tuned
    ones (NIS per sensor, hold-out score), None when nothing is applied; ``why_not``: why the
    tuned values are not applied (None: they are)."""

    result: TuneResult | None
    before: Check | None = None
    after: Check | None = None
    why_not: str | None = None

    @property
    def applied(self) -> bool:
        return self.why_not is None


def changed(result: TuneResult) -> list:
    """The ``Tuned`` entries whose value the tuning set (tuned, or at a bound of the search)."""
    return [t for t in result.tuned if t.status != "not informed" and t.value is not None]


def tune_on_bag(bag: str | Path, cfg: Config, *, holdout: str | None = None,
                reorder_window: float | None = None, jobs: int | None = None,
                progress: Progress | None = None) -> Tuning:
    """Read ``bag`` whole and tune ``cfg``'s noise values on it (``evaluation.tune.tune``, the
    GPS fixes of ``holdout`` kept out of the fit), then run the tuning estimator with the
    config's values and the tuned ones (``check``). A bag that cannot be read whole, a search
    that fails, or one that informs no value gives a ``Tuning`` with ``why_not`` saying so
    (not an error: the run goes on with the config as given). ``cfg`` is left as it was read."""
    from ddfuse.estimation.bags import read_stream

    say = progress or (lambda stage, f: None)
    try:
        stream = read_stream(bag, cfg, progress=lambda f: say("read", f),
                             reorder_window=reorder_window)
    except BagError as e:
        return Tuning(None, why_not=f"the bag could not be read whole to tune on ({e})")
    try:
        result = tune(cfg, stream, holdout=holdout, jobs=jobs, progress=say)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError, BrokenProcessPool,
            DdfuseError) as e:
        return Tuning(None, why_not=f"the search failed ({type(e).__name__}: {e})")
    if not changed(result):
        return Tuning(result, why_not=(
            f"no value is informed by the data (each has under {MIN_INFORMATION:g} of "
            f"Fisher information on its log over the {result.innovations} innovations of "
            f"the {result.estimator} EKF: the bag is too short or too static, no sensor ties "
            "the innovations to it, or the EKF's own twist random walk explains them; each "
            "value's reason is in tuning.json)"))
    say("before / after", 0.0)
    before = check(cfg, stream, [None] * len(result.tuned), estimator=result.estimator,
                   holdout=holdout, params=[t.param for t in result.tuned])
    say("before / after", 0.5)
    after = check(cfg, stream, result.values(), estimator=result.estimator, holdout=holdout,
                  params=[t.param for t in result.tuned])
    say("before / after", 1.0)
    return Tuning(result, before, after)


def _nis_json(c: Check | None) -> dict:
    return {label: s.to_json() for label, s in c.nis.items()} if c is not None else {}


def tuning_json(tuning: Tuning, *, bag: str, config: str | None, holdout: str | None,
                run_config: str | None) -> dict:
    """``tuning.json``: the bag, the config as given, the hold-out kept out of the fit,
    whether the tuned values were applied (``why_not`` if not), which config the run in this
    directory used (``run_config``: the report's check that the file is this run's); the
    search (estimator, innovations, estimator runs, iterations, wall s, the objective at the
    start and the end, the optimiser's message); per value its key, label, unit, config
    value (``before``, null: the messages' covariance or the estimator's default,
    ``source`` says which), start, tuned value (``after``), status, reason, standard error of
    its log (``se_log``) and Fisher information on its log; the pairs not told apart (their
    correlation); NIS per sensor of the tuning estimator before and after (metrics.json's
    ``nis`` entries) and its GPS hold-out RMSE (m) before and after. Non-finite numbers are
    null."""
    r = tuning.result
    out: dict = {"bag": bag, "config": config, "gps_holdout": holdout,
                 "applied": tuning.applied, "why_not": tuning.why_not,
                 "tuned_config": TUNED_CONFIG if tuning.applied else None,
                 "shipped_run": SHIPPED_DIR if tuning.applied else None,
                 "run_config": run_config}
    if r is not None:
        out.update(
            estimator=r.estimator, innovations=r.innovations, estimator_runs=r.runs,
            iterations=r.iterations, wall_s=num(r.wall_s), nll_start=num(r.nll_start),
            nll_end=num(r.nll_end), message=r.message,
            values=[{"key": t.param.key, "label": t.param.label, "unit": t.param.unit,
                     "before": num(t.param.before), "source": t.param.source,
                     "start": num(t.param.start), "after": num(t.value), "status": t.status,
                     "reason": t.reason, "se_log": num(t.se_log),
                     "information": num(t.information)} for t in r.tuned],
            pairs=[{"a": a, "b": b, "correlation": num(c)} for a, b, c in r.pairs])
    out["nis"] = {"before": _nis_json(tuning.before), "after": _nis_json(tuning.after)}
    out["holdout_rmse_m"] = {
        "before": num(tuning.before.holdout_rmse_m) if tuning.before else None,
        "after": num(tuning.after.holdout_rmse_m) if tuning.after else None}
    out["holdout_nees"] = {k: (num(c.holdout_nees.mean) if c and c.holdout_nees else None)
                           for k, c in (("before", tuning.before), ("after", tuning.after))}
    return out


@dataclass
class TunedRuns:
    """``run_tuned``'s outcome: the tuning (and tuning.json's dictionary), the run in OUT
    (the tuned config's, or the given one's when nothing was applied) and the given config's
    run in OUT/shipped (None when nothing was applied)."""

    tuning: Tuning
    record: dict  # tuning.json's
    run: RunSummary
    shipped: RunSummary | None


def _write_tuning(outdir: Path, tuning: Tuning, bag: str | Path, config: Path | None,
                  cfg: Config, holdout: str | None,
                  gps_model: str | None = None) -> tuple[Config | None, dict]:
    """tuned.yaml (when applied) and tuning.json into ``outdir``, both or neither (a signal
    meanwhile is acted on after them); the tuned Config, parsed from tuned.yaml's text with
    relative paths (landmark maps) resolved as the given config's, or None; and tuning.json's
    dictionary. ``gps_model`` (``--gps-model``, the tuning's) is written into tuned.yaml."""
    from ddfuse.evaluation.tune_yaml import write_tuned

    outdir.mkdir(parents=True, exist_ok=True)
    tuned_path = outdir / TUNED_CONFIG
    run_config = str(tuned_path) if tuning.applied else (str(cfg.path) if cfg.path else None)
    record = tuning_json(tuning, bag=str(bag), config=str(config) if config else None,
                         holdout=holdout, run_config=run_config)
    with held_signals() as held:
        if tuning.applied:
            date = datetime.date.today().isoformat()
            write_tuned(config, tuned_path, tuning.result, Path(bag).name, date,
                        tuning.before, tuning.after, holdout, gps_model)
        else:
            remove(tuned_path)  # an earlier --tune run's: not this run's config
        write_text(outdir / TUNING_FILE, json.dumps(record, indent=1) + "\n")
    deliver(held)
    if not tuning.applied:
        return None, record
    base = Path(config).parent if config else None
    return parse_config_text(tuned_path.read_text(encoding="utf-8"), str(tuned_path),
                             base), record


def run_tuned(bag: str | Path, config: Path | None, cfg: Config, outdir: str | Path, *,
              holdout: str | None = None,
              reorder_window: float | None = None, jobs: int | None = None,
              progress: Progress | None = None,
              notice: Callable[[str], None] | None = None, **run_args) -> TunedRuns:
    """``ddfuse run --tune`` (module docstring): tune on ``bag`` (``tune_on_bag``), write
    tuned.yaml and tuning.json into ``outdir``, then the comparison (``pipeline.run_bag``;
    ``run_args``: its other options: ``names``, ``lag``) with the tuned config into
    ``outdir`` and with ``cfg`` (the one read from ``config``) into ``outdir``/shipped; with
    nothing applied, once with ``cfg`` into ``outdir``. ``progress(stage, fraction)`` for each
    stage, named 'tuning: ...', 'tuned config: ...' and 'given config: ...'. A run's errors
    (a damaged bag, Ctrl-C: ``run_bag``'s) propagate, with what it wrote in place."""
    outdir = Path(outdir)

    def stage(prefix: str) -> Progress | None:
        return (lambda name, f: progress(f"{prefix}: {name}", f)) if progress else None

    gps_model = run_args.get("gps_model")
    try:
        tuning = tune_on_bag(bag, with_gps_model(cfg, gps_model), holdout=holdout,
                             reorder_window=reorder_window, jobs=jobs, progress=stage("tuning"))
    except KeyboardInterrupt as e:
        raise KeyboardInterrupt(f"interrupted ({interrupt_name(e)}) while tuning: nothing "
                                "written") from None
    tuned, record = _write_tuning(outdir, tuning, bag, config, cfg, holdout, gps_model)
    common = dict(holdout=holdout, reorder_window=reorder_window, **run_args)
    if tuned is None:
        m = run_bag(bag, cfg, outdir, progress=stage("given config"), notice=notice, **common)
        return TunedRuns(tuning, record, m, None)
    m = run_bag(bag, tuned, outdir, progress=stage("tuned config"), notice=notice, **common)
    # the same notices (a batch left out, its solve's time) would come twice
    shipped = run_bag(bag, cfg, outdir / SHIPPED_DIR, progress=stage("given config"), **common)
    return TunedRuns(tuning, record, m, shipped)
