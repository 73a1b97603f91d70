"""``ddfuse online BAG``: replay a bag message by message, printing the current estimates.

The replay is the library's (``evaluation.online.replay``); this module prints the rows as the
replay calls back, the line of an estimator that is stopped, and the latency summary.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from ddfuse.estimation.errors import DdfuseError
from ddfuse.evaluation.cli.arguments import (
    CONFIG_HELP,
    add_foxglove,
    add_reorder_window,
    lag_seconds,
    online_estimator_list,
)
from ddfuse.evaluation.cli.terminal import one_line
from ddfuse.evaluation.shipped import config_for


def add_to(sub) -> None:
    sp = sub.add_parser(
        "online", help="replay a bag message by message, as a live robot would",
        description="Replay a bag message by message, as a live robot would, printing the "
        "current estimates as it goes. An estimator that fails is stopped there (one line says "
        "which, when and why; its last estimate is kept) and the others go on; the exit code "
        "stays 0 then, as for 'run' (whose table shows ERROR in its row). Exit 2: bad input "
        "(a truncated bag: after replaying what could be read); 3: every estimator failed or "
        "never gave an estimate; 130: Ctrl-C. With --foxglove, the view keeps serving after the "
        "end until Ctrl-C, which then ends it with the exit code the replay had.")
    sp.add_argument("bag", type=Path, help="bag to replay: ROS1 .bag, ROS2 bag directory or "
                    ".mcap")
    sp.add_argument("-c", "--config", type=Path, help=CONFIG_HELP)
    sp.add_argument("--estimators", type=online_estimator_list, metavar="LIST",
                    help="comma-separated (default: all the sensors allow); not "
                    "smoother_lagged or batch: the lagged output exists only once a keyframe "
                    "leaves the smoother's window and the batch only at the end, so neither can "
                    "be shown as the data comes (use 'ddfuse run')")
    sp.add_argument("--realtime", action="store_true", help="pace messages by their stamps")
    sp.add_argument("--every", type=lag_seconds, default=1.0, metavar="S",
                    help="print the current estimates every S > 0 seconds of data (default 1); "
                    "the final ones are always printed")
    add_reorder_window(sp)
    add_foxglove(sp)
    sp.set_defaults(func=command)


def online_header(frame: dict[str, str]) -> str:
    """The column header ``online`` prints, naming the local frame as ``run``'s report does
    (``frame``: ``ddfuse.evaluation.local_frame.frame`` of the run)."""
    axes = ("x east, y north, yaw counter-clockwise from east" if frame["kind"] == "enu"
            else "yaw counter-clockwise from x")
    return (f"t = s since the first message; per estimator (x m, y m, yaw deg) in "
            f"{frame['short']} ({axes}) +- its 1-sigma (m, m, deg)")


def command(args: argparse.Namespace) -> int:
    """Exit code 0 when the bag was replayed to its end, also if an estimator failed (it is
    stopped, one line says which, when and why, and its rows say 'stopped'), as ``run`` exits
    0 with ERROR in that estimator's row; 2 for bad input (a truncated bag: after the
    replay), 3 when every estimator failed or never gave an estimate, 130 for Ctrl-C."""
    import numpy as np
    from ddfuse.estimation.config import load_config
    from ddfuse.estimation.errors import RunInterrupted
    from ddfuse.estimation.heading_survey import config_warnings, recorder_for
    from ddfuse.evaluation.online import ONLINE_TRACKS_REFUSED, online_frame, replay

    for name in args.estimators or ():
        if name in ONLINE_TRACKS_REFUSED:  # before any work
            raise DdfuseError(f"--estimators {name}: not available online: "
                              f"{ONLINE_TRACKS_REFUSED[name]}")
    cfg = load_config(config_for(args.bag, args.config))
    header = online_header(online_frame(args.bag, cfg, args.reorder_window))
    printed: list[bool] = []
    stopped: dict[str, float | None] = {}  # estimator -> s since the first message it stopped

    def show(t: float, estimates: dict, final: bool = False) -> None:
        if not printed:
            printed.append(True)
            print(header)
        cells = []
        for name, e in estimates.items():
            mark = ""
            if name in stopped:
                if not final:
                    cells.append(f"{name} stopped")
                    continue
                at = stopped[name]
                mark = " stopped" + ("" if at is None else f" at t={at:.2f} s")
            if e is None:
                cells.append(f"{name} -{mark}")
                continue
            sd = [math.sqrt(v) if v >= 0.0 else math.nan for v in np.diag(e.pose_cov)]
            # a heading sigma past 180 deg says only that the heading is unknown
            sd_yaw = f"{math.degrees(sd[2]):.1f}" if not sd[2] > math.pi else ">180"
            cells.append(f"{name} ({e.pose[0]:8.2f}, {e.pose[1]:8.2f}, "
                         f"{math.degrees(e.pose[2]):7.1f} deg) +- ({sd[0]:.2f}, {sd[1]:.2f}, "
                         f"{sd_yaw} deg){mark}")
        end = "" if not final else "  (at the interrupt)" if final == "interrupted" else \
            "  (final)"
        print(f"t={t:8.2f} s  " + "  ".join(cells) + end, flush=True)

    def on_stop(name: str, t: float | None, why: str) -> None:
        stopped[name] = t
        at = "in its finish" if t is None else f"at t={t:.2f} s"
        print(f"{name} failed {at} and is stopped (its last estimate is kept, the others go "
              f"on): {one_line(why)}", flush=True)

    offsets = recorder_for(cfg)
    view, feed = ((None, None) if args.foxglove is None
                  else live_view(cfg, args.estimators, args.foxglove, args.bag))
    try:
        session = replay(args.bag, cfg, names=args.estimators, realtime=args.realtime,
                         print_every=args.every, on_print=show,
                         reorder_window=args.reorder_window, interruptible=True,
                         on_stop=on_stop, observers=(offsets.add,), on_update=feed)
    except ValueError as e:
        raise DdfuseError(str(e)) from None
    if feed is not None:
        feed.finish(session)
    # as run warns: the reader's (a topic mostly dropped), a wrong compass offset
    for w in [*session.input_warnings, *config_warnings(offsets.surveys(), cfg)]:
        sys.stderr.write(f"ddfuse: warning: {w}\n")
    if session.last_t is not None:  # after every estimator's finish(): what it ends with
        show(session.last_t, {k: session.estimate(k) for k in session.estimators},
             final="interrupted" if session.interrupted else True)
    _print_latency(session, stopped)
    if view is not None:
        _serve_until_interrupt(view, held=not session.interrupted,
                               resend=lambda: feed.finish(session))
    if session.interrupted:
        sys.stdout.flush()
        raise RunInterrupted(session.interrupted)
    if session.input_error:  # a truncated or damaged bag: replayed up to where it breaks off
        sys.stdout.flush()
        raise DdfuseError(f"{session.input_error}; replayed the "
                          f"{session.replayed_s:.1f} s that could be read")
    failed = [k for k in session.estimators
              if k in stopped or session.errors[k] or session.estimate(k) is None]
    if session.estimators and len(failed) == len(session.estimators):
        from ddfuse.evaluation.cli.guard import NO_ESTIMATE

        sys.stderr.write("ddfuse: error: every estimator failed or never gave an estimate "
                         "(the lines above say why)\n")
        return NO_ESTIMATE
    return 0


def live_view(cfg, estimators, port: int, bag=None):
    """The Foxglove live view of ``--foxglove`` (``online``, ``node``) on ``port`` and its feed;
    with ``bag``, the bag's ground truth read ahead (the replay keeps none)."""
    from ddfuse.evaluation import estimators as registry
    from ddfuse.evaluation.live_view import LiveView, ReplayFeed, read_truth
    from ddfuse.evaluation.online import ONLINE_TRACKS_REFUSED as refused

    # the session's tracks, advertised before any client connects (foxglove-sdk 0.30 refused
    # a subscription to a channel created while a client was connected, now and then)
    names = [t for n in registry.select(cfg, estimators) if n not in refused
             for t in registry.SPECS[n].produces if t not in refused]
    view = LiveView(cfg, names, port=port)
    sys.stderr.write(f"ddfuse: live view on {view.url} (Foxglove: Open connection, Foxglove "
                     "WebSocket, that address)\n")
    return view, ReplayFeed(view, cfg, read_truth(bag, cfg) if bag is not None else None)


