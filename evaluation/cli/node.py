"""``ddfuse node``: the estimators as a ROS 1 node (``evaluation.node`` on
``evaluation.ros1_transport``), until Ctrl-C; with ``-o DIR`` then ``run``'s results of what it
fused."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from ddfuse.estimation.errors import DdfuseError
from ddfuse.evaluation.cli.arguments import (
    add_foxglove,
    add_reorder_window,
    online_estimator_list,
)
from ddfuse.evaluation.cli.output_paths import check_output_dir


def add_to(sub) -> None:
    sp = sub.add_parser(
        "node", help="run the estimators as a ROS 1 node on the config's topics",
        description="Run the estimators as a ROS 1 node: subscribe to the config's sensor "
        "topics, feed every message through the online path (as 'online'), publish each "
        "estimator's nav_msgs/Odometry on /ddfuse/<estimator>/odom and sensor_msgs/NavSatFix "
        "on /ddfuse/<estimator>/fix (when there is a datum), the smoother's keyframes as they "
        "leave its window on /ddfuse/smoother_lagged/odom, one estimator's TF local->base "
        "(node.tf) and diagnostic_msgs/DiagnosticArray on /diagnostics. Needs a ROS master "
        "(roscore) and ROS 1's rospy (apt-get install python3-rospy ...). Ctrl-C or SIGTERM "
        "ends it (exit 0). Exit 2: bad config, no ROS master, a configured topic of a type its "
        "sensor cannot read.")
    sp.add_argument("-c", "--config", type=Path, required=True,
                    help="config YAML (the same as for 'run'; its node: section sets the "
                    "publishing)")
    sp.add_argument("--estimators", type=online_estimator_list, metavar="LIST",
                    help="comma-separated (default: all the sensors allow, but batch; the "
                    "smoother's lagged keyframes are published with the smoother)")
    sp.add_argument("-o", "--outdir", type=Path,
                    help="on Ctrl-C, write the results 'run' writes (metrics.json, tracks, "
                    "run.npz) for what the node fused, into this directory")
    add_reorder_window(sp)
    add_foxglove(sp)
    sp.add_argument("--name", default="ddfuse", help="ROS node name (default: ddfuse)")
    sp.set_defaults(func=command)


def command(args: argparse.Namespace) -> int:
    from ddfuse.estimation.config import load_config
    from ddfuse.evaluation.cli.online import _print_latency, live_view
    from ddfuse.evaluation.node import NodeCore
    from ddfuse.evaluation.ros1_transport import Ros1Node, check_master

    if args.outdir is not None:
        check_output_dir(args.outdir, "-o")  # before any work
    cfg = load_config(args.config)
    check_master(args.name)  # before the estimators are built (their kernels load)
    view, feed = ((None, None) if args.foxglove is None
                  else live_view(cfg, args.estimators, args.foxglove))
    try:
        core = NodeCore(cfg, args.estimators, keep_measurements=args.outdir is not None,
                        reorder_window=args.reorder_window, on_update=feed)
        node = Ros1Node(core, args.name)
    except (ValueError, DdfuseError) as e:
        if view is not None:
            view.close()
        if isinstance(e, DdfuseError):
            raise
        raise DdfuseError(str(e)) from None
    _log_to_stderr()
    print(f"ddfuse node {args.name}: {', '.join(core.session.estimators)} on "
          f"{', '.join(core.topics)}; Ctrl-C ends it", flush=True)
    try:
        why = node.spin()
        if feed is not None:
            feed.finish(core.session)
    finally:
        node.close()
        if view is not None:
            view.close()
    print(f"ddfuse node: {why}; {core.resets} resets", flush=True)
    _print_latency(core.session, {n: t for n, t in core.session.stopped_t.items()})
    for w in core.conv.warnings:
        sys.stderr.write(f"ddfuse: warning: {w}\n")
    if args.outdir is not None:
        try:
            core.write_results(args.outdir)
        except ValueError as e:
            raise DdfuseError(f"-o {args.outdir}: {e}") from None
        print(f"results in {args.outdir}/ (metrics.json, <estimator>.tum/.csv, run.npz)")
    return 0


def _log_to_stderr() -> None:
    """The node's warnings (a clock jump, a topic refused, dropped stamps) on stderr, also
    without -v: rospy's init_node sends the root logger to its log file and /rosout only."""
    lg = logging.getLogger("ddfuse")
    if lg.level == logging.NOTSET or lg.level > logging.WARNING:
        lg.setLevel(logging.WARNING)
    if not any(isinstance(h, logging.StreamHandler) and getattr(h, "stream", None) is sys.stderr
               for h in logging.getLogger().handlers):
        h = logging.StreamHandler(sys.stderr)
        h.setFormatter(logging.Formatter("ddfuse: %(levelname)s %(name)s: %(message)s"))
        lg.addHandler(h)
