"""``ddfuse fleet BAG_OR_DIR...``: every bag run as ``ddfuse run`` would (its report rendered by
the worker, unless --no-report), on local processes or a Dask cluster (``evaluation.engine``),
and one summary (``evaluation.fleet``: fleet.json, fleet.html)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ddfuse.evaluation.cli.arguments import (
    CONFIG_HELP,
    GPS_HOLDOUT_HELP,
    estimator_list,
    gps_holdout,
)
from ddfuse.evaluation.cli.engine_options import add_scheduler
from ddfuse.evaluation.cli.output_paths import check_output_dir
from ddfuse.evaluation.cli.terminal import fmt


def add_to(sub) -> None:
    sp = sub.add_parser("fleet", help="run every bag of one or more directories and summarise "
                        "them: ranking per bag, wins across bags (fleet.json)")
    sp.add_argument("paths", type=Path, nargs="+", metavar="BAG_OR_DIR",
                    help="bags (ROS1 .bag, ROS 2 directory, .mcap) or directories searched "
                    "for them")
    sp.add_argument("-c", "--config", type=Path,
                    help="one config for every bag (default: each bag's own; " +
                    CONFIG_HELP.removeprefix("config YAML (default: "))
    sp.add_argument("-o", "--outdir", type=Path, default=Path("ddfuse-fleet"),
                    help="output directory: OUTDIR/<bag>/ per bag (as ddfuse run's -o), "
                    "OUTDIR/fleet.json and OUTDIR/fleet.html (default: ddfuse-fleet)")
    sp.add_argument("--estimators", type=estimator_list, metavar="LIST",
                    help="comma-separated estimator names, as ddfuse run's")
    sp.add_argument("--gps-holdout", type=gps_holdout, metavar="every:K|window:T0:T1",
                    help=GPS_HOLDOUT_HELP)
    sp.add_argument("--no-report", action="store_true",
                    help="write each bag's results (metrics.json, tracks, run.npz) but not its "
                    "HTML report ('ddfuse report OUTDIR/<bag>' renders it later)")
    add_scheduler(sp)
    sp.set_defaults(func=command)


def _say_progress(done: int, total: int, left: float | None, bag: str, error: str | None):
    what = f"ERROR: {error}" if error else "ok"
    sys.stderr.write(f"ddfuse: fleet: {done}/{total} bags done ({bag}: {what}), about "
                     f"{fmt(left, '.0f')} s left\n")
    sys.stderr.flush()


def print_standings(doc: dict, out) -> None:
    """Per bag its winner (or tie) and failures; per estimator its wins across bags."""
    for b in doc["bags"]:
        if b["error"]:
            out.write(f"{b['bag']:24} ERROR: {b['error']}\n")
        elif b["winner"]:
            out.write(f"{b['bag']:24} {b['score']} best {b['winner']} by "
                      f"{fmt(b['margin_m'], '.3f')} m ({fmt(b['margin_pct'], '.1f')}%); "
                      f"ranking {', '.join(b['ranking'])}\n")
        else:
            what = f"tie: {', '.join(b['tied'])}" if b["tied"] else "no score"
            out.write(f"{b['bag']:24} {what}\n")
    out.write(f"{'estimator':16} {'scored':>6} {'wins':>5} {'tied 1st':>8} "
              f"{'mean margin m':>13} {'mean margin %':>13}\n")
    for name, s in doc["estimators"].items():
        out.write(f"{name:16} {s['scored']:>6} {s['wins']:>5} {s['tied_first']:>8} "
                  f"{fmt(s['mean_margin_m'], '.3f'):>13} {fmt(s['mean_margin_pct'], '.1f'):>13}\n")


def command(args: argparse.Namespace) -> int:
    from ddfuse.evaluation.engine import Engine
    from ddfuse.evaluation.fleet import FLEET_JSON, plan, run_fleet
    from ddfuse.evaluation.fleet_page import FLEET_HTML

    check_output_dir(args.outdir, "-o")
    jobs = plan(args.paths, args.outdir, args.config, args.estimators, args.gps_holdout,
                report=not args.no_report)
    import os

    workers = min(args.jobs or os.cpu_count() or 1, len(jobs))  # no idle worker to start
    engine = Engine(args.scheduler, workers, timeout=args.scheduler_timeout)
    with engine:
        sys.stderr.write(f"ddfuse: fleet: {len(jobs)} bags on {engine.backend}\n")
        doc = run_fleet(jobs, args.outdir, engine, progress=_say_progress)
    print_standings(doc, sys.stdout)
    sys.stdout.write(f"{doc['bags_ran']} of {doc['bags_total']} bags ran in {doc['wall_s']:.1f} "
                     f"s; per bag results in {args.outdir}/<bag>/, the summary in "
                     f"{args.outdir / FLEET_JSON} and {args.outdir / FLEET_HTML}\n")
    return 0 if doc["bags_ran"] else 2
