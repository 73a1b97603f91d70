"""``ddfuse inspect BAG [-o FILE.yaml]``: topics, rates, covariance sanity and a suggested config.

Stdout is one YAML document: every fact line is a comment ("# "), the suggested config follows,
so ``ddfuse inspect BAG > cfg.yaml`` is a config that loads, with the facts its noise values are
to be reviewed against kept above it. With ``-o`` the config alone (its comments included) is
written to the file, whole or not at all, and stdout keeps the facts.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ddfuse.estimation.errors import DdfuseError
from ddfuse.estimation.gps_watch import ROBUST_MODEL
from ddfuse.evaluation.cli.terminal import fmt


def add_to(sub) -> None:
    sp = sub.add_parser("inspect", help="topics, rates, covariance sanity and a suggested config")
    sp.add_argument("bag", type=Path, help="ROS1 .bag, ROS2 bag directory or .mcap")
    sp.add_argument("-o", "--output", type=Path, metavar="FILE.yaml",
                    help="write the suggested config to FILE.yaml (stdout keeps the facts)")
    sp.set_defaults(func=command)


def command(args: argparse.Namespace) -> int:
    from ddfuse.estimation.baginfo import bag_info, offset_surveys, suggest_config
    from ddfuse.estimation.rosmsg import short_type
    from ddfuse.evaluation.atomic_files import replacing

    info = bag_info(args.bag)
    # measured on the sensors suggest_config picks; a bag that breaks off is not read twice
    surveys = [] if info.error else offset_surveys(args.bag, suggest_config(info))
    lines = [f"bag: {info.path}",
             f"time span: {info.t0:.3f} .. {info.t1:.3f} s (header stamps), "
             f"duration {info.duration:.1f} s", ""]
    rows = [("topic", "type", "count", "rate Hz", "median dt s", "span s", "out of order")]
    for t in info.topics:
        rows.append((t.topic, short_type(t.msgtype), str(t.count), fmt(t.rate_hz),
                     fmt(t.median_dt, ".4f"), fmt(t.t1 - t.t0, ".1f"), str(t.out_of_order)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for r in rows:
        lines.append("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip())
    lines.append("")
    for t in info.topics:
        lines += [f"{t.topic}: {note}" for note in t.notes]
    for sv in surveys:
        lines.append(f"{sv.sensor}: {sv.describe()}"
                     + (": it wanders (heading_offset_walk below)" if sv.wanders else ""))
    tree = suggest_config(info, surveys)
    fits = [] if info.error else compass_correlations(args.bag, tree)
    lines += [f.describe() for f in fits]
    bursts = [] if info.error else gps_bursts(args.bag, tree)
    lines += [_burst_fact(b) for b in bursts]
    lines.append("")
    text = config_text(tree, info, {f.sensor: f for f in fits if f.tau is not None}, bursts)
    out = sys.stdout
    out.write("".join(f"# {line}\n" if line else "#\n" for line in lines))
    if args.output is not None:
        with replacing(args.output) as f:
            f.write(f"# suggested by ddfuse inspect {info.path} (review the noise values; they "
                    "are starting points)\n" + text)
        out.write(f"# suggested config written to {args.output}\n")
    else:
        out.write("# suggested config (review the noise values; they are starting points)\n"
                  + text)
    if info.error:  # a truncated ROS1 bag: the facts are of what could be read
        out.flush()
        raise DdfuseError(info.error)
    return 0


def compass_correlations(path, tree: dict) -> list:
    """Each IMU yaw's correlation in the suggested config ``tree`` measured against its gyro
    (``evaluation.compass_correlation``); where identified, its ``correlation_time`` is put into
    ``tree``. [] without an IMU that gives both yaw and yaw rate."""
    from ddfuse.estimation.bags import read_stream
    from ddfuse.estimation.config import parse_config
    from ddfuse.estimation.errors import DdfuseError
    from ddfuse.evaluation.compass_correlation import measure

    imus = [s for s in (tree.get("sensors") or {}).get("imu") or ()
            if "yaw" in s.get("use", ()) and "yaw_rate" in s.get("use", ())]
    if not imus:
        return []
    try:
        cfg = parse_config({"sensors": {"imu": imus}}, f"{path} (suggested config)")
        stream = read_stream(path, cfg)
    except DdfuseError:  # what the bag lacks is inspect's facts to report, not this
        return []
    fits = [f for f in (measure(cfg, stream, s.name) for s in cfg.sensors) if f is not None]
    for f in fits:
        if f.tau is not None:
            for s in imus:
                if s["topic"] == f.sensor:
                    s["correlation_time"] = round(f.tau, 1)
    return fits


def _burst_fact(b) -> str:
    """A ``scores.GpsBursts`` as inspect's fact line."""
    return (f"{b.topic}: disagreed with the odometry's dead reckoning {b.episodes} times "
            f"({b.fixes} fixes, up to {b.largest_m:.0f} m, the longest {b.longest_s:.1f} s): "
            "errors in bursts, as multipath and non-line-of-sight fixes give "
            f"(gps: {{model: {ROBUST_MODEL}}} in the suggested config)")


