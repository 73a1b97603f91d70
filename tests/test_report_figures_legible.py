"""The report's figures as a reader sees them: as wide as the page (shown at their own size),
no font under 9 pt, the error panels on one y scale per column, and close-ups on the
stretches that matter (an outage, where the estimators disagree most, the largest error)."""

from __future__ import annotations

import numpy as np
import pytest
from ddfuse.estimation.runner import Trajectory
from ddfuse.evaluation import close_ups, plots, report
from ddfuse.evaluation.consistency import InnovationTable
from ddfuse.evaluation.results import SavedRun
from matplotlib.text import Text

T = np.arange(0.0, 100.0, 0.1)


def _track(offset_y: float, bump_at: float | None = None, bump: float = 0.0,
           sigma: float = 0.1) -> Trajectory:
    y = np.full_like(T, offset_y)
    if bump_at is not None:
        y += bump * np.exp(-0.5 * ((T - bump_at) / 2.0) ** 2)
    pose = np.column_stack([T, y, np.zeros_like(T)])
    return Trajectory(T, pose, np.tile(np.diag([sigma**2, sigma**2, 1e-4]), (len(T), 1, 1)))


def _run(tracks: dict[str, Trajectory], outage: tuple[float, float] | None = None,
         holdout: str | None = None) -> SavedRun:
    gps_t = np.arange(0.0, 100.0, 1.0)
    if outage:
        gps_t = gps_t[(gps_t < outage[0]) | (gps_t > outage[1])]
    gps_xy = np.column_stack([gps_t, np.zeros_like(gps_t)])
    m = {"estimators": {n: {"samples": len(T), "nis": {}} for n in tracks},
         "data": {"t0": 0.0, "gps_fixes": len(gps_t)}, "gps_holdout": holdout,
         "gps_outages": [{"t0": outage[0], "t1": outage[1]}] if outage else []}
    table = InnovationTable(gps_t, np.full(len(gps_t), "/fix"), np.full(len(gps_t), "gps"),
                            np.ones(len(gps_t)), np.full(len(gps_t), 2),
                            np.ones(len(gps_t), bool))
    return SavedRun(None, m, tracks, _track(0.0), gps_t, gps_xy,
                    np.tile(np.eye(2), (len(gps_t), 1, 1)), np.zeros(len(gps_t), bool),
                    innovations={n: table for n in tracks}, log_owner={n: n for n in tracks},
                    update_s={n: np.full(50, 1e-4) for n in tracks})


@pytest.fixture(scope="module")
def run() -> SavedRun:
    return _run({"ekf": _track(0.05, 30.0, 0.4), "smoother": _track(-0.02),
                 "batch": _track(0.01, 70.0, -0.2)}, outage=(45.0, 55.0),
                holdout="window:45:55")


def test_every_figure_is_page_wide_and_no_font_is_under_9_pt(run):
    figures = [(name, fig) for name, fig in (
        ("trajectories", plots.trajectories(run)), ("zooms", close_ups.trajectory_zooms(run)),
        ("each", plots.trajectories_each(run)), ("errors", plots.errors(run)[0]),
        ("nees", plots.nees(*plots.nees_inputs(run))), ("nis", plots.nis(run)),
        ("covariance", plots.covariance(run)), ("latency", plots.latency(run)))]
    for name, fig in figures:
        assert fig is not None, name
        fig.canvas.draw()  # the ticks as drawn
        assert fig.get_size_inches()[0] == pytest.approx(plots.PAGE_W), name
        small = {(t.get_text(), t.get_fontsize()) for t in fig.findobj(Text)
                 if t.get_visible() and t.get_text() and t.get_fontsize() < plots.MIN_PT}
        assert not small, (name, sorted(small)[:5])
    # and the page shows them at that width: the CSS width of the content, not less
    assert plots.PAGE_W * plots.DPI <= 1400 - 32 and "figure img{width:100%" in report._CSS


def test_the_error_panels_share_each_columns_y_axis(run):
    fig, caption = plots.errors(run)
    axes = np.array(fig.axes).reshape(3, 3)
    for c in range(3):
        assert len({axes[r, c].get_ylim() for r in range(3)}) == 1, c
    # the ekf's bump of 0.4 m sets the north column's scale for all
    assert axes[1, 1].get_ylim()[1] >= 0.4
    assert "Each column's y axis is the same for every estimator." in caption


def test_a_track_far_off_the_others_keeps_its_own_scale_and_the_caption_says_so():
    far = _run({"ekf": _track(0.05), "smoother": _track(-0.02), "batch": _track(0.01),
                "dr": _track(0.0, 50.0, 30.0)})
    fig, caption = plots.errors(far)
    axes = np.array(fig.axes).reshape(4, 3)
    assert axes[3, 1].get_ylim()[1] > 30 and axes[0, 1].get_ylim()[1] < 1
    assert len({axes[r, 1].get_ylim() for r in range(3)}) == 1
    assert "but for dr, whose errors need over 4 times the others' range" in caption


def test_close_ups_on_the_outage_the_largest_disagreement_and_the_largest_error(run):
    zooms = close_ups.zoom_windows(run)
    assert [z.label for z in zooms] == ["A", "B", "C"]
    a, b, c = zooms
    assert (a.t0, a.t1) == (45.0, 55.0) and a.why.startswith("GPS hold-out window")
    # ekf's 0.4 m bump at 30 s is where the tracks are furthest apart, and the worst error
    assert b.why.startswith("the estimators disagree most") and abs(
        (b.t0 + b.t1) / 2 - 30.0) < 0.2
    assert b.center[0] == pytest.approx(30.0, abs=0.2) and b.half_m >= 5 * 0.4
    # the largest error, ekf's at 30 s, is B's: C is the largest outside A and B, batch's
    assert c.why.startswith("the largest error against the truth: batch 0.19 m at 70 s")
    fig = close_ups.trajectory_zooms(run, zooms)
    assert len(fig.axes) == 3
    assert fig.axes[1].get_xlim() == pytest.approx((b.center[0] - b.half_m,
                                                    b.center[0] + b.half_m))
    overview = close_ups.mark_zooms(plots.trajectories(run), run, zooms)
    labels = [t.get_text().strip() for t in overview.axes[0].texts]
    assert labels == ["A", "B", "C"] and len(overview.axes[0].patches) == 3
    cap = report.captions(run, zooms)
    assert "A, 45-55 s: GPS hold-out window" in cap["trajectory_zooms"]
    assert "Dashed boxes: the close-ups below (A, B, C)." in cap["trajectories"]
