"""``ddfuse mc SCENARIO``: Monte Carlo runs of the estimators on a simulator scenario.

The runs and their statistics are the library's (``evaluation.montecarlo``); this module checks
the output directory before any seed runs, prints the markdown table and, when the results
cannot be written at the end, keeps them (the table on stdout, the JSON in a temporary file).
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
from pathlib import Path

from ddfuse.estimation.errors import DdfuseError
from ddfuse.evaluation.cli.arguments import (
    DdfuseParser,
    estimator_list,
    int_at_least,
    lag_seconds,
    simulated_scenario,
)
from ddfuse.evaluation.cli.engine_options import add_scheduler
from ddfuse.evaluation.cli.guard import guarded
from ddfuse.evaluation.cli.output_paths import check_output_dir
from ddfuse.evaluation.montecarlo import monte_carlo, report_stem, to_markdown, write_report
from ddfuse.evaluation.simulate import SCENARIOS, SMOOTHER_LAG


def _save_or_show(mc: dict, outdir: Path) -> tuple[Path, Path]:
    """write_report; if that fails after all the runs, the table goes to stdout and the JSON to
    a temporary file, and the one-line error (DdfuseError) names both."""
    try:
        return write_report(mc, outdir)
    except OSError as e:
        reason = f"{e.filename or outdir}: {e.strerror or e}"
    sys.stdout.write(to_markdown(mc))
    sys.stdout.flush()
    try:
        fd, kept = tempfile.mkstemp(prefix=f"ddfuse-{report_stem(mc)}-", suffix=".json")
        with os.fdopen(fd, "w") as f:
            f.write(json.dumps(mc.to_json(), indent=2, default=float) + "\n")
        where = f"the table is above, the JSON in {kept}"
    except OSError:
        where = "the table is above; the JSON could not be kept"
    raise DdfuseError(f"-o {outdir}: could not write the results ({reason}); {where}")


def _main(argv: list[str] | None) -> int:
    ap = DdfuseParser(
        prog="ddfuse mc",
        description="Monte Carlo runs of the estimators on a simulator scenario: position RMSE, "
        "dead-reckoning RMSE, average NEES against its 95% chi-square band, runtime.")
    ap.add_argument("scenario", choices=list(SCENARIOS))
    ap.add_argument("--seeds", type=int_at_least(1), default=20,
                    help="number of seeds (default 20)")
    ap.add_argument("--first-seed", type=int_at_least(0), default=0,
                    help="first seed (default 0)")
    ap.add_argument("--duration", type=float, default=None, metavar="S",
                    help="seconds per run (default: the scenario's); shorter, the scenario's drive "
                    "for the seed cut to S s (ddfuse simulate --help)")
    ap.add_argument("--estimators", type=estimator_list, metavar="LIST",
                    help="comma-separated (default: every EKF the simulated "
                    "config allows); dead reckoning always runs")
    ap.add_argument("--jobs", type=int_at_least(1), default=None,
                    help="local processes, >= 1 (default: os.cpu_count())")
    add_scheduler(ap, jobs=False)
    ap.add_argument("--fixed-truth", action="store_true",
                    help="every seed with the scenario's true geometry and the exact true "
                    "initial pose (default: both drawn per seed from the priors the config "
                    "states)")
    ap.add_argument("--lag", type=lag_seconds, default=None, metavar="S",
                    help="smoother lag, s (default: the simulated config's, "
                    f"{SMOOTHER_LAG:g} s)")
    ap.add_argument("-o", "--outdir", type=Path, default=Path("ddfuse-out"),
                    help="where mc_<scenario>[_fixed-truth][_lag<S>].json and .md go "
                    "(default ddfuse-out)")
    args = ap.parse_args(argv)
    simulated_scenario(args.scenario, args.duration)
    # before any seed runs: an output directory that cannot be made fails now, not at the end
    check_output_dir(args.outdir, "-o")
    from ddfuse.evaluation.engine import Engine

    jobs = min(args.jobs or os.cpu_count() or 1, args.seeds)
    try:
        with Engine(args.scheduler, jobs, timeout=args.scheduler_timeout) as engine:
            if engine.kind != "serial":
                sys.stderr.write(f"ddfuse: mc: {args.seeds} seeds on {engine.backend}\n")
            mc = monte_carlo(args.scenario,
                             range(args.first_seed, args.first_seed + args.seeds),
                             args.estimators, duration=args.duration, engine=engine,
                             fixed_truth=args.fixed_truth, lag=args.lag)
    except ValueError as e:
        raise DdfuseError(str(e)) from None
    j, m = _save_or_show(mc, args.outdir)
    sys.stdout.write(to_markdown(mc))
    print(f"wrote {j} and {m}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``ddfuse mc SCENARIO [--seeds N] [--first-seed S] [--duration S] [--estimators LIST]
    [--jobs J] [--scheduler ADDRESS] [-o OUTDIR]``; a user error ends in one line on stderr
    and exit code 2."""
    return guarded(_main, argv)
