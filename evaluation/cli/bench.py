"""``ddfuse bench [BAGS]``: speed and memory of each estimator on bags, as a table."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from ddfuse.estimation.errors import DdfuseError
from ddfuse.evaluation.atomic_files import write_text
from ddfuse.evaluation.cli.arguments import CONFIG_HELP, estimator_list, lag_seconds
from ddfuse.evaluation.cli.output_paths import check_output_file
from ddfuse.evaluation.cli.terminal import fmt
from ddfuse.evaluation.shipped import SAMPLE_BAG, config_for


def add_to(sub) -> None:
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
    sp.set_defaults(func=command)


def command(args: argparse.Namespace) -> int:
    import json

    from ddfuse.evaluation.bench import bench_bag

    bags = args.bags or [SAMPLE_BAG]
    if args.json:  # before the benchmarks, not after them
        check_output_file(args.json, "--json")
    results = []
    for bag in bags:
        try:
            r = bench_bag(bag, config_for(bag, args.config), args.estimators, args.lag)
        except ValueError as e:
            raise DdfuseError(str(e)) from None
        results.append(r)
        _print_bag(bag, r)
    # the reader's warnings (the same for every estimator of a bag): once each
    for w in dict.fromkeys(w for r in results for w in r.get("input_warnings") or ()):
        sys.stderr.write(f"ddfuse: warning: {w}\n")
    if args.json:
        write_text(args.json, json.dumps(results, indent=2) + "\n")
    broken = [r["input_error"] for r in results if r.get("input_error")]
    if broken:  # a truncated or damaged bag: benchmarked on what could be read
        sys.stdout.flush()
        raise DdfuseError(f"{broken[0]}; benchmarked on what could be read"
                          + (f" ({len(broken)} bags)" if len(broken) > 1 else ""))
    return 0


def _print_bag(bag: Path, r: dict) -> None:
    """The table of ``bench_bag``'s result ``r`` for ``bag``: one row per estimator."""
    print(f"{bag}: {r['duration_s']:.1f} s of data, {r['messages']} measurements, decode "
          f"{r['decode_s']:.3f} s ({fmt(r['decode_rtf'], '.0f')}x real time)")
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
        print(f"  {label:15} {e['runtime_s']:8.3f} {fmt(e['rtf'], '8.0f')} "
              f"{e['wall_s']:8.3f} {u['p50']:8.3f} {u['p99']:8.3f} {u['max']:8.3f} "
              f"{e['peak_rss_mb']:8.1f} {e['start_rss_mb']:8.1f}"
              + (f"  ERROR {e['error']}" if e["error"] else ""))
    for line in notes:
        print(line)
