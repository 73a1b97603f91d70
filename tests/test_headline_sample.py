"""The headline of the demo (``ddfuse run`` on data/sample_husky.bag): the terminal prints the
lines the report shows on top, its winner and margin are metrics.json's, and its next command
runs."""

from __future__ import annotations

import contextlib
import html
import io
import json
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow  # the sample bag's run and the next command's: about 80 s CPU


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> tuple[Path, str]:
    from ddfuse.evaluation import cli

    out = tmp_path_factory.mktemp("headline") / "out"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert cli.main(["run", str(ROOT / "data" / "sample_husky.bag"), "-o", str(out)]) == 0
    return out, buf.getvalue()


def _terminal_headline(stdout: str) -> list[str]:
    lines = stdout.splitlines()
    start = next(k for k, ln in enumerate(lines) if ln.startswith("---- headline "))
    return lines[start + 1:next(k for k, ln in enumerate(lines) if ln.startswith("results in "))]


def _report_headline(page: str) -> list[str]:
    block = re.search(r"<div class='headline' id='headline'>(.*?)</div>", page).group(1)
    return [html.unescape(re.sub(r"<[^>]+>", "", p)) for p in re.findall(r"<p>(.*?)</p>", block)]


def test_the_terminal_and_the_report_show_the_same_headline(demo):
    out, stdout = demo
    term = _terminal_headline(stdout)
    assert term and term == _report_headline((out / "report.html").read_text())


def test_the_winner_and_margin_are_those_of_metrics_json(demo):
    out, stdout = demo
    m = json.loads((out / "metrics.json").read_text())
    common = {n: e["ate_common_rmse_m"] for n, e in m["estimators"].items()}
    order = sorted(common, key=common.get)
    first = _terminal_headline(stdout)[0]
    hit = re.match(r"Best: (\w+)[^,]*, ATE on common stamps ([0-9.]+) m", first)
    assert hit and hit.group(1) == order[0]
    assert float(hit.group(2)) == pytest.approx(common[order[0]], abs=5e-4)
    # the margin is to the first track more than the tie rule's 5 % behind
    nxt = next(n for n in order if common[n] - common[order[0]] > 0.05 * common[n])
    gap = re.search(r"; ([0-9.]+) m \((\d+)%\) lower than the next, (\w+)", first)
    assert gap.group(3) == nxt
    assert float(gap.group(1)) == pytest.approx(common[nxt] - common[order[0]], abs=1e-3)
    # the table ranks on the same figure: its rows in that order
    rows = [ln.split() for ln in stdout.splitlines() if ln[:1].isdigit()]
    assert [r[1] for r in rows] == order


def test_the_next_command_runs(demo, tmp_path):
    from ddfuse.evaluation import cli

    _, stdout = demo
    line = next(ln for ln in _terminal_headline(stdout) if ln.startswith("Next: "))
    cmd = shlex.split(line[len("Next: "):].split("  (")[0])
    assert cmd[0] == "ddfuse"
    args = cmd[1:]
    if "-o" in args:  # into this test's folder, not the working directory
        args[args.index("-o") + 1] = str(tmp_path / args[args.index("-o") + 1])
    assert cli.main(args) == 0
    if args[0] == "run" and "--gps-holdout" in args:
        m = json.loads((Path(args[args.index("-o") + 1]) / "metrics.json").read_text())
        assert m["gps_holdout_fixes"] > 0 and m["gps_outages"]


def test_report_prints_the_runs_headline(demo):
    """``ddfuse report OUTDIR`` re-renders the page and prints the headline ``run`` printed."""
    from ddfuse.evaluation import cli

    out, stdout = demo
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert cli.main(["report", str(out)]) == 0
    printed = buf.getvalue().splitlines()
    start = printed.index(next(ln for ln in printed if ln.startswith("---- headline ")))
    assert printed[start + 1:-1] == _terminal_headline(stdout)
    assert printed[-1] == str(out / "report.html")
