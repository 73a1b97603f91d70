"""ddfuse from a notebook: importing it leaves matplotlib's backend alone, the report's figures
come from an in-memory RunResult as from a saved run, and ``score(result)`` scores each
estimator's NEES in its own coordinates, as ``run_bag`` does."""

from __future__ import annotations

import importlib.util
import io
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
from ddfuse.estimation.config import load_config
from ddfuse.evaluation import pipeline, plots
from ddfuse.evaluation.results import SavedRun, load_run
from matplotlib.figure import Figure

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data"
PNG = b"\x89PNG\r\n\x1a\n"

# Backends that need no display and are not Agg: the notebook's inline one where installed.
BACKENDS = ["pdf"] + (["module://matplotlib_inline.backend_inline"]
                      if importlib.util.find_spec("matplotlib_inline") else [])


@pytest.fixture(scope="module")
def husky(tmp_path_factory):
    """run_bag on the sample (ekf, smoother and its lagged track, a 20 s hold-out), with the
    RunResult it scored: (cfg, outdir, summary, result)."""
    cfg = load_config(DATA / "sample_husky.yaml")
    out = tmp_path_factory.mktemp("nb") / "out"
    seen = []
    real = pipeline.score
    mp = pytest.MonkeyPatch()
    mp.setattr(pipeline, "score", lambda result, *a, **k: seen.append(result) or
               real(result, *a, **k))
    try:
        m = pipeline.run_bag(DATA / "sample_husky.bag", cfg, out,
                             names=["ekf", "smoother", "smoother_lagged"],
                             holdout="window:40:60")
    finally:
        mp.undo()
    [result] = seen
    return cfg, out, m, result


