"""The ``ddfuse`` command line: argument parsing only; the work is done by the library.

Every user error (bad config, unreadable bag, absent topic, ...) ends in one line on stderr
naming the file, topic, field or key, and exit code 2: never a traceback.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
from pathlib import Path

import yaml
from ddfuse.estimation.errors import DdfuseError

from ddfuse import __version__


def data_dir() -> Path:
    """Where ddfuse's shipped data is: the package ``ddfuse.data`` (the sample bags and their
    configs, ``configs/<stem>.yaml`` of the known real bags), which is ``data/`` of the checkout
    in an editable install and a copy in site-packages in a regular one."""
    from importlib.resources import files

    return Path(str(files("ddfuse.data")))


DATA = data_dir()
SAMPLE_BAG = DATA / "sample_husky.bag"
CONFIGS = DATA / "configs"


def _fmt(v: float, spec: str = ".2f") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def cmd_inspect(args: argparse.Namespace) -> int:
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
        rows.append((t.topic, short_type(t.msgtype), str(t.count), _fmt(t.rate_hz),
                     _fmt(t.median_dt, ".4f"), _fmt(t.t1 - t.t0, ".1f"), str(t.out_of_order)))
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


def _config_for(bag: Path, given: Path | None) -> Path:
    """The config: -c if given, else the bag's path with .yaml (for the storage file inside a
    ROS 2 bag directory, ``h.mcap/h.mcap``, the directory's: ``h.yaml``, as ``ddfuse simulate``
    writes it), else the one ddfuse ships for the known real bags (data/configs/<stem>.yaml)."""
    if given is not None:
        return given
    if not Path(bag).exists():  # say that, not that its config is missing
        raise DdfuseError(f"{bag}: no such bag (file or ROS 2 directory)")
    cands = [bag.with_suffix(".yaml")]
    if (bag.parent / "metadata.yaml").is_file():  # a file inside a ROS 2 bag directory
        cands.append(bag.parent.with_suffix(".yaml"))
    for cand in (*cands, CONFIGS / f"{bag.stem}.yaml"):
        if cand.is_file():
            return cand
    raise DdfuseError(f"{bag}: no config given (-c) and none at {bag.with_suffix('.yaml')}; "
                      f"'ddfuse inspect {bag}' suggests one")


def online_header(frame: dict[str, str]) -> str:
    """The column header ``online`` prints, naming the local frame as ``run``'s report does
    (``frame``: ``ddfuse.evaluation.local_frame.frame`` of the run)."""
    axes = ("x east, y north, yaw counter-clockwise from east" if frame["kind"] == "enu"
            else "yaw counter-clockwise from x")
    return (f"t = s since the first message; per estimator (x m, y m, yaw deg) in "
            f"{frame['short']} ({axes}) +- its 1-sigma (m, m, deg)")


def online_frame(bag: Path, cfg, reorder_window: float | None = None) -> dict[str, str]:
    """``evaluation.local_frame.frame`` of an online replay of ``bag``: the facts it is named from
    (the datum: the config's or the first GPS fix; the landmark map; the initial pose) as
    ``run`` records them in metrics.json. The bag's start is decoded for the datum (what the
    replay's own stream does before its first message, a few ms)."""
    from ddfuse.estimation.bags import BagStream
    from ddfuse.evaluation.local_frame import frame

    stream = BagStream(bag, cfg, reorder_window=reorder_window, keep_truth=False).prime()
    try:
        ip = cfg.initial_pose
        facts = {"data": {"datum": list(stream.datum) if stream.datum else None,
                          "landmarks": len(stream.landmarks)},
                 "initial_pose": "first ground-truth pose" if ip == "ground_truth"
                 else list(ip) if ip else None}
    finally:
        stream.close()
    return frame(facts)


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def cmd_online(args: argparse.Namespace) -> int:
    """Exit code 0 when the bag was replayed to its end, also if an estimator failed (it is
    stopped, one line says which, when and why, and its rows say 'stopped'), as ``run`` exits
    0 with ERROR in that estimator's row; 2 for bad input (a truncated bag: after the
    replay), 130 for Ctrl-C."""
    import numpy as np
    from ddfuse.estimation.config import load_config
    from ddfuse.estimation.errors import RunInterrupted
    from ddfuse.estimation.heading_survey import config_warnings, recorder_for
    from ddfuse.evaluation.online import ONLINE_TRACKS_REFUSED, replay

    for name in args.estimators or ():
        if name in ONLINE_TRACKS_REFUSED:  # before any work
            raise DdfuseError(f"--estimators {name}: not available online: "
                              f"{ONLINE_TRACKS_REFUSED[name]}")
    cfg = load_config(_config_for(args.bag, args.config))
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
              f"on): {_one_line(why)}", flush=True)

    offsets = recorder_for(cfg)
    try:
        session = replay(args.bag, cfg, names=args.estimators, realtime=args.realtime,
                         print_every=args.every, on_print=show,
                         reorder_window=args.reorder_window, interruptible=True,
                         on_stop=on_stop, observers=(offsets.add,))
    except ValueError as e:
        raise DdfuseError(str(e)) from None
    # as run warns: the reader's (a topic mostly dropped), a wrong compass offset
    for w in [*session.input_warnings, *config_warnings(offsets.surveys(), cfg)]:
        sys.stderr.write(f"ddfuse: warning: {w}\n")
    if session.last_t is not None:  # after every estimator's finish(): what it ends with
        show(session.last_t, {k: session.estimate(k) for k in session.estimators},
             final="interrupted" if session.interrupted else True)
    print("update latency (ms):")
    for name, q in session.latency_ms().items():
        err = ""
        if name in stopped:  # said in full when it happened
            at = stopped[name]
            err = "  ERROR: stopped " + ("in its finish" if at is None else f"at t={at:.2f} s")
        elif session.errors[name]:  # interrupted by Ctrl-C inside an update
            err = f"  ERROR: {_one_line(session.errors[name])}"
        ms = {k: "-" if math.isnan(q[k]) else f"{q[k]:.3f}" for k in ("p50", "p99", "max")}
        print(f"  {name:16} p50 {ms['p50']}  p99 {ms['p99']}  max {ms['max']}  "
              f"({q['updates']} updates){err}")
    compact = {n: q for n, q in session.latency_ms().items() if q["compactions"]}
    if compact:  # on the update thread too, every 1000 updates
        print("outside them, the innovation log's compaction every 1000 updates (max ms): "
              + ", ".join(f"{n} {q['compact_max']:.3f} ({q['compactions']} x)"
                          for n, q in compact.items()))
    if session.rejected:
        print("dropped and counted, per topic and reason:")
        for (topic, reason), n in sorted(session.rejected.items()):
            print(f"  {topic}: {n} x {reason}")
    if session.interrupted:
        sys.stdout.flush()
        raise RunInterrupted(session.interrupted)
    if session.input_error:  # a truncated or damaged bag: replayed up to where it breaks off
        sys.stdout.flush()
        raise DdfuseError(f"{session.input_error}; replayed the "
                          f"{session.replayed_s:.1f} s that could be read")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    import json

    from ddfuse.evaluation.bench import bench_bag

    bags = args.bags or [SAMPLE_BAG]
    if args.json:  # before the benchmarks, not after them
        check_output_file(args.json, "--json")
    results = []
    for bag in bags:
        try:
            r = bench_bag(bag, _config_for(bag, args.config), args.estimators, args.lag)
        except ValueError as e:
            raise DdfuseError(str(e)) from None
        results.append(r)
        print(f"{bag}: {r['duration_s']:.1f} s of data, {r['messages']} measurements, decode "
              f"{r['decode_s']:.3f} s ({_fmt(r['decode_rtf'], '.0f')}x real time)")
        print(f"  {'estimator':15} {'est s':>8} {'RTF':>8} {'wall s':>8} {'p50 ms':>8} "
              f"{'p99 ms':>8} {'max ms':>8} {'RSS MB':>8} {'start':>8}")
        notes = []
        for e in r["estimators"]:
            u = e["update_ms"] or {"p50": math.nan, "p99": math.nan, "max": math.nan}
            # the smoother's row says whether it computed the lagged output too
            label = e["estimator"] + ("+lagged" if f"{e['estimator']}_lagged" in e["outputs"]
                                      else "")
            if e.get("offline"):
                # Its latencies look tiny: they miss the whole-run solve, which finish() does.
                label += " *"
                notes.append(f"  * {e['estimator']}: the latencies are of its per-message "
                             f"updates; its whole-run solve runs once in finish(): "
                             f"{e['finish_s']:.3f} s of its est s")
            print(f"  {label:15} {e['runtime_s']:8.3f} {_fmt(e['rtf'], '8.0f')} "
                  f"{e['wall_s']:8.3f} {u['p50']:8.3f} {u['p99']:8.3f} {u['max']:8.3f} "
                  f"{e['peak_rss_mb']:8.1f} {e['start_rss_mb']:8.1f}"
                  + (f"  ERROR {e['error']}" if e["error"] else ""))
        for line in notes:
            print(line)
    # the reader's warnings (the same for every estimator of a bag): once each
    for w in dict.fromkeys(w for r in results for w in r.get("input_warnings") or ()):
        sys.stderr.write(f"ddfuse: warning: {w}\n")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    broken = [r["input_error"] for r in results if r.get("input_error")]
    if broken:  # a truncated or damaged bag: benchmarked on what could be read
        sys.stdout.flush()
        raise DdfuseError(f"{broken[0]}; benchmarked on what could be read"
                          + (f" ({len(broken)} bags)" if len(broken) > 1 else ""))
    return 0


