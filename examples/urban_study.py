"""The urban GPS study of issue 31 (``ddfuse.evaluation.urban_study``): a scenario over seeds,
the EKFs, and the smoother and batch under each GPS model; its table is docs/results/urban.md.

    python examples/urban_study.py --seeds 0-19 --models default,cauchy --json urban.json
    python examples/urban_study.py --json urban.json --table [more.json ...]
    python examples/urban_study.py --scenario husky --seeds 0-4 --json husky.json
    python examples/urban_study.py --models cauchy --estimators ekf,ekf_igvc --json e.json

(--table joins the files' records per seed: several studies of the same seeds.)
"""

from __future__ import annotations

import argparse
import json
import sys

from ddfuse.evaluation.urban_study import merge, run_study, table


def _seeds(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-19")
    ap.add_argument("--models", default="default,cauchy")
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--scenario", default="urban")
    ap.add_argument("--estimators", default=None,
                    help="comma-separated: only these (e.g. ekf,ekf_igvc); default all")
    ap.add_argument("--json", required=True)
    ap.add_argument("--table", action="store_true",
                    help="print the table of the results in --json (and in the files after it)")
    ap.add_argument("more", nargs="*")
    a = ap.parse_args(argv)
    if a.table:
        results = []
        for path in [a.json, *a.more]:
            with open(path) as f:
                results += json.load(f)
        print(table(merge(results)))
        return 0
    run_study(_seeds(a.seeds), [m for m in a.models.split(",") if m], a.json, a.duration,
              a.scenario, done=lambda s: print(f"seed {s} done", file=sys.stderr, flush=True),
              estimators=a.estimators.split(",") if a.estimators else None)
    return 0


if __name__ == "__main__":
    sys.exit(main())
