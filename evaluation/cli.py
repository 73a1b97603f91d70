"""The ``ddfuse`` command line: argument parsing only; the work is done by the library.

Every user error (bad config, unreadable bag, absent topic, ...) ends in one line on stderr
naming the file, topic, field or key, and exit code 2: never a traceback.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

import yaml

from estimation.errors import DdfuseError

ROOT = Path(__file__).resolve().parents[1]
SAMPLE_BAG = ROOT / "data" / "sample_husky.bag"


def _fmt(v: float, spec: str = ".2f") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def cmd_inspect(args: argparse.Namespace) -> int:
    from estimation.baginfo import bag_info, suggest_config
    from estimation.rosmsg import short_type

    info = bag_info(args.bag)
    out = sys.stdout
    out.write(f"bag: {info.path}\n")
    out.write(f"time span: {info.t0:.3f} .. {info.t1:.3f} s (header stamps), "
              f"duration {info.duration:.1f} s\n\n")
    rows = [("topic", "type", "count", "rate Hz", "median dt s", "span s", "out of order")]
    for t in info.topics:
        rows.append((t.topic, short_type(t.msgtype), str(t.count), _fmt(t.rate_hz),
                     _fmt(t.median_dt, ".4f"), _fmt(t.t1 - t.t0, ".1f"), str(t.out_of_order)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for r in rows:
        out.write("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() + "\n")
    out.write("\n")
    for t in info.topics:
        for note in t.notes:
            out.write(f"{t.topic}: {note}\n")
    out.write("\n# suggested config (review the noise values; they are starting points)\n")
    out.write(yaml.safe_dump(suggest_config(info), sort_keys=False, default_flow_style=None))
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    from evaluation import simulate

    return simulate.main(args.rest) or 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="ddfuse",
        description="Pose estimation for differential-drive robots from ROS bags: "
                    "EKF baseline vs GTSAM fixed-lag smoother.")
    p.add_argument("-v", "--verbose", action="store_true", help="log details to stderr")
    sub = p.add_subparsers(dest="command", required=True)

    sp = sub.add_parser("inspect", help="topics, rates, covariance sanity and a suggested config")
    sp.add_argument("bag", type=Path, help="ROS1 .bag, ROS2 bag directory or .mcap")
    sp.set_defaults(func=cmd_inspect)

    sp = sub.add_parser("simulate", help="simulate a robot drive into a bag with ground truth",
                        add_help=False)
    sp.add_argument("rest", nargs=argparse.REMAINDER)
    sp.set_defaults(func=cmd_simulate)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.ERROR,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except DdfuseError as e:
        print(f"ddfuse: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("ddfuse: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
