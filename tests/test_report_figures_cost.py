"""What a report figure costs beyond its drawing: ``plots._finish`` lays a figure out once and
leaves no layout engine behind (else ``savefig`` draws the whole figure a second time before
rendering it), ``plots.legible`` sizes the tick labels without making the ticks, and the
figures' helper is one process (no resource tracker beside it)."""

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
