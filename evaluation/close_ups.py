"""Close-ups of a run's trajectories, offline (no script in the report): the stretches worth
a close look (``zoom_windows``: GPS outages, where the estimators disagree most, the largest
error against the truth), drawn side by side (``trajectory_zooms``) and marked on the overview
(``mark_zooms``). Times are seconds since the first measurement, positions metres in the
run's local frame, as in ``evaluation.plots``; docs/design/headline.md says why these."""

from __future__ import annotations

import textwrap
from dataclasses import dataclass

import numpy as np
from ddfuse.evaluation.plots import (
    _STYLE,
    MIN_PT,
    PAGE_W,
    _finish,
    _frame_labels,
    _t0,
    colors,
    subplots,
)
from ddfuse.evaluation.results import SavedRun
from matplotlib.figure import Figure


@dataclass(frozen=True)
class Zoom:
    """A stretch of the run the report draws close up (``trajectory_zooms``): its ``label``
    on the overview, its time span [s since the first measurement] (what is drawn), why it was
    chosen, and for a moment the box about it: ``center`` (x, y) [m] and ``half_m``."""

    label: str
    t0: float
    t1: float
    why: str
    center: tuple[float, float] | None = None
    half_m: float | None = None


ZOOM_HALF_S = 10.0  # a zoom on a moment draws this many seconds either side of it
# ... in a box this many times the distance it is about (a spread, an error), at least 1 m:
# the distance a tenth of the box, large enough to see
ZOOM_SCALE = 5.0
MAX_ZOOMS = 3


def _outside(t: np.ndarray, taken: list[Zoom]) -> np.ndarray:
    """Which stamps ``t`` [s since the first measurement] lie in none of the ``taken`` zooms."""
    ok = np.ones(len(t), bool)
    for z in taken:
        ok &= (t < z.t0) | (t > z.t1)
    return ok


def _spread(run: SavedRun, names: list[str], taken: list[Zoom]
            ) -> tuple[float, float, tuple[float, float]] | None:
    """(s since the first measurement, metres, their mean position) of the largest distance
    between any two tracks at one moment outside the ``taken`` zooms, on a grid over the span
    they share; None with fewer than two tracks or no such moment."""
    trs = [run.tracks[n] for n in names]
    lo, hi = max(tr.t[0] for tr in trs), min(tr.t[-1] for tr in trs)
    if len(trs) < 2 or not hi > lo:
        return None
    g = np.linspace(lo, hi, 2000)
    xy = np.stack([np.column_stack([np.interp(g, tr.t, tr.pose[:, 0]),
                                    np.interp(g, tr.t, tr.pose[:, 1])]) for tr in trs])
    d = np.nan_to_num(np.linalg.norm(xy[:, None] - xy[None], axis=-1).max(axis=(0, 1)))
    d[~_outside(g - _t0(run), taken)] = 0.0
    k = int(np.argmax(d))
    if d[k] <= 0:
        return None
    cx, cy = xy[:, k].mean(axis=0)
    return float(g[k]) - _t0(run), float(d[k]), (float(cx), float(cy))


def _worst_error(run: SavedRun, names: list[str], taken: list[Zoom]
                 ) -> tuple[float, str, float, tuple[float, float]] | None:
    """(metres, track, s since the first measurement, its position) of the largest error of
    any track against the truth (interpolated) outside the ``taken`` zooms; None without."""
    if run.truth is None or len(run.truth) < 2:
        return None
    worst = None
    for n in names:
        tr = run.tracks[n]
        e = np.hypot(np.interp(tr.t, run.truth.t, run.truth.pose[:, 0]) - tr.pose[:, 0],
                     np.interp(tr.t, run.truth.t, run.truth.pose[:, 1]) - tr.pose[:, 1])
        ok = (tr.t >= run.truth.t[0]) & (tr.t <= run.truth.t[-1]) & _outside(
            tr.t - _t0(run), taken) & np.isfinite(e)
        if not ok.any():
            continue
        k = int(np.flatnonzero(ok)[np.argmax(e[ok])])
        if worst is None or e[k] > worst[0]:
            worst = (float(e[k]), n, float(tr.t[k]) - _t0(run),
                     (float(tr.pose[k, 0]), float(tr.pose[k, 1])))
    return worst if worst and worst[0] > 0 else None


def zoom_windows(run: SavedRun) -> list[Zoom]:
    """Up to MAX_ZOOMS stretches worth a close look, in this order: the GPS outages (a
    --gps-holdout window, or a gap in the fixes of 5 s or more), then outside those the moment
    the estimators disagree most, then outside all these the moment of the largest error of
    any track against the truth."""
    t0 = _t0(run)
    names = [n for n, tr in run.tracks.items() if len(tr) > 1]
    if not names:
        return []
    end = max(float(run.tracks[n].t[-1]) for n in names) - t0
    out: list[Zoom] = []

    def add(a: float, b: float, why: str, center=None, half=None) -> None:
        a, b = max(a, 0.0), min(b, end)
        if b > a and len(out) < MAX_ZOOMS:
            out.append(Zoom("ABC"[len(out)], a, b, why, center, half))

    window = str(run.summary.gps_holdout or "").startswith("window")
    for o in run.summary.gps_outages or []:
        add(o.t0 - t0, o.t1 - t0, ("GPS hold-out window" if window else "GPS outage")
            + ": dead reckoning carries each estimate")
    spread = _spread(run, names, out)
    if spread:
        tm, d, center = spread
        add(tm - ZOOM_HALF_S, tm + ZOOM_HALF_S,
            f"the estimators disagree most: {d:.2f} m apart at {tm:.0f} s", center,
            max(ZOOM_SCALE * d, 1.0))
    worst = _worst_error(run, names, out)
    if worst:
        e, n, tm, center = worst
        add(tm - ZOOM_HALF_S, tm + ZOOM_HALF_S,
            f"the largest error against the truth: {n} {e:.2f} m at {tm:.0f} s", center,
            max(ZOOM_SCALE * e, 1.0))
    return out


