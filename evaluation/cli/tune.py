"""``ddfuse tune BAG``: the config's noise values estimated from the bag (evaluation/tune.py),
a before / after table, and the tuned config written."""

from __future__ import annotations

import argparse
import contextlib
import datetime
import sys
from pathlib import Path

from ddfuse.estimation.errors import DdfuseError
from ddfuse.evaluation.cli.arguments import CONFIG_HELP, GPS_HOLDOUT_HELP, gps_holdout
from ddfuse.evaluation.cli.engine_options import add_scheduler
from ddfuse.evaluation.cli.output_paths import check_output_file
from ddfuse.evaluation.cli.terminal import fmt, progress


def add_to(sub) -> None:
    sp = sub.add_parser("tune", help="estimate the config's noise values from the bag "
                        "(maximum likelihood of the EKF's innovations) and write a tuned config")
    sp.add_argument("bag", type=Path, help="bag")
    sp.add_argument("-c", "--config", type=Path, help=CONFIG_HELP)
    sp.add_argument("-o", "--output", type=Path, metavar="TUNED.yaml",
                    help="write the tuned config here (default: print the table only)")
    sp.add_argument("--gps-holdout", type=gps_holdout, metavar="every:K|window:T0:T1",
                    help=GPS_HOLDOUT_HELP + "; the withheld fixes are kept out of the fit")
    sp.add_argument("--jobs", type=int, default=None, metavar="J",
                    help="processes for the estimator runs (default: the machine's cores, "
                    "at most 2)")
    sp.add_argument("--twist-rates", action="store_true",
                    help="fit the sensors' noise with an EKF whose twist has rates "
                    "(acceleration states) first, then the process noise with it held: the "
                    "sensors' own noise where the robot's speed ramps and its turns fool a "
                    "walk of the twist (docs/design/tuning.md, 'The twist's rates')")
    add_scheduler(sp, jobs=False)
    sp.set_defaults(func=command)


def command(args: argparse.Namespace) -> int:
    from ddfuse.estimation.bags import read_stream
    from ddfuse.estimation.config import load_config
    from ddfuse.evaluation.shipped import config_for
    from ddfuse.evaluation.tune import check, holdout_worse, tune, tuning_estimator
    from ddfuse.evaluation.tune_yaml import write_tuned

    if args.output:
        check_output_file(args.output, "-o")
    if args.jobs is not None and args.jobs < 1:
        raise DdfuseError(f"--jobs: expected a number of processes >= 1, got {args.jobs}")
    config = config_for(args.bag, args.config)
    cfg = load_config(config)
    if args.gps_holdout and not cfg.of_kind("gps"):
        raise DdfuseError(f"--gps-holdout {args.gps_holdout}: {config} has no gps sensor")
    if args.twist_rates and tuning_estimator(cfg) != "ekf":
        raise DdfuseError(f"--twist-rates: {config} has landmarks, so ekf_landmark tunes it, "
                          "and its twist is the odometry's, with no rates to add")
    bars = progress()
    try:
        with _engine(args) as engine:  # an unreachable scheduler said before the bag is read
            stream = read_stream(args.bag, cfg, progress=(lambda f: bars.update("read", f))
                                 if bars else None)
            result = tune(cfg, stream, holdout=args.gps_holdout, jobs=args.jobs,
                          engine=engine, progress=bars.update if bars else None,
                          twist_rates=args.twist_rates)
        if bars:
            bars.update("before / after", 0.0)
        before = check(cfg, stream, [None] * len(result.tuned), estimator=result.estimator,
                       holdout=args.gps_holdout)
        after = check(cfg, stream, result.values(), estimator=result.estimator,
                      holdout=args.gps_holdout)
    finally:
        if bars:
            bars.stop()
    sys.stdout.write(format_report(result, before, after, args.gps_holdout) + "\n")
    if args.output:
        sys.stdout.flush()
        date = datetime.date.today().isoformat()
        write_tuned(config, args.output, result, Path(args.bag).name, date, before, after,
                    args.gps_holdout)
        sys.stdout.write(f"tuned config written to {args.output}\n")
    worse = holdout_worse(before, after, args.gps_holdout, result.estimator)
    if worse:
        sys.stdout.flush()
        sys.stderr.write(f"ddfuse: warning: {worse}; `ddfuse run --tune` runs every "
                         "estimator with both configs, side by side\n")
    return 0


@contextlib.contextmanager
def _engine(args: argparse.Namespace):
    """The --scheduler's engine, entered, with its one line on stderr; None without one (tune
    then forks its own --jobs processes)."""
    if not args.scheduler:
        yield None
        return
    from ddfuse.evaluation.engine import Engine

    with Engine(args.scheduler, timeout=args.scheduler_timeout) as engine:
        sys.stderr.write(f"ddfuse: tune: the runs on {engine.backend}\n")
        yield engine


def format_report(result, before, after, holdout: str | None) -> str:
    """The tuning's table: each value before and after with its standard error and status,
    then NIS mean / expected per sensor with its verdict before and after, the hold-out
    score, the pairs the data do not tell apart, and what the search took."""
    lines = [f"tuned on the {result.estimator} EKF's innovations ({result.innovations}): "
             f"{result.runs} runs, {result.iterations} iterations, {result.wall_s:.1f} s"
             + (f" ({result.message})" if result.message else ""),
             "",
             f"{'value':56} {'before':>10} {'after':>10} {'+-%':>6}  status",
             ]
    for t in result.tuned:
        p = t.param
        was = fmt(p.before, ".3g") if p.before is not None else f"({p.source})"
        now = fmt(t.value, ".3g") if t.value is not None else "-"
        se = fmt(100.0 * t.se_log, ".0f") if t.se_log is not None and t.value is not None \
            else ""
        lines.append(f"{p.key + ' [' + p.unit + ']':56} {was:>10} {now:>10} {se:>6}  "
                     f"{t.status}")
    notes = [f"  {t.param.key}: {t.reason}" for t in result.tuned if t.reason]
    if notes:
        lines += ["", "why:"] + notes
    if result.pairs:
        lines += ["", "pairs the data do not tell apart (correlation of the estimates):"]
        lines += [f"  {a} / {b}: {r:+.2f}" for a, b, r in result.pairs]
    lines += ["", f"{'NIS mean / expected':56} {'before':>16} {'after':>16}"]
    for label in sorted(set(before.nis) | set(after.nis)):
        cells = []
        for c in (before, after):
            s = c.nis.get(label)
            cells.append("-" if s is None else
                         f"{fmt(s.nis.ratio, '.3f')} {s.nis.verdict or '-'}")
        lines.append(f"{label:56} {cells[0]:>16} {cells[1]:>16}")
    if holdout:
        b, a = fmt(before.holdout_rmse_m, ".3f"), fmt(after.holdout_rmse_m, ".3f")
        lines.append(f"{'GPS hold-out RMSE (' + holdout + '), m':56} {b:>16} {a:>16}")
        if before.holdout_nees is not None or after.holdout_nees is not None:
            b, a = (c.holdout_nees.brief() if c.holdout_nees else "-" for c in (before, after))
            lines.append(f"{'GPS hold-out NEES (expected 2)':56} {b:>16} {a:>16}")
    red = [w for w in after.whiteness if not w.white]
    if red:
        lines += ["", "innovations at the tuned values that are not white (the likelihood assumes "
                  "they are; evaluation.tune_whiteness):"]
        lines += [f"  {w.describe()}" for w in red]
    return "\n".join(lines)
