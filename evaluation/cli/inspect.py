"""``ddfuse inspect BAG``: topics, rates, covariance sanity and a suggested config."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ddfuse.estimation.errors import DdfuseError
from ddfuse.evaluation.cli.terminal import fmt


def add_to(sub) -> None:
    sp = sub.add_parser("inspect", help="topics, rates, covariance sanity and a suggested config")
    sp.add_argument("bag", type=Path, help="ROS1 .bag, ROS2 bag directory or .mcap")
    sp.set_defaults(func=command)


def command(args: argparse.Namespace) -> int:
    import yaml
    from ddfuse.estimation.baginfo import bag_info, offset_surveys, suggest_config
    from ddfuse.estimation.rosmsg import short_type

    info = bag_info(args.bag)
    # measured on the sensors suggest_config picks; a bag that breaks off is not read twice
    surveys = [] if info.error else offset_surveys(args.bag, suggest_config(info))
    out = sys.stdout
    out.write(f"bag: {info.path}\n")
    out.write(f"time span: {info.t0:.3f} .. {info.t1:.3f} s (header stamps), "
              f"duration {info.duration:.1f} s\n\n")
    rows = [("topic", "type", "count", "rate Hz", "median dt s", "span s", "out of order")]
    for t in info.topics:
        rows.append((t.topic, short_type(t.msgtype), str(t.count), fmt(t.rate_hz),
                     fmt(t.median_dt, ".4f"), fmt(t.t1 - t.t0, ".1f"), str(t.out_of_order)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for r in rows:
        out.write("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() + "\n")
    out.write("\n")
    for t in info.topics:
        for note in t.notes:
            out.write(f"{t.topic}: {note}\n")
    for sv in surveys:
        out.write(f"{sv.sensor}: {sv.describe()}"
                  + (": it wanders (heading_offset_walk below)\n" if sv.wanders else "\n"))
    out.write("\n# suggested config (review the noise values; they are starting points)\n")
    out.write(yaml.safe_dump(suggest_config(info, surveys), sort_keys=False,
                             default_flow_style=None))
    if info.error:  # a truncated ROS1 bag: the facts are of what could be read
        out.flush()
        raise DdfuseError(info.error)
    return 0
