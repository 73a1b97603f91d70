"""``ddfuse simulate SCENARIO -o PATH``: simulate a robot drive into a bag with ground truth."""

from __future__ import annotations

import argparse
import os
import textwrap
from pathlib import Path

from ddfuse.estimation.errors import DdfuseError
from ddfuse.evaluation.cli.arguments import DdfuseParser, int_at_least, simulated_scenario
from ddfuse.evaluation.cli.guard import guarded
from ddfuse.evaluation.cli.output_paths import check_output_file
from ddfuse.evaluation.simulate import (
    FORMATS,
    SCENARIOS,
    check_bag_path,
    simulate,
    storage_file,
    write_bag,
)


def _main(argv: list[str] | None) -> int:
    ap = DdfuseParser(
        prog="ddfuse simulate",
        description=textwrap.fill(
            "Simulate a differential-drive robot and write a bag with ground truth, plus the "
            "ddfuse config (and landmark map) next to it.", 78),
        # one scenario per paragraph, never broken inside a name (husky-multipath)
        epilog="Scenarios:\n" + "\n".join(
            textwrap.fill(f"{k}: {v.description}", 78, subsequent_indent="  ",
                          break_on_hyphens=False) for k, v in SCENARIOS.items()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("scenario", choices=list(SCENARIOS))
    ap.add_argument("--seed", type=int_at_least(0), default=0, help="random seed (default 0)")
    ap.add_argument("--duration", type=float, default=None, metavar="S",
                    help="seconds to simulate (default: the scenario's). The run is the "
                    "scenario's drive for this seed cut to S s: the truth (and seed002's "
                    "landmark map) is that of the default-duration run up to S - 3 s, where the "
                    "robot starts slowing to rest. Longer than the default, the path is the "
                    "default run's up to its duration - 3 s and then goes on (seed002 then draws "
                    "its landmark map around the longer path). Sensor noise is drawn for the S s "
                    "run, so it is not the default run's")
    ap.add_argument("--format", choices=FORMATS, default="ros1",
                    help="ros1 (a .bag file), ros2 (a directory: NAME.db3 and metadata.yaml) "
                    "or mcap (a directory: NAME.mcap and metadata.yaml)")
    ap.add_argument("-o", "--output", required=True,
                    help="bag path to create: for ros2 and mcap the directory, whose file is "
                    "named after it (-o h.mcap: h.mcap/h.mcap; -o run: run/run.mcap); the "
                    "config goes beside it, the path with .yaml (h.yaml, run.yaml)")
    args = ap.parse_args(argv)
    simulated_scenario(args.scenario, args.duration)
    # Before simulating (the long scenario takes a while): the bag must not exist, and its
    # directory must be one (it is created, as a ROS 2 writer creates its own).
    out = Path(args.output)
    try:
        check_bag_path(out, args.format)
    except (FileExistsError, ValueError) as e:
        raise DdfuseError(f"-o {e}") from None
    check_output_file(out, "-o", create_parents=True)
    res = simulate(args.scenario, seed=args.seed, duration=args.duration)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        bag, cfg, lmap = write_bag(res, out, args.format)
    except FileExistsError as e:  # made meanwhile by someone else
        raise DdfuseError(f"-o {e}") from None
    what = f"{res.duration:g} s, scenario {args.scenario}, seed {args.seed}"
    if args.format == "ros1":
        print(f"wrote {bag} (ros1, {what})")
    else:  # say that it is a directory, and what is in it
        print(f"wrote {bag}{os.sep} (ROS 2 bag directory, {args.format}, {what}): "
              f"{storage_file(bag, args.format)} and {bag / 'metadata.yaml'}")
    print(f"wrote {cfg}")
    if lmap:
        print(f"wrote {lmap}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``ddfuse simulate SCENARIO [--seed N] [--duration S] [--format F] -o PATH``; a user error
    ends in one line on stderr and exit code 2."""
    return guarded(_main, argv)
