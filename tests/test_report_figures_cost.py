"""What a report figure costs beyond its drawing: ``plots._finish`` lays a figure out in one
pass and leaves no layout engine behind (else ``savefig`` draws the whole figure a second time
before rendering it), ``plots.legible`` sizes the tick labels without making the ticks, the NIS
figure makes no blank panels, and the figures' helper is one process (no resource tracker beside
it) that, like the command, starts without importlib.metadata."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from ddfuse.evaluation import plots
from matplotlib.figure import Figure


def _figure() -> Figure:
    fig, axes = plots.subplots(3, 1, figsize=(plots.PAGE_W, 6.0), sharex=True)
    t = np.linspace(0.0, 100.0, 500)
    for k, ax in enumerate(axes):
        ax.plot(t, np.sin(t / (k + 1)), label="x")
        ax.set_title(f"panel {k}", fontsize=7)
        ax.tick_params(labelsize=6)
        ax.legend(fontsize=6)
    axes[-1].set_xlabel("time [s]")
    return fig


def test_the_layout_measures_each_panel_once(monkeypatch):
    from matplotlib.axes import Axes

    measured = []
    real = Axes.get_tightbbox

    def get_tightbbox(self, *a, **k):
        measured.append(self)
        return real(self, *a, **k)

    monkeypatch.setattr(Axes, "get_tightbbox", get_tightbbox)
    fig = plots._finish(_figure())
    assert measured == fig.axes  # TightLayoutEngine with a rect (its default) measures twice


def test_a_finished_figure_is_drawn_once_when_saved(monkeypatch):
    fig = plots._finish(_figure())
    draws = []
    real = Figure.draw

    def draw(self, renderer):
        draws.append(self)
        return real(self, renderer)

    monkeypatch.setattr(Figure, "draw", draw)
    png = plots.save_png(fig)
    assert png.startswith(b"\x89PNG") and draws == [fig]


def test_legible_makes_no_ticks_and_every_text_is_at_least_min_pt_when_drawn():
    fig = _figure()
    plots.legible(fig)
    # at most the first tick of each axis (which the others copy), not one per location
    assert all(len(axis.majorTicks) <= 1 for ax in fig.axes for axis in (ax.xaxis, ax.yaxis))
    fig.canvas.draw()
    texts = [t for t in fig.findobj(lambda a: hasattr(a, "get_fontsize"))
             if t.get_visible() and t.get_text()]
    assert len(texts) > 10 and min(t.get_fontsize() for t in texts) >= plots.MIN_PT


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
def test_the_helper_is_a_single_process(tmp_path):
    """Started for a directory without results, it fails in its own process, delivers nothing,
    and was the only process started."""
    code = (
        "import os, sys\n"
        "from pathlib import Path\n"
        "from ddfuse.evaluation import figure_helper\n"
        "h = figure_helper.Helper(Path(sys.argv[1]))\n"
        "def ppid(p):\n"
        "    try:\n"
        "        return int(Path(f'/proc/{p}/stat').read_text().rsplit(')', 1)[1].split()[1])\n"
        "    except (OSError, IndexError, ValueError):\n"
        "        return None\n"
        "kids = [p for p in os.listdir('/proc') if p.isdigit() and ppid(p) == os.getpid()]\n"
        "print(len(kids), h.results())\n")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "none")], check=True,
                         capture_output=True, text=True, env=os.environ.copy()).stdout.split()
    assert out == ["1", "None"]


def test_the_report_command_and_its_helper_start_without_importlib_metadata():
    """``ddfuse.__version__`` is read when asked for: importlib.metadata (~25-50 ms of
    imports) is not on the report's path, in either process."""
    code = ("import sys; import ddfuse.evaluation.cli, ddfuse.evaluation.figure_helper; "
            "print('importlib.metadata' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["False"]


def test_the_nis_figure_makes_a_panel_only_where_a_row_has_a_sensor():
    from ddfuse.estimation.runner import Trajectory
    from ddfuse.evaluation.consistency import InnovationTable
    from ddfuse.evaluation.results import SavedRun

    t = np.arange(0.0, 50.0, 0.5)
    track = Trajectory(t, np.zeros((len(t), 3)), np.tile(np.eye(3) * 0.01, (len(t), 1, 1)))

    def table(topics):
        k = np.arange(len(t)) % len(topics)
        return InnovationTable(t, np.array(topics)[k], np.full(len(t), "gps"), np.ones(len(t)),
                               np.full(len(t), 2), np.ones(len(t), bool))

    m = {"estimators": {n: {"samples": len(t), "nis": {}} for n in ("a", "b")},
         "data": {"t0": 0.0, "gps_fixes": 0}}
    run = SavedRun(None, m, {"a": track, "b": track}, None, np.zeros(0), np.zeros((0, 2)),
                   np.zeros((0, 2, 2)), np.zeros(0, bool),
                   innovations={"a": table(["/x", "/y", "/z"]), "b": table(["/x"])},
                   log_owner={"a": "a", "b": "b"}, update_s={})
    fig = plots.nis(run)
    # rows a (3 sensors) and b (1) on a 2 x 3 grid: 4 panels, no blank axes beside them
    assert len(fig.axes) == 4 and all(ax.axison for ax in fig.axes)
    assert [ax.get_subplotspec().get_geometry() for ax in fig.axes] == [(2, 3, k, k)
                                                                     for k in (0, 1, 2, 3)]