@pytest.mark.parametrize("backend", BACKENDS)
def test_importing_and_plotting_leave_the_backend_alone(husky, backend):
    _, out, _, _ = husky
    code = (
        "import sys, matplotlib\n"
        "import ddfuse.evaluation.plots, ddfuse.evaluation.report, ddfuse.evaluation.results\n"
        "import ddfuse.evaluation.plot_sim\n"
        "before = matplotlib.get_backend()\n"
        "pyplot = 'matplotlib.pyplot' in sys.modules\n"
        "run = ddfuse.evaluation.results.load_run(sys.argv[1])\n"
        "png = ddfuse.evaluation.plots.save_png(ddfuse.evaluation.plots.trajectories(run))\n"
        "print(before, pyplot, matplotlib.get_backend(), png[:8] == b'\\x89PNG\\r\\n\\x1a\\n')\n")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env.update(MPLBACKEND=backend, PYTHONPATH=os.pathsep.join(
        [str(ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])))
    p = subprocess.run([sys.executable, "-c", code, str(out)], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    before, pyplot, after, png = p.stdout.split()
    assert before == backend and after == backend  # not switched to Agg
    assert pyplot == "False"  # ddfuse never imports pyplot
    assert png == "True"  # rendered headless all the same


def test_score_takes_each_estimators_pose_error_from_the_result(husky):
    _, _, m, result = husky
    mine = pipeline.score(result)  # no pose_errors: from the result
    for name in m.estimators:
        assert mine.estimators[name].pose_error == m.estimators[name].pose_error
    assert m.estimators["ekf"].pose_error == "se2"
    assert m.estimators["smoother"].pose_error == "world"
    ekf = m.estimators["ekf"].nees_mean
    assert mine.estimators["ekf"].nees_mean == ekf
    # scored in world coordinates (the old default) it differs: the test can tell
    world = pipeline.score(result, pose_errors={"ekf": "world"})
    assert world.estimators["ekf"].nees_mean != ekf


def _figures(run: SavedRun) -> dict[str, bytes]:
    """PNG bytes of every figure of the report (as report.make_figures makes them)."""
    series, t, dof = plots.nees_inputs(run)
    figs = {"trajectories": plots.trajectories(run),
            "trajectories_each": plots.trajectories_each(run),
            "errors": plots.errors(run)[0],
            "nees": plots.nees(series, t, dof, plots.colors(list(run.tracks))),
            "nis": plots.nis(run), "covariance": plots.covariance(run),
            "latency": plots.latency(run)}
    for fig in figs.values():
        assert isinstance(fig, Figure)
    return {name: plots.save_png(fig) for name, fig in figs.items()}


@pytest.mark.slow
def test_figures_from_an_in_memory_result_equal_the_saved_ones(husky, tmp_path):
    cfg, out, _, result = husky
    disk = load_run(out)
    mem = SavedRun.from_result(result, cfg=cfg)
    assert mem.outdir is None and not list(tmp_path.iterdir())
    # the same inputs: run.npz's arrays, the tracks (the CSV keeps 10 digits), the metrics
    for f in ("gps_t", "gps_xy", "gps_cov", "gps_withheld"):
        assert np.array_equal(getattr(mem, f), getattr(disk, f)), f
    assert mem.landmarks == disk.landmarks and mem.log_owner == disk.log_owner
    assert mem.config_text == disk.config_text and "heading_offset" in mem.config_text
    assert set(mem.innovations) == set(disk.innovations) == set(mem.update_s)
    for name in mem.innovations:
        a, b = mem.innovations[name], disk.innovations[name]
        for f in ("t", "sensor", "kind", "nis", "dim", "accepted"):
            assert np.array_equal(getattr(a, f), getattr(b, f)), (name, f)
        assert np.array_equal(mem.update_s[name], disk.update_s[name])
    assert list(mem.tracks) == list(disk.tracks)
    for name in mem.tracks:
        for f in ("t", "pose", "cov"):
            np.testing.assert_allclose(getattr(mem.tracks[name], f),
                                       getattr(disk.tracks[name], f), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(mem.truth.pose, disk.truth.pose, rtol=1e-9, atol=1e-12)
    # scored with run's GPS antenna model (the sample config's 0.2 s delay) too
    assert mem.summary.gps_antenna.delay_s == cfg.of_kind("gps")[0].delay == 0.2
    for key in ("estimators", "data", "initial_pose", "gps_outages", "gps_antenna"):
        assert mem.metrics[key] == disk.metrics[key], key
    # Fed the same tracks, the same figures byte for byte: nothing else differs.
    b = _figures(disk)
    a = _figures(replace(mem, tracks=disk.tracks, truth=disk.truth))
    for name in a:
        assert a[name].startswith(PNG) and a[name] == b[name], name
    # With its own (unrounded) tracks: at most a few pixels one level apart (the CSV's 10
    # digits move an antialiased edge of the error lines).
    for name, png in _figures(mem).items():
        x, y = (matplotlib.image.imread(io.BytesIO(d)) for d in (png, b[name]))
        assert x.shape == y.shape, name
        diff = np.abs(x.astype(float) - y.astype(float)).max(axis=-1) * 255
        assert diff.max() <= 1.001 and np.count_nonzero(diff) <= 20, name


def test_notebook_flow_without_a_config(husky):
    """``SavedRun.from_result(result)`` alone (no metrics, no config): scored on the fly, the
    frame and times from the stream; a figure displays as a notebook shows it."""
    _, _, m, result = husky
    run = SavedRun.from_result(result)
    assert run.summary.estimators["ekf"].nees_mean == m.estimators["ekf"].nees_mean
    assert plots.frame(run.summary)["kind"] == "enu"
    assert run.summary.data.t0 == m.data.t0
    fig = plots.trajectories(run)
    assert isinstance(fig, Figure)
    pylabtools = pytest.importorskip("IPython.core.pylabtools")
    assert pylabtools.print_figure(fig, "png").startswith(PNG)  # what display(fig) shows


def test_from_result_shows_the_config_that_ran_whatever_it_was_parsed_from(husky, tmp_path):
    from ddfuse.estimation.config import load_config, parse_config_text

    _, _, _, result = husky
    text = (DATA / "sample_husky.yaml").read_text()
    # parsed from text under a label that is no file: shown, not read from disk
    run = SavedRun.from_result(result, cfg=parse_config_text(text, "my robot's config"))
    assert run.config_text == text
    # loaded from a file that is changed afterwards: what ran, not what the file holds now
    p = tmp_path / "c.yaml"
    p.write_text(text)
    cfg = load_config(p)
    p.write_text("# edited later\n")
    assert SavedRun.from_result(result, cfg=cfg).config_text == text