class _Bars:
    """Rich progress bars on stderr, one per stage, shown only when both stdout and stderr are
    terminals and only once a stage has run for ``delay`` seconds (short runs stay quiet)."""

    def __init__(self, delay: float = 2.0, clock=None) -> None:
        import time

        self.delay = delay
        self.clock = clock or time.monotonic
        self.bar = None
        self.tasks: dict[str, int] = {}
        self.started = self.clock()

    def update(self, stage: str, fraction: float) -> None:
        if self.bar is None:
            if self.clock() - self.started < self.delay or fraction >= 1.0:
                return
            from rich.console import Console
            from rich.progress import Progress

            self.bar = Progress(console=Console(stderr=True), transient=True)
            self.bar.start()
        if stage not in self.tasks:
            self.tasks[stage] = self.bar.add_task(stage, total=1.0)
        self.bar.update(self.tasks[stage], completed=fraction)

    def stop(self) -> None:
        if self.bar is not None:
            self.bar.stop()
            self.bar = None


def _progress() -> _Bars | None:
    """Progress bars on a terminal; None (no output at all) when output is redirected."""
    return _Bars() if sys.stdout.isatty() and sys.stderr.isatty() else None


def _render(outdir: Path, bars: _Bars | None) -> Path:
    from ddfuse.evaluation.report import render_report

    return render_report(outdir, progress=(lambda f: bars.update("report", f)) if bars
                         else None)