def _window_xy(run: SavedRun, z: Zoom) -> list[tuple[str, np.ndarray]]:
    """(whose, positions) of the truth, the GPS fixes and each track within zoom ``z``."""
    t0 = _t0(run)
    out = []
    srcs = ([("truth", run.truth.t, run.truth.pose[:, :2])] if run.truth is not None else []) + [
        ("gps", run.gps_t, run.gps_xy.reshape(-1, 2))] + [
        (n, tr.t, tr.pose[:, :2]) for n, tr in run.tracks.items()]
    for whose, t, xy in srcs:
        sel = (t - t0 >= z.t0) & (t - t0 <= z.t1)
        if sel.any():
            out.append((whose, xy[sel]))
    return out


def _zoom_box(run: SavedRun, z: Zoom) -> tuple[float, float, float, float] | None:
    """(x0, x1, y0, y1) [m] of what zoom ``z`` shows: the estimates and the truth in its span
    with a margin (a fix or two far off would make the zoom no zoom); a moment's box about
    it."""
    if z.center is not None:
        (x, y), h = z.center, z.half_m
        return x - h, x + h, y - h, y + h
    pts = [xy for whose, xy in _window_xy(run, z) if whose != "gps"]
    xy = np.concatenate(pts) if pts else np.zeros((0, 2))
    xy = xy[np.isfinite(xy).all(axis=1)]
    if not len(xy):
        return None
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    pad = np.maximum(0.1 * (hi - lo), 0.5)
    return lo[0] - pad[0], hi[0] + pad[0], lo[1] - pad[1], hi[1] + pad[1]


def trajectory_zooms(run: SavedRun, zooms: list[Zoom] | None = None) -> Figure | None:
    """The stretches of ``zoom_windows`` close up, side by side: in each, only what lies in
    its time span (the truth, the fixes used and withheld, every track); None without any."""
    zooms = zoom_windows(run) if zooms is None else zooms
    boxes = [(z, _zoom_box(run, z)) for z in zooms]
    boxes = [(z, b) for z, b in boxes if b]
    if not boxes:
        return None
    cols = colors(list(run.tracks))
    fig, axes = subplots(1, len(boxes), figsize=(PAGE_W, 5.2), squeeze=False)
    xl, yl = _frame_labels(run)
    for ax, (z, box) in zip(axes[0], boxes, strict=True):
        for whose, xy in _window_xy(run, z):
            if whose == "truth":
                ax.plot(xy[:, 0], xy[:, 1], "-", color="k", lw=5, alpha=0.2,
                        solid_capstyle="round", label="ground truth")
            elif whose != "gps":
                ax.plot(xy[:, 0], xy[:, 1], _STYLE.get(whose, "-"), color=cols[whose], lw=1.3,
                        label=whose)
        t = run.gps_t - _t0(run)
        sel = (t >= z.t0) & (t <= z.t1)
        for held, style in ((False, dict(marker=".", color="0.45", ms=4, ls="none")),
                            (True, dict(marker="o", mfc="none", mec="tab:red", ms=6,
                                        ls="none"))):
            k = sel & (run.gps_withheld == held)
            if k.any():
                ax.plot(run.gps_xy[k, 0], run.gps_xy[k, 1], **style)
        ax.set_xlim(box[0], box[1])
        ax.set_ylim(box[2], box[3])
        ax.set_aspect("equal", adjustable="box")  # the box's limits kept, the panel shaped
        ax.set_title(f"{z.label}: {z.t0:.0f}-{z.t1:.0f} s\n"
                     + textwrap.fill(z.why, int(100 / len(boxes))), fontsize=MIN_PT,
                     loc="left")
        ax.set_xlabel(xl)
        ax.grid(True, alpha=0.3)
    axes[0, 0].set_ylabel(yl)
    axes[0, -1].legend(loc="best", fontsize=MIN_PT)
    return _finish(fig)


def mark_zooms(fig: Figure, run: SavedRun, zooms: list[Zoom]) -> Figure:
    """``fig``, the overview (``plots.trajectories``), with the zooms' boxes (``_zoom_box``)
    drawn dashed on its plot, each with its label."""
    from matplotlib.patches import Rectangle

    ax = fig.axes[0]
    for z in zooms:
        box = _zoom_box(run, z)
        if box is None:
            continue
        ax.add_patch(Rectangle((box[0], box[2]), box[1] - box[0], box[3] - box[2], fill=False,
                               ec="k", lw=1.0, ls="--", zorder=5))
        ax.text(box[0], box[3], f" {z.label}", va="bottom", ha="left", fontsize=MIN_PT + 1,
                fontweight="bold", zorder=5)
    return fig
