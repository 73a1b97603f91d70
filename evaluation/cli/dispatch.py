"""The ``ddfuse`` program: the top-level parser, ``main(argv)`` and the console script ``entry``.

``inspect``, ``run``, ``report``, ``online``, ``node``, ``bench``, ``tune``, ``fleet`` and
``compare`` are sub-parsers of the top-level parser (each command module's ``add_to``);
``simulate``, ``plot-sim``, ``lag-sweep`` and ``mc`` parse their own arguments (their module's
``main(argv)``), dispatched before the top-level parser because argparse.REMAINDER cannot pass
a leading option such as --help through.
The layout and its reasons: docs/design/command_line.md.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys

from ddfuse.estimation.interrupts import terminate_as_interrupt
from ddfuse.evaluation.cli import (
    bench,
    compare,
    fleet,
    inspect,
    node,
    online,
    report,
    run,
    tune,
)
from ddfuse.evaluation.cli.arguments import DdfuseParser
from ddfuse.evaluation.cli.guard import guarded

# sub-command -> (its module, its line in the top-level help)
DELEGATED = {
    "simulate": ("ddfuse.evaluation.cli.simulate", "simulate a robot drive into a bag with "
                 "ground truth (ddfuse simulate --help)"),
    "plot-sim": ("ddfuse.evaluation.cli.plot_sim", "plot a simulated scenario: truth, GPS, dead "
                 "reckoning (ddfuse plot-sim --help)"),
    "lag-sweep": ("ddfuse.evaluation.cli.lag_sweep", "the smoother's accuracy, latency and CPU "
                  "against its lag (ddfuse lag-sweep --help)"),
    "mc": ("ddfuse.evaluation.cli.mc", "Monte Carlo runs on a simulated scenario: RMSE, dead "
           "reckoning, average NEES and its chi-square band (ddfuse mc --help)"),
}


class _Version(argparse.Action):
    """argparse's "version" action with the version read when asked for (``ddfuse.__version__``
    is read on first use: every other command is spared importlib.metadata)."""

    def __call__(self, parser, namespace, values, option_string=None):
        import ddfuse

        sys.stdout.write(f"{parser.prog} {ddfuse.__version__}\n")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    p = DdfuseParser(
        prog="ddfuse",
        description="Pose estimation for differential-drive robots from ROS bags: "
                    "EKF baseline vs GTSAM fixed-lag smoother.")
    p.add_argument("-v", "--verbose", action="store_true", help="log details to stderr")
    p.add_argument("--version", action=_Version, nargs=0, default=argparse.SUPPRESS,
                   help="show program's version number and exit")
    sub = p.add_subparsers(dest="command", required=True)
    for command in (inspect, run, report, online, node, bench, tune, fleet, compare):
        command.add_to(sub)
    for name, (_, text) in DELEGATED.items():
        sub.add_parser(name, help=text)
    return p


def main(argv: list[str] | None = None) -> int:
    """``ddfuse`` with ``argv`` (default: the process's): the exit code (``guard``: 0, 2 for a
    user error in one line on stderr, 3 for a run without any estimate, 130 for Ctrl-C, 143 for
    SIGTERM)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in DELEGATED:
        import importlib

        return guarded(importlib.import_module(DELEGATED[argv[0]][0]).main, argv[1:])
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.ERROR,
                        format="%(levelname)s %(name)s: %(message)s")
    return guarded(args.func, args)


def entry() -> None:
    """The ``ddfuse`` program: :func:`main`, then exit without tearing the interpreter down
    (a program about to end need not free its memory; docs/design/command_line.md).

    Output streams and logging are flushed first. ``main`` itself returns normally (tests call
    it); an exception that escapes it ends the process the ordinary way, with its traceback. A
    reader that stops early (``ddfuse inspect BAG | head``) ends it quietly, as it does
    ``cat``."""
    terminate_as_interrupt()  # SIGTERM (timeout, docker stop) stops a run as Ctrl-C does
    try:
        rc = main()
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
    except BrokenPipeError:
        # the reader of stdout has gone: what is still buffered can never be written (the
        # Python docs' recipe, "Note on SIGPIPE"); 141 = 128 + SIGPIPE, as a shell reports it
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        os._exit(141)
    os._exit(rc if isinstance(rc, int) else 0)