def produced_estimates(e: dict) -> bool:
    """Whether an estimator's metrics.json entry has a track (``samples``: its length; entries
    written without it are taken to have one)."""
    return e.get("samples") != 0


def _print_summary(m: dict, out) -> None:
    cols = ("final_xy", "ate_rmse_m", "yaw_rmse_deg", "nees_mean", "gps_holdout_rmse_m", "rtf")
    out.write(f"{m['bag']}: {m['duration_s']:.1f} s, {m['messages']} measurements, "
              f"decoded in {m['decode_s']:.2f} s\n")
    out.write("estimator        " + "  ".join(f"{c:>18}" for c in cols) + "\n")
    for name, e in m["estimators"].items():
        cells = []
        for c in cols:
            v = e[c]
            if c == "rtf" and not produced_estimates(e):
                v = None  # the speed of an estimator that never estimated says nothing
            if c == "final_xy" and v:
                cells.append(f"({v[0]:.2f}, {v[1]:.2f})")
            else:
                cells.append("-" if v is None else f"{v:.3f}")
        out.write(f"{name:16} " + "  ".join(f"{c:>18}" for c in cells)
                  + (f"  ERROR: {e['error']}" if e["error"] else "") + "\n")
    w = m.get("wall_s")
    if w:
        est = ", ".join(f"{k} {v:.3f}" for k, v in w["estimators"].items())
        out.write(f"wall time {_fmt(w['total'], '.3f')} s: startup {_fmt(w['startup'], '.3f')}, "
                  f"decode {w['decode']:.3f}, build {w['build']:.3f}, {est}, runner "
                  f"{w['runner']:.3f}, metrics {w['metrics']:.3f}, write {w['write']:.3f}"
                  " (to metrics.json; the report after it not included)\n")