def _burst_source(b) -> str:
    """A ``scores.GpsBursts`` as the comment above the suggested ``gps.model``."""
    return (f"gps.model {ROBUST_MODEL}: {b.topic} disagreed with the odometry's dead reckoning "
            f"in {b.episodes} bursts (up to {b.largest_m:.0f} m), which a gating model can "
            "follow; a robust one weighs them (docs/design/urban_gps.md; `ddfuse run` warns by "
            "the same rule)")


def gps_bursts(path, tree: dict) -> list:
    """The GPS topics of the suggested config ``tree`` whose fixes disagree with its odometry
    in bursts, read as ``ddfuse run`` reads them (``estimation.gps_watch``); where there are
    any, ``tree`` gets the robust GPS model. ``scores.GpsBursts`` per topic; [] without a GPS
    and a speed source."""
    from ddfuse.estimation.bags import BagStream
    from ddfuse.estimation.config import parse_config
    from ddfuse.evaluation.scores import GpsBursts

    sensors = tree.get("sensors") or {}
    if not sensors.get("gps") or not (sensors.get("odometry") or sensors.get("wheels")):
        return []
    try:
        raw = {k: tree[k] for k in ("sensors", "frame", "robot") if k in tree}
        bs = BagStream(path, parse_config(raw, f"{path} (suggested config)"))
        for _ in bs:
            pass
    except DdfuseError:  # what the bag lacks is inspect's facts to report, not this
        return []
    out = GpsBursts.of_watch(bs.watch)
    if out:
        tree["gps"] = {"model": ROBUST_MODEL}
    return out


def config_text(tree: dict, info, compasses: dict | None = None,
                bursts: list | None = None) -> str:
    """Config ``tree`` as YAML, each GPS sensor's suggested ``correlation_time`` with a comment
    above it saying where the value comes from (its topic's ``scatter`` in BagInfo ``info``), and
    so each IMU's whose yaw correlation was measured (``compasses``: topic -> its
    ``compass_correlation.CompassCorrelation``), and the GPS model where ``bursts`` set it."""
    import yaml

    sources = {t.topic: t.scatter.source() for t in info.topics
               if t.scatter is not None and t.scatter.recommended}
    for topic, f in (compasses or {}).items():
        sources[topic] = (f"from the yaw's error against the gyro's integral: Gauss-Markov, "
                          f"sigma {f.sigma:.4f} rad, {f.tau:.1f} s "
                          "(evaluation.compass_correlation)")
    out, topic = [], None
    for line in yaml.safe_dump(tree, sort_keys=False, default_flow_style=None).splitlines():
        key = line.lstrip(" -")
        if key.startswith("topic: "):
            topic = key[len("topic: "):]
        elif key.startswith("correlation_time: ") and topic in sources:
            out.append(" " * (len(line) - len(key)) + f"# correlation_time {sources[topic]}")
        elif line.startswith("gps:") and bursts:
            out += [f"# {_burst_source(b)}" for b in bursts]
        out.append(line)
    return "\n".join(out) + "\n"
