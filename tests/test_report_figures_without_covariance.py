"""Figures and captions when a track has no covariance or no innovation (dead reckoning):
no blank figure, a note saying why, and the track named where others are drawn."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import pytest
from ddfuse.evaluation import cli, plots, report
from ddfuse.evaluation.results import load_run

ROOT = Path(__file__).resolve().parents[1]
SEED002 = ROOT / "data" / "sample_seed002.bag"


@pytest.fixture(scope="module")
def dr_run(tmp_path_factory) -> Path:
    """The embedded sample, dead reckoning alone: no covariance, no innovation."""
    out = tmp_path_factory.mktemp("dr") / "out"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert cli.main(["run", "-o", str(out), "--estimators", "dr"]) == 0
    out.joinpath("warnings.txt").write_text("\n".join(str(w.message) for w in caught))
    return out


def test_no_blank_figures_when_nothing_has_a_covariance_or_an_innovation(dr_run):
    """dr alone: no nis.png (it was a blank white image), no covariance.png (empty
    axes), each replaced by a note saying why, and no matplotlib legend warning."""
    names = sorted(p.name for p in (dr_run / "plots").iterdir())
    assert "nis.png" not in names and "covariance.png" not in names and "nees.png" not in names
    assert "errors.png" in names and "trajectories.png" in names
    page = (dr_run / "report.html").read_text()
    figs = page.split("<h2>Figures</h2>")[1].split("<h2>Data</h2>")[0]
    assert len(re.findall(r"<img ", figs)) == len([n for n in names if n.endswith(".png")])
    assert "No NIS figure: no estimator logged an innovation" in figs
    assert "No covariance figure: dr has no covariance." in figs
    assert "No NEES figure: dr has no covariance." in figs
    assert "No per-estimator trajectory figure: dr is the only estimate" in figs
    # nothing promised that is not there
    assert "NIS of each innovation" not in figs and "Trace of the position covariance" not in figs
    [errors_caption] = [c for c in re.findall(r"<figcaption>(.*?)</figcaption>", figs)
                        if c.startswith("Errors against")]
    assert "±3σ" not in errors_caption and "No envelope: dr has no covariance." in errors_caption
    assert "No artists with labels" not in (dr_run / "warnings.txt").read_text()
    run = load_run(dr_run)
    assert plots.nis(run) is None and plots.covariance(run) is None
    # the errors panel draws no envelope, so its legend names none
    fig, _ = plots.errors(run)
    assert "±3σ" not in [t.get_text() for ax in fig.axes if ax.get_legend()
                         for t in ax.get_legend().get_texts()]


def test_a_track_without_covariance_is_named_where_the_others_have_one(dr_run, seed002_run):
    """Beside tracks with a covariance: the figures are drawn, and their captions say dr is
    not in them (no envelope, not drawn)."""
    run = load_run(seed002_run)
    dr = load_run(dr_run).tracks["dr"]
    run.tracks = {**run.tracks, "dr": dr}
    cap = report.captions(run)
    assert "Not drawn: dr (it has no covariance)." in cap["covariance"]
    assert "Not drawn: dr" in cap["nees"]
    assert plots.covariance(run) is not None
    _, errors_caption = plots.errors(run)
    assert "±3σ envelope" in errors_caption and "dr has no covariance, so no envelope." in \
        errors_caption