def _print_written_summary(outdir: Path) -> None:
    """The summary table of the metrics.json a run stopped short (a damaged bag, Ctrl-C) wrote
    in ``outdir``, on stdout before the error line (as ``online`` and ``bench`` show what was
    read); nothing when it cannot be read back."""
    import json

    try:
        m = json.loads((Path(outdir) / "metrics.json").read_text())
        _print_summary(m, sys.stdout)
    except (OSError, ValueError, KeyError, TypeError):
        return
    sys.stdout.flush()


def check_holdout_sensor(cfg, config: Path, holdout: str | None) -> None:
    """Before decoding: a GPS hold-out needs a gps sensor in the config; DdfuseError naming
    the option and the config otherwise (it ran and warned that no fix was withheld)."""
    if holdout and not cfg.of_kind("gps"):
        raise DdfuseError(f"--gps-holdout {holdout}: {config} has no gps sensor")


def cmd_run(args: argparse.Namespace) -> int:
    import time

    from ddfuse.estimation.config import load_config
    from ddfuse.estimation.errors import BagError, RunInterrupted
    from ddfuse.evaluation.pipeline import run_bag

    check_output_dir(args.outdir, "-o")  # before any work
    bag = args.bag or SAMPLE_BAG
    config = _config_for(bag, args.config)
    cfg = load_config(config)
    check_holdout_sensor(cfg, config, args.gps_holdout)  # before decoding
    bars = _progress()
    try:
        try:
            m = run_bag(bag, cfg, args.outdir, names=args.estimators, lag=args.lag,
                        holdout=args.gps_holdout, progress=bars.update if bars else None,
                        reorder_window=args.reorder_window)
        except ValueError as e:
            raise DdfuseError(str(e)) from None
        except (BagError, RunInterrupted) as e:
            # A damaged bag whose readable part was estimated, or a run stopped by Ctrl-C: the
            # table and the report show that part, then the error line says why it is a part.
            if getattr(e, "results_written", False):
                _print_written_summary(args.outdir)
                if not args.no_report:
                    _render(args.outdir, bars)
            raise
        _print_summary(m, sys.stdout)
        for w in m.get("warnings") or ():
            sys.stderr.write(f"ddfuse: warning: {w}\n")
        if args.gps_holdout and not m.get("gps_holdout_fixes"):
            sys.stderr.write(f"ddfuse: warning: --gps-holdout {args.gps_holdout} withheld no GPS "
                             f"fix (the data span {m.get('duration_s') or 0:.1f} s from the first "
                             "message): nothing is scored against withheld fixes\n")
        if args.no_report:
            sys.stdout.write(f"results in {args.outdir}/ (metrics.json, <estimator>.tum/.csv, "
                             "run.npz); no report (--no-report)\n")
            return 0
        # The report is rendered after the run, so its time is in no estimator's runtime.
        t_a = time.perf_counter()
        report = _render(args.outdir, bars)
        report_s = time.perf_counter() - t_a
    finally:
        if bars:
            bars.stop()
    sys.stdout.write(f"results in {args.outdir}/ (metrics.json, <estimator>.tum/.csv, run.npz); "
                     f"report {report} ({report_s:.1f} s)\n")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    check_output_dir(args.outdir, "OUTDIR")
    bars = _progress()
    try:
        path = _render(args.outdir, bars)
    finally:
        if bars:
            bars.stop()
    sys.stdout.write(f"{path}\n")
    return 0


