"""``ddfuse lag-sweep [BAG]``: the smoother's accuracy, latency and CPU against its lag."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from ddfuse.estimation.config import GPS_MODELS
from ddfuse.estimation.errors import BagError, DdfuseError
from ddfuse.evaluation import lag_sweep as lag_sweep_module
from ddfuse.evaluation.atomic_files import write_text
from ddfuse.evaluation.cli.arguments import (
    CONFIG_HELP,
    GPS_HOLDOUT_HELP,
    DdfuseParser,
    gps_holdout,
    int_at_least,
    plain_text,
)
from ddfuse.evaluation.cli.engine_options import add_scheduler
from ddfuse.evaluation.cli.guard import guarded
from ddfuse.evaluation.cli.output_paths import check_output_file
from ddfuse.evaluation.lag_sweep import DEFAULT_LAGS, format_table, lag_sweep
from ddfuse.evaluation.shipped import SAMPLE_BAG, config_for


def _main(argv: list[str] | None) -> int:
    p = DdfuseParser(prog="ddfuse lag-sweep",
                     description=plain_text(lag_sweep_module.__doc__.split("\n\n")[1]))
    p.add_argument("bag", type=Path, nargs="?", help="bag (default: the embedded sample)")
    p.add_argument("-c", "--config", type=Path, help=CONFIG_HELP)
    p.add_argument("--lags", default=",".join(f"{x:g}" for x in DEFAULT_LAGS), metavar="S,S,...",
                   help="comma-separated lags in seconds (default: 0.5,2,10,30)")
    p.add_argument("--gps-holdout", type=gps_holdout, metavar="every:K|window:T0:T1",
                   help=GPS_HOLDOUT_HELP)
    p.add_argument("--gps-model", choices=GPS_MODELS, metavar="MODEL",
                   help="the GPS error model instead of the config's gps.model: "
                   f"{', '.join(GPS_MODELS)}")
    p.add_argument("--json", type=Path, metavar="FILE", help="also write the rows as JSON")
    add_scheduler(p, jobs=False)
    p.add_argument("--jobs", type=int_at_least(1), default=1, metavar="N",
                   help="local worker processes, each point (lag) of the sweep its own task "
                   "that decodes the bag (default 1: decoded once, the points in turn here)")
    args = p.parse_args(argv)
    try:
        lags = [float(x) for x in args.lags.split(",") if x.strip()]
    except ValueError:
        p.error(f"--lags: expected comma-separated seconds, got {args.lags!r}")
    if not lags or not all(x > 0 and math.isfinite(x) for x in lags):
        p.error(f"--lags: every lag must be > 0 s, got {args.lags!r}")
    if args.json:  # before the sweep, not after it
        check_output_file(args.json, "--json")
    bag = args.bag or SAMPLE_BAG
    damaged = None
    from ddfuse.evaluation.engine import Engine

    try:
        with Engine(args.scheduler, args.jobs, timeout=args.scheduler_timeout) as engine:
            if engine.kind != "serial":
                sys.stderr.write(f"ddfuse: lag-sweep: {len(lags) + 1} runs on "
                                 f"{engine.backend}\n")
            rows = lag_sweep(bag, config_for(bag, args.config), lags, args.gps_holdout,
                             engine=engine, gps_model=args.gps_model)
    except ValueError as e:
        raise DdfuseError(str(e)) from None
    except BagError as e:
        if not hasattr(e, "rows"):
            raise
        damaged, rows = e, e.rows
    sys.stdout.write(format_table(rows) + "\n")
    if args.json:
        sys.stdout.flush()  # the table stays, whatever happens to the JSON
        try:
            write_text(args.json, json.dumps(rows, indent=2) + "\n")
        except OSError as e:
            raise DdfuseError(f"--json {args.json}: could not write it ({e.strerror or e}); "
                              "the table above has the rows") from None
    if damaged is not None:
        raise damaged
    return 0


def main(argv: list[str] | None = None) -> int:
    """``ddfuse lag-sweep [BAG] [-c CONFIG] [--lags 0.5,2,10,30] [--gps-holdout SPEC]
    [--json FILE] [--scheduler ADDRESS] [--jobs N]``; a user error ends in one line on stderr
    and exit code 2."""
    return guarded(_main, argv)
