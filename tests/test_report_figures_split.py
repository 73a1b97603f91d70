"""The report's figures drawn in two processes (``evaluation.report_figures`` with a
``figure_helper``): every figure drawn once, by one of them, the page and the PNGs byte for byte
those of one process; a helper that delivers nothing leaves its share to this process; and the
page's 'not run' list no longer loads the estimators' libraries."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from ddfuse.evaluation import cli, close_ups, figure_helper, report, report_figures
from ddfuse.evaluation.results import load_run
from ddfuse.evaluation.run_files import PLOTS_DIR


@pytest.fixture(scope="module")
def sample_run(tmp_path_factory) -> Path:
    """The embedded sample with the default estimators, no report rendered yet."""
    out = tmp_path_factory.mktemp("split") / "out"
    assert cli.main(["run", "-o", str(out), "--no-report"]) == 0
    return out


def _pngs(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((out / PLOTS_DIR).glob("*.png"))}


def test_the_split_deals_every_figure_once_and_alike_in_both_processes(sample_run):
    run = load_run(sample_run)
    mine, theirs = report_figures.split(run, 2, 0.0)
    assert sorted(mine + theirs) == sorted(report_figures.FIGURES)
    assert not set(mine) & set(theirs) and theirs
    # the estimated shares are within one figure of each other
    panels = report_figures.panels(run, 2)
    assert panels["nis"] >= 6 and panels["errors"] == 15  # 5 tracks x (x, y, heading)
    # the helper starting later gets less
    late_mine, late_theirs = report_figures.split(run, 2, 5.0)
    assert len(late_theirs) < len(theirs) and report_figures.split(run, 2, 0.0) == (mine, theirs)


@pytest.mark.slow
def test_two_processes_draw_the_page_of_one(sample_run, tmp_path, monkeypatch):
    if not figure_helper.wanted():
        pytest.skip("one CPU: no helper process is started")
    one = tmp_path / "one"
    two = tmp_path / "two"
    for d in (one, two):
        # the same results in two directories (the page names its directory)
        subprocess.run(["cp", "-r", str(sample_run), str(d)], check=True)
    sent = []
    results = figure_helper.Helper.results

    def spy(self):
        got = results(self)
        sent.append(sorted(got or {}))
        return got

    monkeypatch.setattr(figure_helper.Helper, "results", spy)
    report.render_report(two)
    run = load_run(two)
    theirs = report_figures.split(run, len(close_ups.zoom_windows(run)),
                                  figure_helper.LATE_START_S)[1]
    assert theirs and sent == [sorted(theirs)]  # the helper delivered its share
    monkeypatch.setattr(figure_helper, "wanted", lambda: False)
    report.render_report(one)
    assert _pngs(one) == _pngs(two) and len(_pngs(one)) >= 6

    def page(d):
        text = (d / "report.html").read_text().replace(str(d), "OUT")
        return text.split("Rendered", 1)[0] + text.split("figures in", 1)[1].split(")", 1)[1]

    assert page(one) == page(two)


@pytest.mark.slow
def test_a_helper_that_delivers_nothing_leaves_its_share_here(sample_run, tmp_path,
                                                              monkeypatch):
    if not figure_helper.wanted():
        pytest.skip("one CPU: no helper process is started")
    out = tmp_path / "out"
    subprocess.run(["cp", "-r", str(sample_run), str(out)], check=True)
    monkeypatch.setattr(figure_helper.Helper, "results", lambda self: (self.close(), None)[1])
    report.render_report(out)
    names = {p.stem for p in (out / PLOTS_DIR).glob("*.png")}
    assert {"errors", "nis", "latency", "covariance", "trajectories"} <= names
    assert report.render_report(out).exists()


def test_the_pages_not_run_list_loads_no_estimator_library():
    """``report.not_run`` reads the registry (evaluation.estimators): its names and rules, not
    the estimators' classes (gtsam, numba, scipy: ~0.8 s of imports for a list of names)."""
    code = ("import sys; from ddfuse.evaluation import report; "
            "from ddfuse.evaluation.scores import RunSummary; "
            "report.not_run(RunSummary.from_json({'estimators': {}}), None); "
            "print(sorted(m for m in ('gtsam', 'numba', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "[]"