def _reorder_window(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not v >= 0.0:
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}")
    return v


def lag_seconds(text: str) -> float:
    """argparse type of a smoother lag: seconds > 0 (the config's smoother.lag rule)."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (v > 0.0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"expected seconds > 0, got {text!r}")
    return v


def int_at_least(minimum: int):
    """argparse type: an integer >= ``minimum``."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}"
                                             ) from None
        if v < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}")
        return v

    return parse


def estimator_list(text: str) -> list[str]:
    """argparse type of --estimators: comma-separated known estimator (or track) names; an
    empty list is refused (leave the option out for the default set)."""
    from ddfuse.evaluation.estimators import TRACK_TO_SPEC

    return _estimator_names(text, list(TRACK_TO_SPEC))


def online_estimator_list(text: str) -> list[str]:
    """``estimator_list`` of ``online``: an unknown name is refused with the names online can
    run (not smoother_lagged or batch; asked for, those are refused with the reason by
    ``cmd_online``)."""
    from ddfuse.evaluation.estimators import TRACK_TO_SPEC
    from ddfuse.evaluation.online import ONLINE_TRACKS_REFUSED

    return _estimator_names(text, [n for n in TRACK_TO_SPEC if n not in ONLINE_TRACKS_REFUSED])


def _estimator_names(text: str, known: list[str]) -> list[str]:
    from ddfuse.evaluation.estimators import TRACK_TO_SPEC

    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated estimator names, got {text!r} (leave --estimators out "
            "for the default set)")
    unknown = [n for n in names if n not in TRACK_TO_SPEC]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown estimator {unknown[0]!r} (known: "
                                         f"{', '.join(known)})")
    return names


def gps_holdout(text: str) -> str:
    """argparse type of --gps-holdout: ``every:K`` (K >= 2) or ``window:T0:T1`` with
    0 <= T0 < T1, seconds from the bag's first message; returned as given."""
    from ddfuse.estimation.runner import parse_holdout

    try:
        parse_holdout(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("--gps-holdout: ")) from None
    return text


GPS_HOLDOUT_HELP = ("withhold these GPS fixes from every estimator and score against them: "
                    "every K-th fix (K >= 2), or the fixes from T0 to T1 s after the bag's first "
                    "message (0 <= T0 < T1)")


def simulated_scenario(name: str, duration: float | None):
    """The simulator scenario ``name`` (chosen from its list by argparse) with ``duration``;
    DdfuseError naming --duration when the duration is refused (before any work)."""
    from ddfuse.evaluation.simulate import get_scenario

    try:
        return get_scenario(name, duration)
    except ValueError as e:
        raise DdfuseError(f"--duration {duration:g}: {str(e).removeprefix('duration ')}"
                          ) from None


