"""``ddfuse run [BAG]``: run the estimators side by side on a bag, score them, print the table.

The results (metrics.json, tracks, run.npz) and the HTML report are written by the library
(``evaluation.pipeline.run_bag``, ``evaluation.report``); this module checks the options before
any work, prints the summary table and the warnings, and shows progress on a terminal.
"""

from __future__ import annotations

import argparse
import sys
from contextlib import nullcontext
from pathlib import Path
from typing import TYPE_CHECKING

from ddfuse.estimation.config import GPS_MODELS
from ddfuse.estimation.errors import DdfuseError
from ddfuse.evaluation.cli.arguments import (
    CONFIG_HELP,
    GPS_HOLDOUT_HELP,
    add_reorder_window,
    estimator_list,
    gps_holdout,
    lag_seconds,
)
from ddfuse.evaluation.cli.output_paths import check_output_dir
from ddfuse.evaluation.cli.report import render
from ddfuse.evaluation.cli.terminal import fmt, headline_text, progress, table
from ddfuse.evaluation.shipped import SAMPLE_BAG, config_for

if TYPE_CHECKING:  # the scores' module loads numpy and scipy: not for `ddfuse --help`
    from ddfuse.evaluation.scores import RunSummary


def add_to(sub) -> None:
    sp = sub.add_parser("run", help="run the estimators side by side on a bag and score them")
    sp.add_argument("bag", type=Path, nargs="?",
                    help=f"bag to run (default: the embedded sample {SAMPLE_BAG.name})")
    sp.add_argument("-c", "--config", type=Path, help=CONFIG_HELP)
    sp.add_argument("-o", "--outdir", type=Path, default=Path("ddfuse-out"),
                    help="output directory (default: ddfuse-out)")
    sp.add_argument("--estimators", type=estimator_list, metavar="LIST",
                    help="comma-separated: ekf, ekf_igvc, ekf_landmark, "
                    "ekf_slam, smoother, smoother_lagged, batch, dr (dead reckoning, by name "
                    "only; default: all but dr that the config's sensors allow)")
    sp.add_argument("--lag", type=lag_seconds, metavar="S",
                    help="smoother lag, s (default: from the config)")
    sp.add_argument("--gps-model", choices=GPS_MODELS, metavar="MODEL",
                    help="the GPS error model of every estimator instead of the config's "
                    f"gps.model: {', '.join(GPS_MODELS)} (docs/design/urban_gps.md says when "
                    "to use which)")
    sp.add_argument("--gps-holdout", type=gps_holdout, metavar="every:K|window:T0:T1",
                    help=GPS_HOLDOUT_HELP)
    add_reorder_window(sp)
    sp.add_argument("--tune", action="store_true",
                    help="first tune the config's noise values on the bag (as 'ddfuse tune', "
                    "the --gps-holdout fixes kept out of the fit), then run with the config "
                    "as given and with the tuned one: the tuned run's results, tuned.yaml and "
                    "tuning.json in OUTDIR, the given config's in OUTDIR/shipped; the report "
                    "says what tuning changed")
    sp.add_argument("--no-report", action="store_true",
                    help="write the results (metrics.json, tracks, run.npz) but not the HTML "
                    "report ('ddfuse report OUTDIR' renders it later)")
    sp.set_defaults(func=command)


# The short table's columns (metrics.json keys) after the one ranked on, each shown where some
# estimator has a value; the speed (rtf) is in the report, with its definition.
SUMMARY_COLUMNS = ("ate_rmse_m", "yaw_rmse_deg", "nees_mean", "gps_holdout_rmse_m")


