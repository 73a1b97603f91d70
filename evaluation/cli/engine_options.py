"""The options of every command that fans out over ``evaluation.engine``: where the tasks run."""

from __future__ import annotations

import argparse

SCHEDULER_HELP = ("a running Dask scheduler, e.g. tcp://10.0.0.5:8786 (needs the scale extra: "
                  "pip install 'ddfuse[scale]'; the workers need the same ddfuse version, and for "
                  "fleet and lag-sweep the bags at the same paths); default: local processes")


def add_scheduler(sp: argparse.ArgumentParser, jobs: bool = True) -> None:
    """--scheduler and --scheduler-timeout, and (``jobs``) --jobs."""
    from ddfuse.evaluation.cli.arguments import int_at_least

    sp.add_argument("--scheduler", metavar="ADDRESS", help=SCHEDULER_HELP)
    sp.add_argument("--scheduler-timeout", type=float, default=10.0, metavar="S",
                    help="seconds to wait for the scheduler to answer (default 10)")
    if jobs:
        sp.add_argument("--jobs", type=int_at_least(1), metavar="N",
                        help="local worker processes without --scheduler (default: the "
                        "machine's cores; 1: in this process)")
