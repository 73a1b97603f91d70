"""``ddfuse compare BASELINE NEW``: per bag and estimator what got better or worse beyond a
tolerance (``evaluation.compare_scores``); exit 1 on a regression, for CI pipelines."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ddfuse.evaluation.cli.output_paths import check_output_file
from ddfuse.evaluation.cli.terminal import fmt

REGRESSED = 1  # exit code: something got worse (or was lost) beyond the tolerance


def _non_negative(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = -1.0
    if not v >= 0.0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return v


def add_to(sub) -> None:
    sp = sub.add_parser("compare", help="compare two runs' scores per bag and estimator; "
                        "exit 1 when something got worse beyond the tolerance")
    sp.add_argument("baseline", type=Path, metavar="BASELINE",
                    help="metrics.json, a run directory or a fleet.json")
    sp.add_argument("new", type=Path, metavar="NEW", help="the same, of the run to judge")
    sp.add_argument("--tol-m", type=_non_negative, default=0.01, metavar="M",
                    help="a change counts only beyond M metres (default 0.01)")
    sp.add_argument("--tol-pct", type=_non_negative, default=5.0, metavar="P",
                    help="... and beyond P %% of the baseline's score (default 5, the "
                    "report's tie rule)")
    sp.add_argument("--json", type=Path, metavar="OUT", help="write the comparison here")
    sp.set_defaults(func=command)


def _cell(s) -> str:
    if s is None:
        return "-"
    if s.value is None:
        return f"ERROR {s.error}" if s.error else "no score"
    return f"{s.value:.3f} m ({s.kind})"


def command(args: argparse.Namespace) -> int:
    from ddfuse.evaluation.atomic_files import write_text
    from ddfuse.evaluation.compare_scores import REGRESSIONS, compare, load_scores, to_json

    if args.json:
        check_output_file(args.json, "--json")
    pairs = compare(load_scores(args.baseline), load_scores(args.new), args.tol_m,
                    args.tol_pct)
    out = sys.stdout
    for p in pairs:
        change = "" if p.delta_m is None else (f" ({p.delta_m:+.3f} m, "
                                               f"{fmt(p.delta_pct, '+.1f')}%)")
        out.write(f"{p.bag:24} {p.estimator or '(bag)':16} {p.status.upper():12} "
                  f"{_cell(p.base)} -> {_cell(p.new)}{change}\n")
    doc = to_json(pairs, args.tol_m, args.tol_pct)
    if args.json:
        write_text(args.json, json.dumps(doc, indent=1) + "\n")
    n = doc["regressions"]
    out.write(f"{len(pairs)} compared (tolerance {args.tol_m:g} m and {args.tol_pct:g}%): "
              + ", ".join(f"{c} {k}" for k, c in doc["counts"].items())
              + (f"; {n} regression{'s' if n > 1 else ''} "
                 f"({', '.join(sorted(REGRESSIONS))})" if n else "; no regression") + "\n")
    return REGRESSED if n else 0