def print_summary(m: RunSummary, out, headline: bool = True) -> None:
    """The table of a run's summary ``m`` to ``out``: one row per estimator ranked on the
    verdict's score (``verdict.ranking``, its column first; unranked rows last), its other
    scores where any estimator has them and its final position; the wall-time line; then the
    headline (``evaluation.headline``) where ``headline``."""
    from ddfuse.evaluation.headline import headline as make_headline
    from ddfuse.evaluation.verdict import ranking, track_kind

    r = ranking(m)
    ranked = r.figure
    cols = ([ranked] if ranked else []) + [c for c in SUMMARY_COLUMNS if c != ranked and any(
        getattr(e, c) is not None for e in m.estimators.values())]
    names = r.order + [n for n in m.estimators if n not in r.scored]
    out.write(f"{m.bag}: {m.duration_s:.1f} s, {m.messages} measurements, "
              f"decoded in {m.decode_s:.2f} s\n")
    rows = []
    for k, name in enumerate(names):
        e = m.estimators[name]
        rank = str(k + 1) if name in r.scored else "-"
        cells = [rank, name, track_kind(name, m.lag_s)]
        cells += ["-" if getattr(e, c) is None else f"{getattr(e, c):.3f}" for c in cols]
        v = e.final_xy
        cells.append(f"({v[0]:.2f}, {v[1]:.2f})" if v and None not in v else "-")
        if e.error:
            cells.append(f"ERROR: {e.error}")
        rows.append(cells)
    header = ["rank", "estimator", "output", *cols, "final_xy"]
    width = max(len(row) for row in [header, *rows])
    out.write(table(header + [""] * (width - len(header)),
                    [c + [""] * (width - len(c)) for c in rows], left=3))
    if ranked:
        out.write(f"ranked on {ranked} (the verdict's score, m, lower is better); columns are "
                  "metrics.json keys; speeds (rtf) in metrics.json and the report\n")
    w = m.wall_s
    if w:
        side = w.side_process or []
        est = ", ".join(f"{k} {v:.3f}" for k, v in w.estimators.items() if k not in side)
        beside = (f", waiting for the side process {w.side_wait:.3f} (it fed "
                  + ", ".join(f"{k} {w.estimators[k]:.3f}" for k in side if k in w.estimators)
                  + " meanwhile)") if side else ""
        out.write(f"wall time {fmt(w.total, '.3f')} s: startup {fmt(w.startup, '.3f')}, "
                  f"decode {w.decode:.3f}, build {w.build:.3f}, {est}, runner "
                  f"{w.runner:.3f}{beside}, metrics {w.metrics:.3f}, write {w.write:.3f}"
                  " (to metrics.json; the report after it not included)\n")
    if headline:
        out.write(headline_text(make_headline(m).lines()))


def _print_written_summary(outdir: Path) -> None:
    """The summary table of the metrics.json a run stopped short (a damaged bag, Ctrl-C) wrote
    in ``outdir``, on stdout before the error line (as ``online`` and ``bench`` show what was
    read); nothing when it cannot be read back."""
    import json

    from ddfuse.evaluation.scores import RunSummary

    try:
        m = RunSummary.from_json(json.loads((Path(outdir) / "metrics.json").read_text()))
        print_summary(m, sys.stdout)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return
    sys.stdout.flush()


def check_holdout_sensor(cfg, config: Path, holdout: str | None) -> None:
    """Before decoding: a GPS hold-out needs a gps sensor in the config; DdfuseError naming
    the option and the config otherwise (it ran and warned that no fix was withheld)."""
    if holdout and not cfg.of_kind("gps"):
        raise DdfuseError(f"--gps-holdout {holdout}: {config} has no gps sensor")


def command(args: argparse.Namespace) -> int:
    from ddfuse.factors import jitcache

    # EKF kernels missing from numba's cache (the first run after installing): the Python
    # reference filters for this run, the kernels compiled in the background for the next,
    # once this one is over (beside it, the build slows it on a small machine); with --tune
    # at once: the tuning's many runs pick the kernels up as soon as they are cached
    was = jitcache.on_cold_cache()
    jitcache.on_cold_cache("reference")
    try:
        with nullcontext() if args.tune else jitcache.deferred_build():
            return _command(args)
    finally:
        jitcache.on_cold_cache(was)