def _first_existing(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists (the working directory at worst)."""
    for p in (path, *path.parents):
        if p.exists():
            return p
    return Path(".")


def check_output_file(path: Path, option: str, create_parents: bool = False) -> None:
    """Before any work: ``path`` (given as ``option``) can be written, i.e. it is not a
    directory and its directory exists (or, with ``create_parents``, can be created: no file on
    the way), is a directory and is writable. DdfuseError naming both otherwise."""
    path = Path(path)
    if path.is_dir():
        raise DdfuseError(f"{option} {path}: is a directory; give a file path")
    parent = path.parent
    anchor = _first_existing(parent)
    if not anchor.is_dir():
        raise DdfuseError(f"{option} {path}: {anchor} is a file, not a directory")
    if anchor != parent and not create_parents:
        raise DdfuseError(f"{option} {path}: no such directory {parent}")
    if not os.access(anchor, os.W_OK | os.X_OK):
        raise DdfuseError(f"{option} {path}: directory {anchor} is not writable")


def check_output_dir(path: Path, option: str) -> None:
    """Before any work: the output directory ``path`` (given as ``option``) is a writable
    directory or can be made one (no file on the way, its nearest existing ancestor
    writable); it is not created here, so a run refused later leaves nothing behind.
    DdfuseError naming it otherwise."""
    path = Path(path)
    anchor = _first_existing(path)
    if not anchor.is_dir():
        what = "is a file" if anchor == path else f"{anchor} is a file"
        raise DdfuseError(f"{option} {path}: {what}, not a directory")
    if not os.access(anchor, os.W_OK | os.X_OK):
        raise DdfuseError(f"{option} {path}: directory {anchor} is not writable")


class DdfuseParser(argparse.ArgumentParser):
    """The parser of ``ddfuse`` and of each sub-command: a usage error is one line,
    ``ddfuse: error: <sub-command>: <what> (see ddfuse <sub-command> --help)``, and exit code 2
    (argparse's own prints the usage block first and prefixes the sub-command's prog)."""

    def error(self, message: str):
        sub = self.prog.removeprefix("ddfuse").strip()
        where = f"{sub}: " if sub else ""
        hint = f"ddfuse {sub} --help" if sub else "ddfuse --help"
        self.exit(2, f"ddfuse: error: {where}{_one_line(message)} (see {hint})\n")


CONFIG_HELP = ("config YAML (default: the bag's path with .yaml; else, for the real bags "
               "ddfuse ships a config for, data/configs/<bag's stem>.yaml)")


def _reorder_arg(sp: argparse.ArgumentParser) -> None:
    sp.add_argument("--reorder-window", type=_reorder_window, metavar="S",
                    help="seconds of header-stamp disorder the decoder sorts out (messages "
                    "later than that are dropped and counted; default: the config's "
                    "reorder_window, 0.5 s)")


def build_parser() -> argparse.ArgumentParser:
    p = DdfuseParser(
        prog="ddfuse",
        description="Pose estimation for differential-drive robots from ROS bags: "
                    "EKF baseline vs GTSAM fixed-lag smoother.")
    p.add_argument("-v", "--verbose", action="store_true", help="log details to stderr")
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    sp = sub.add_parser("inspect", help="topics, rates, covariance sanity and a suggested config")
    sp.add_argument("bag", type=Path, help="ROS1 .bag, ROS2 bag directory or .mcap")
    sp.set_defaults(func=cmd_inspect)

    sp = sub.add_parser("run", help="run the estimators side by side on a bag and score them")
    sp.add_argument("bag", type=Path, nargs="?",
                    help=f"bag to run (default: the embedded sample {SAMPLE_BAG.name})")
    sp.add_argument("-c", "--config", type=Path, help=CONFIG_HELP)
    sp.add_argument("-o", "--outdir", type=Path, default=Path("ddfuse-out"),
                    help="output directory (default: ddfuse-out)")
    sp.add_argument("--estimators", type=estimator_list, metavar="LIST",
                    help="comma-separated: ekf, ekf_igvc, ekf_landmark, "
                    "ekf_slam, smoother, smoother_lagged, batch, dr (dead reckoning, by name "
                    "only; default: all but dr that the config's sensors allow)")
    sp.add_argument("--lag", type=lag_seconds, metavar="S",
                    help="smoother lag, s (default: from the config)")
    sp.add_argument("--gps-holdout", type=gps_holdout, metavar="every:K|window:T0:T1",
                    help=GPS_HOLDOUT_HELP)
    _reorder_arg(sp)
    sp.add_argument("--no-report", action="store_true",
                    help="write the results (metrics.json, tracks, run.npz) but not the HTML "
                    "report ('ddfuse report OUTDIR' renders it later)")
    sp.set_defaults(func=cmd_run)

    sp = sub.add_parser("report", help="re-render OUTDIR/report.html from the results that "
                        "'ddfuse run -o OUTDIR' saved")
    sp.add_argument("outdir", type=Path, help="a directory written by ddfuse run")
    sp.set_defaults(func=cmd_report)

    sp = sub.add_parser(
        "online", help="replay a bag message by message, as a live robot would",
        description="Replay a bag message by message, as a live robot would, printing the "
        "current estimates as it goes. An estimator that fails is stopped there (one line says "
        "which, when and why; its last estimate is kept) and the others go on; the exit code "
        "stays 0 then, as for 'run' (whose table shows ERROR in its row). Exit 2: bad input "
        "(a truncated bag: after replaying what could be read); 130: Ctrl-C.")
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
    _reorder_arg(sp)
    sp.set_defaults(func=cmd_online)

    sp = sub.add_parser("bench", help="speed and memory of each estimator on bags")
    sp.add_argument("bags", type=Path, nargs="*", help="bags (default: the embedded sample)")
    sp.add_argument("-c", "--config", type=Path,
                    help="config YAML for every bag given (default: per bag, "
                    + CONFIG_HELP.removeprefix("config YAML (default: "))
    sp.add_argument("--estimators", type=estimator_list, metavar="LIST",
                    help="comma-separated (default: all the sensors allow); 'smoother' alone "
                    "times the filtered output, with 'smoother_lagged' the lagged one too")
    sp.add_argument("--lag", type=lag_seconds, metavar="S",
                    help="smoother lag, s (default: from the config)")
    sp.add_argument("--json", type=Path, metavar="FILE", help="also write the results as JSON")
    sp.set_defaults(func=cmd_bench)

    sub.add_parser("simulate", help="simulate a robot drive into a bag with ground truth "
                   "(ddfuse simulate --help)")
    sub.add_parser("plot-sim", help="plot a simulated scenario: truth, GPS, dead reckoning "
                   "(ddfuse plot-sim --help)")
    sub.add_parser("lag-sweep", help="the smoother's accuracy, latency and CPU against its lag "
                   "(ddfuse lag-sweep --help)")
    sub.add_parser("mc", help="Monte Carlo runs on a simulated scenario: RMSE, dead reckoning, "
                   "average NEES and its chi-square band (ddfuse mc --help)")
    return p


# Sub-commands whose module parses its own arguments (argparse.REMAINDER cannot pass a leading
# option such as --help through, so they are dispatched before the top-level parser).
DELEGATED = {"simulate": "ddfuse.evaluation.simulate", "plot-sim": "ddfuse.evaluation.plot_sim",
             "lag-sweep": "ddfuse.evaluation.lag_sweep", "mc": "ddfuse.evaluation.montecarlo"}


def guarded(func, *args) -> int:
    """``func(*args)`` with ddfuse's error handling: a DdfuseError, or an OSError on a path
    (an output directory that is a file, a full disk...), ends in one line on stderr and exit
    code 2; Ctrl-C in 130. Anything else (a bug) propagates with its traceback."""
    try:
        return func(*args) or 0
    except DdfuseError as e:
        print(f"ddfuse: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        raise  # a reader that stopped early: entry() ends quietly
    except OSError as e:  # an output path that cannot be written: a directory that is a file...
        where = f"{e.filename}: " if e.filename else ""
        what = " (a file where a directory is needed)" if isinstance(
            e, (FileExistsError, NotADirectoryError)) else ""
        print(f"ddfuse: error: {where}{e.strerror or e}{what}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        print(f"ddfuse: {e}" if str(e) else "ddfuse: interrupted", file=sys.stderr)
        return 130


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in DELEGATED:
        import importlib

        return guarded(importlib.import_module(DELEGATED[argv[0]]).main, argv[1:])
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.ERROR,
                        format="%(levelname)s %(name)s: %(message)s")
    return guarded(args.func, args)


def entry() -> None:
    """The ``ddfuse`` program: :func:`main`, then exit without tearing the interpreter down.

    Tearing down a process that has loaded numba's kernels, LLVM, gtsam and scipy takes
    0.3-0.4 s (module by module, object by object) after the work is done and every output
    file is closed; a program about to end need not free its memory. Output streams and
    logging are flushed first. ``main`` itself returns normally (tests call it); an exception
    that escapes it ends the process the ordinary way, with its traceback. A reader that
    stops early (``ddfuse inspect BAG | head``) ends it quietly, as it does ``cat``."""
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


if __name__ == "__main__":
    entry()