def _serve_until_interrupt(view, held: bool, resend) -> None:
    """After the replay: keep serving the last estimates until Ctrl-C (``held``; not after a
    Ctrl-C that ended the replay), sent again every second (``resend``) for a client that
    connects after the end, then stop the server."""
    import time

    try:
        if held:
            sys.stderr.write(f"ddfuse: the replay has ended; still serving on {view.url} "
                             "(Ctrl-C to end)\n")
            sys.stderr.flush()
            while True:
                time.sleep(1.0)
                resend()
    except KeyboardInterrupt:
        pass
    finally:
        view.close()


def _print_latency(session, stopped: dict[str, float | None]) -> None:
    """Per estimator its update latency percentiles (and why it stopped), the innovation log's
    compactions, and what the reader dropped."""
    print("update latency (ms):")
    for name, q in session.latency_ms().items():
        err = ""
        if name in stopped:  # said in full when it happened
            at = stopped[name]
            err = "  ERROR: stopped " + ("in its finish" if at is None else f"at t={at:.2f} s")
        elif session.errors[name]:  # interrupted by Ctrl-C inside an update
            err = f"  ERROR: {one_line(session.errors[name])}"
        ms = {k: "-" if math.isnan(q[k]) else f"{q[k]:.3f}" for k in ("p50", "p99", "max")}
        print(f"  {name:16} p50 {ms['p50']}  p99 {ms['p99']}  max {ms['max']}  "
              f"({q['updates']} updates){err}")
    compact = {n: q for n, q in session.latency_ms().items() if q["compactions"]}
    if compact:  # on the update thread too, every 1000 updates
        print("outside them, the innovation log's compaction every 1000 updates (max ms): "
              + ", ".join(f"{n} {q['compact_max']:.3f} ({q['compactions']} x)"
                          for n, q in compact.items()))
    late = session.late_counts()
    if any(c["used"] or c["dropped"] for c in late.values()):
        # the smoother can put a late fix into a past keyframe, an EKF cannot
        print("late measurements (stamped before one already passed on), per estimator: "
              "used / dropped, by sensor")
        for name, c in late.items():
            used, dropped = (", ".join(f"{s} {n}" for s, n in c[k].items()) or "-"
                             for k in ("used", "dropped"))
            print(f"  {name:16} used {used}  dropped {dropped}")
    if session.rejected:
        print("dropped and counted, per topic and reason:")
        for (topic, reason), n in sorted(session.rejected.items()):
            print(f"  {topic}: {n} x {reason}")