def _command(args: argparse.Namespace) -> int:
    import time

    from ddfuse.estimation.config import load_config
    from ddfuse.estimation.errors import BagError, RunInterrupted
    from ddfuse.evaluation.pipeline import run_bag

    check_output_dir(args.outdir, "-o")  # before any work
    bag = args.bag or SAMPLE_BAG
    config = config_for(bag, args.config)
    cfg = load_config(config)
    check_holdout_sensor(cfg, config, args.gps_holdout)  # before decoding
    bars = progress()
    tuned = None
    try:
        try:
            options = dict(names=args.estimators, lag=args.lag, gps_model=args.gps_model,
                           holdout=args.gps_holdout,
                           progress=bars.update if bars else None,
                           reorder_window=args.reorder_window,
                           notice=lambda text: _notice(text, bars))
            if args.tune:
                from ddfuse.evaluation.run_tuned import run_tuned

                tuned = run_tuned(bag, config, cfg, args.outdir, **options)
                m = tuned.run
            else:
                m = run_bag(bag, cfg, args.outdir, side_process=True, **options)
        except ValueError as e:
            raise DdfuseError(str(e)) from None
        except (BagError, RunInterrupted) as e:
            # A damaged bag whose readable part was estimated, or a run stopped by Ctrl-C: the
            # table and the report show that part, then the error line says why it is a part.
            if getattr(e, "results_written", False):
                _print_written_summary(args.outdir)
                if not args.no_report:
                    _render_or_say(args.outdir, bars)
            raise
        print_summary(m, sys.stdout)
        for w in m.warnings or ():
            sys.stderr.write(f"ddfuse: warning: {w}\n")
        if tuned is not None:
            _say_tuning(tuned, args.outdir)
        if args.gps_holdout and not m.gps_holdout_fixes:
            sys.stderr.write(f"ddfuse: warning: --gps-holdout {args.gps_holdout} withheld no GPS "
                             f"fix (the data span {m.duration_s or 0:.1f} s from the first "
                             "message): nothing is scored against withheld fixes\n")
        if args.no_report:
            sys.stdout.write(f"results in {args.outdir}/ (metrics.json, <estimator>.tum/.csv, "
                             "estimates.mcap, run.npz); no report (--no-report)\n")
            return _all_failed(m, args.outdir)
        # The report is rendered after the run, so its time is in no estimator's runtime.
        t_a = time.perf_counter()
        if tuned is not None and tuned.shipped is not None:
            _render_or_say(args.outdir / SHIPPED, bars)
        report = _render_or_say(args.outdir, bars)
        report_s = time.perf_counter() - t_a
    finally:
        if bars:
            bars.stop()
    sys.stdout.write(f"results in {args.outdir}/ (metrics.json, <estimator>.tum/.csv, "
                     f"estimates.mcap, run.npz); report {report} ({report_s:.1f} s)\n")
    return _all_failed(m, args.outdir)


SHIPPED = "shipped"  # run_tuned.SHIPPED_DIR, without loading the library for --help


def _say_tuning(tuned, outdir: Path) -> None:
    """After ``run --tune``: what tuning changed for the best estimator in one line
    (``report_tuning.change_line``) and where the two runs' results are."""
    from ddfuse.evaluation.report_tuning import change_line
    from ddfuse.evaluation.tune import holdout_worse

    line = change_line(tuned.record, tuned.run, tuned.shipped)
    if not tuned.tuning.applied:
        sys.stderr.write(f"ddfuse: warning: {line}\n")
        return
    sys.stdout.write(f"{line}\n")
    sys.stdout.write(f"the tuned config's results are these, in {outdir}/ (with tuned.yaml, "
                     f"tuning.json); the given config's in {outdir / SHIPPED}/\n")
    t = tuned.tuning
    worse = holdout_worse(t.before, t.after, tuned.record.get("gps_holdout"),
                          t.result.estimator)
    if worse:
        sys.stdout.flush()
        sys.stderr.write(f"ddfuse: warning: {worse}; the report's 'What tuning changed' "
                         "compares every estimator's runs with both configs\n")


def _notice(text: str, bars) -> None:
    """A line on stderr while the run goes on (above the progress bars on a terminal)."""
    if bars is not None and bars.bar is not None:
        bars.bar.console.print(f"ddfuse: {text}", markup=False, highlight=False)
    else:
        sys.stderr.write(f"ddfuse: {text}\n")
        sys.stderr.flush()


def _render_or_say(outdir: Path, bars) -> Path:
    """The report rendered (``report.render``); Ctrl-C or SIGTERM meanwhile ends the command
    with a line saying that the results are whole and ``ddfuse report OUTDIR`` renders it."""
    try:
        return render(outdir, bars)
    except KeyboardInterrupt as e:
        from ddfuse.estimation.interrupts import interrupt_name

        raise KeyboardInterrupt(
            f"interrupted ({interrupt_name(e)}) while the report was rendered: the results in "
            f"{outdir}/ are complete; 'ddfuse report {outdir}' renders it") from None


def _all_failed(m: RunSummary, outdir: Path) -> int:
    """0, or ``guard.NO_ESTIMATE`` with a line on stderr when every estimator ended in ERROR
    (the table's rows say why)."""
    if not m.estimators or not all(e.error for e in m.estimators.values()):
        return 0
    from ddfuse.evaluation.cli.guard import NO_ESTIMATE

    sys.stderr.write(f"ddfuse: error: every estimator ended in ERROR (the rows above say why); "
                     f"what they had is in {outdir}/\n")
    return NO_ESTIMATE
