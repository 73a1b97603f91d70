"""``ddfuse report OUTDIR``: re-render OUTDIR/report.html from what ``ddfuse run`` saved."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ddfuse.evaluation.cli.output_paths import check_output_dir
from ddfuse.evaluation.cli.terminal import Bars, progress


def add_to(sub) -> None:
    sp = sub.add_parser("report", help="re-render OUTDIR/report.html from the results that "
                        "'ddfuse run -o OUTDIR' saved")
    sp.add_argument("outdir", type=Path, help="a directory written by ddfuse run")
    sp.set_defaults(func=command)


def render(outdir: Path, bars: Bars | None) -> Path:
    """The report of ``outdir`` rendered, with a 'report' progress bar when ``bars``. The
    figures' second process (``figure_helper``) is started first, so that its imports run
    beside this process's."""
    from ddfuse.evaluation import figure_helper

    helper = figure_helper.start(outdir)
    try:
        from ddfuse.evaluation.report import render_report

        return render_report(outdir, progress=(lambda f: bars.update("report", f)) if bars
                             else None, helper=helper)
    finally:
        if helper is not None:
            helper.close()


def command(args: argparse.Namespace) -> int:
    check_output_dir(args.outdir, "OUTDIR")
    bars = progress()
    try:
        path = render(args.outdir, bars)
    finally:
        if bars:
            bars.stop()
    # the same headline as run's, read back from the metrics the report was rendered from
    import json

    from ddfuse.evaluation.cli.terminal import headline_text
    from ddfuse.evaluation.headline import headline
    from ddfuse.evaluation.scores import RunSummary
    summary = RunSummary.from_json(json.loads((args.outdir / "metrics.json").read_text()))
    sys.stdout.write(headline_text(headline(summary).lines()))
    sys.stdout.write(f"{path}\n")
    return 0
