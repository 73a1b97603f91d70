"""The report's figures: each function returns a matplotlib Figure, or None where the run holds
nothing for it to draw (a blank figure would only look like an empty result).

Inputs are a run's results (``evaluation.results.SavedRun``: read back from an output directory
by ``load_run``, or built in memory from a ``RunResult`` by ``SavedRun.from_result``) or plain
arrays; nothing here computes a score that metrics.json does not already hold, and nothing
reads or writes files except ``save_png``.

The figures are ``matplotlib.figure.Figure`` objects with their own Agg canvas, made without
pyplot: importing or using this module never selects or changes matplotlib's backend (a
notebook's inline backend stays as it was) and needs no display. In a notebook, a returned
figure shows with ``display(fig)`` (or as a cell's last value); ``save_png`` writes one.

Times on the x axes are seconds since the first measurement (metrics.json
``data.t0``); positions are in the run's local frame (``frame``: ENU about the GPS datum, x east,
y north; else the landmark map's frame, the truth's, or the start pose), in metres. Each track
name has one colour in every figure (``PALETTE``)."""

from __future__ import annotations

import io
import math
import zlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import matplotlib.ticker
import numpy as np
from ddfuse.evaluation import consistency, metrics
from ddfuse.evaluation.atomic_files import write_bytes
from ddfuse.evaluation.figure_text import fit_lines
from ddfuse.evaluation.local_frame import frame  # noqa: F401 - the figures' and report's frame
from ddfuse.evaluation.results import SavedRun
from matplotlib.axis import Axis
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.layout_engine import TightLayoutEngine
from matplotlib.text import Text

DPI = 100
# Figure width [in]: at DPI, the report's content width in a 1 400 px window (1 368 px less
# the scroll bar), so that a figure is shown at its own size and a font of MIN_PT points is
# MIN_PT points on the page; narrower windows scale the page's figures down alike.
PAGE_W = 13.5
MIN_PT = 9.0  # the smallest font in any figure
_STYLE = {"smoother_lagged": "--", "batch": ":"}


# One colour per estimator track, whatever else ran: the same in every figure of every report.
# Red is left to the withheld GPS fixes and rejected innovations, grey to the GPS, black to the
# truth, the landmarks and the start.
PALETTE = {
    "ekf": "tab:blue",
    "ekf_igvc": "tab:orange",
    "ekf_landmark": "tab:cyan",
    "ekf_slam": "tab:olive",
    "smoother": "tab:green",
    "smoother_lagged": "tab:purple",
    "batch": "tab:brown",
    "dr": "tab:pink",
}
# Tracks of other names: a colour chosen by a hash of the name (stable across runs).
_OTHER = ("#1f3f7f", "#b8860b", "#2f6f4f", "#7f3f7f", "#5f5f00", "#00607f", "#8f4f1f",
          "#4f4fbf")


def colors(names: Sequence[str]) -> dict[str, str]:
    """A fixed colour per track name (``PALETTE``), the same in every figure and report
    whichever other tracks are present and in whatever order."""
    return {n: PALETTE.get(n) or _OTHER[zlib.crc32(n.encode()) % len(_OTHER)] for n in names}


def figure(figsize: tuple[float, float]) -> Figure:
    """An empty Figure (``figsize`` in inches) on its own Agg canvas, without pyplot: no
    backend chosen or changed, no display needed, nothing to close."""
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig


def subplots(nrows: int = 1, ncols: int = 1, *, figsize: tuple[float, float], **kw
             ) -> tuple[Figure, object]:
    """``pyplot.subplots`` without pyplot: a ``figure`` and its axes (``Figure.subplots``)."""
    fig = figure(figsize)
    return fig, fig.subplots(nrows, ncols, **kw)


def save_png(fig: Figure, path: Path | None = None) -> bytes:
    """The figure as PNG bytes (also written to ``path`` if given). A figure that pyplot
    manages (one a caller made with ``plt.subplots``) is closed there."""
    raw = io.BytesIO()
    fig.savefig(raw, format="rgba", dpi=DPI)
    if getattr(fig.canvas, "manager", None) is not None:
        import matplotlib.pyplot as plt  # already imported: it made the figure

        plt.close(fig)
    data = _png(raw.getbuffer(), int(fig.get_size_inches()[0] * DPI))
    if path is not None:
        write_bytes(path, data)  # whole or not at all
    return data


def _png(rgba, width: int) -> bytes:
    """PNG bytes of Agg's RGBA buffer (rows of ``width`` pixels, as Agg sizes its canvas: the
    width in inches times DPI, truncated): RGB where every pixel is opaque (the figures' white
    background: the same image, a quarter less to filter and compress), zlib level 3, not
    PIL's 6 (half the encoding time, files within a few %)."""
    from PIL import Image

    a = np.frombuffer(rgba, np.uint8).reshape(-1, width, 4)
    img = Image.fromarray(a, "RGBA")
    if a[:, :, 3].min() == 255:
        img = img.convert("RGB")
    buf = io.BytesIO()
    img.save(buf, format="png", compress_level=3, dpi=(DPI, DPI),
             pnginfo=_png_info())
    return buf.getvalue()


def _png_info():
    """The text chunk matplotlib writes in its PNGs (which software drew it)."""
    from PIL.PngImagePlugin import PngInfo

    info = PngInfo()
    info.add_text("Software", f"Matplotlib version{matplotlib.__version__}, "
                  "https://matplotlib.org/")
    return info


def _plain(v: float, _pos=None) -> str:
    return f"{v:g}"


_SUPERSCRIPT = str.maketrans("-0123456789", "\u207b\u2070\u00b9\u00b2\u00b3\u2074\u2075\u2076"
                             "\u2077\u2078\u2079")


def _decade(v: float, _pos=None) -> str:
    """A decade tick's label: 0.1, 1, 10, 100 as numbers, the others as 10 with a Unicode
    superscript exponent (10⁻³, 10⁴). matplotlib's own labels there are mathtext, whose parser
    costs ~0.3 s of CPU to build in each process that draws one."""
    if not v > 0.0:
        return ""
    e = math.log10(v)
    if abs(e - round(e)) > 1e-6:
        return ""
    e = round(e)
    return f"{v:g}" if -1 <= e <= 2 else "10" + str(e).translate(_SUPERSCRIPT)


def label_log_axis(axis) -> None:
    """Labelled ticks on a log axis whatever its span: the decades when it spans three or
    more (``_decade``), else 1-2-5 steps (under one decade: 1-9 steps, or failing two of those
    in view, round linear steps), printed as plain numbers. No minor ticks: on axes spanning
    many decades they cost most of the drawing time and carry no label."""
    axis.set_minor_locator(matplotlib.ticker.NullLocator())
    lo, hi = sorted(axis.get_view_interval())
    if not (lo > 0 and math.isfinite(hi)):
        return
    if hi / lo >= 1e3:
        axis.set_major_formatter(matplotlib.ticker.FuncFormatter(_decade))
        return
    subs = (1.0, 2.0, 5.0) if hi / lo >= 10 else tuple(float(k) for k in range(1, 10))
    loc = matplotlib.ticker.LogLocator(base=10.0, subs=subs, numticks=30)
    ticks = [v for v in loc.tick_values(lo, hi) if lo <= v <= hi]
    if len(ticks) < 2:
        ticks = [v for v in matplotlib.ticker.MaxNLocator(4).tick_values(lo, hi)
                 if lo <= v <= hi and v > 0]
        loc = matplotlib.ticker.FixedLocator(ticks)
    axis.set_major_locator(loc)
    axis.set_major_formatter(matplotlib.ticker.FuncFormatter(_plain))


def legible(fig: Figure, min_pt: float = MIN_PT) -> None:
    """Every text of ``fig`` (tick labels, titles, legends, annotations) at least ``min_pt``
    points."""
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            # the first tick stands for those the axis makes when it is drawn (they copy its
            # properties): asking for all of them here would make a tick per location now,
            # and set_tick_params would then restyle each
            if axis.majorTicks[0].label1.get_fontsize() < min_pt:
                axis.set_tick_params(which="both", labelsize=min_pt)
    for t in _texts(fig):
        if t.get_fontsize() < min_pt:
            t.set_fontsize(min_pt)


def _texts(artist) -> Iterator[Text]:
    """Every Text under ``artist`` but the tick labels: of an Axis, only its label and offset
    text (its ticks' labels take the size ``legible`` gives the axis)."""
    for child in artist.get_children():
        if isinstance(child, Axis):
            yield child.label
            yield child.offsetText
            continue
        if isinstance(child, Text):
            yield child
        yield from _texts(child)


def _finish(fig: Figure) -> Figure:
    """Label the ticks of log axes (``label_log_axis``), fonts at least MIN_PT (``legible``),
    then lay the figure out tightly, once: no layout engine is left on the figure."""
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            if axis.get_scale() == "log":
                label_log_axis(axis)
    legible(fig)
    # Not fig.tight_layout(): it leaves a placeholder engine on the figure, and savefig then
    # draws the whole figure once more (without rendering) before it renders it. rect=None as
    # fig.tight_layout() passes it: with a rect, the layout measures every panel twice.
    TightLayoutEngine(rect=None).execute(fig)
    return fig


def _t0(run: SavedRun) -> float:
    data = run.summary.data
    if data is not None and data.t0 is not None:
        return float(data.t0)
    starts = [tr.t[0] for tr in run.tracks.values() if len(tr)]
    return float(min(starts)) if starts else 0.0


def has_covariance(tr) -> bool:
    """Whether a track carries a position covariance (dead reckoning's is NaN throughout)."""
    return bool(len(tr)) and bool(np.isfinite(tr.cov[:, 0, 0]).any())


def without_covariance(run: SavedRun) -> list[str]:
    """The run's non-empty tracks that carry no covariance (``has_covariance``)."""
    return [n for n, tr in run.tracks.items() if len(tr) and not has_covariance(tr)]


def _frame_labels(run: SavedRun) -> tuple[str, str]:
    f = frame(run.summary)
    return f"{f['x']} [m]", f"{f['y']} [m]"


def seconds(t: float) -> str:
    """``t`` in s to 0.1 s, without a "-0.0"."""
    return f"{0.0 if abs(t) < 0.05 else t:.1f}"


def start_point(run: SavedRun) -> tuple[float, float, str, float] | None:
    """The earliest position among the truth, the GPS fixes and the tracks: (x, y, whose
    ('ground truth', 'GPS fix' or the track's name), when in seconds since the first
    measurement); None without any."""
    t0 = _t0(run)
    cands = []  # (t, order, x, y, whose): on a tie the truth, then GPS, then the tracks
    if run.truth is not None:
        cands.append((run.truth.t, run.truth.pose[:, :2], "ground truth"))
    if len(run.gps_t):
        cands.append((run.gps_t, run.gps_xy.reshape(-1, 2), "GPS fix"))
    cands += [(tr.t, tr.pose[:, :2], name) for name, tr in run.tracks.items()]
    best = None
    for k, (t, xy, whose) in enumerate(cands):
        ok = np.flatnonzero(np.isfinite(xy).all(axis=1) & np.isfinite(t))
        if len(ok) and (best is None or (t[ok[0]], k) < best[:2]):
            best = (float(t[ok[0]]), k, float(xy[ok[0], 0]), float(xy[ok[0], 1]), whose)
    if best is None:
        return None
    return best[2], best[3], best[4], best[0] - t0


def _shade_outages(ax, run: SavedRun) -> None:
    """Grey spans over the GPS outages (metrics.json ``gps_outages``, absolute stamps)."""
    t0 = _t0(run)
    for o in run.summary.gps_outages or []:
        ax.axvspan(o.t0 - t0, o.t1 - t0, color="0.5", alpha=0.15, lw=0)


def gps_outliers(run: SavedRun, only: str | None = None) -> tuple[np.ndarray, str]:
    """Which GPS fixes (a mask over ``run.gps_t``) an estimator's gate rejected or its robust
    GPS model (``gps.model``) took for outliers, and that estimator: ``only``, else the
    smoother's track when it ran (its lagged output's too), else the first with GPS
    innovations. The fixes are matched by stamp to the innovations not accepted (every one is
    kept, docs/design/urban_gps.md)."""
    none = np.zeros(len(run.gps_t), dtype=bool)
    names = sorted((n for n in run.tracks if n in run.innovations
                    and (only is None or n == only)),
                   key=lambda n: (not n.startswith("smoother"), list(run.tracks).index(n)))
    for name in names:
        table = run.innovations[name]
        gps = table.kind == "gps"
        if not gps.any():
            continue
        t_rej = np.sort(table.t[gps & ~table.accepted])
        if not len(t_rej):
            return none, name
        i = np.clip(np.searchsorted(t_rej, run.gps_t), 1, len(t_rej)) - 1
        j = np.clip(i + 1, 0, len(t_rej) - 1)
        d = np.minimum(np.abs(t_rej[i] - run.gps_t), np.abs(t_rej[j] - run.gps_t))
        return d < 1e-6, name
    return none, ""


def trajectories(run: SavedRun) -> Figure:
    """Every track on the local plane with the truth, the GPS fixes (withheld ones marked) and
    the landmarks."""
    cols = colors(list(run.tracks))
    pts = [tr.pose[:, :2] for tr in run.tracks.values()] + [run.gps_xy.reshape(-1, 2)]
    if run.truth is not None:
        pts.append(run.truth.pose[:, :2])
    xy = np.concatenate(pts) if pts else np.zeros((0, 2))
    xy = xy[np.isfinite(xy).all(axis=1)]
    # Size the plot to the path's shape (equal axes), plus room for the legend on the right.
    span = np.ptp(xy, axis=0) if len(xy) else np.ones(2)
    aspect = float(np.clip((span[0] + 1e-9) / (span[1] + 1e-9), 0.5, 2.0))
    # the page's width: the plot as wide as its height allows, the legend beside it
    height = float(np.clip((PAGE_W - 3.8) / aspect, 5.5, 8.0))
    fig, ax = subplots(figsize=(PAGE_W, height))
    if run.truth is not None and len(run.truth):
        # A wide pale band under the estimates: it stays visible where they follow it closely.
        ax.plot(run.truth.pose[:, 0], run.truth.pose[:, 1], "-", color="k", lw=5, alpha=0.2,
                solid_capstyle="round", label="ground truth")
    if len(run.gps_t):
        used = ~run.gps_withheld
        ax.plot(run.gps_xy[used, 0], run.gps_xy[used, 1], ".", color="0.45", ms=3,
                label=f"GPS fixes used ({used.sum()})")
        if run.gps_withheld.any():
            w = run.gps_withheld
            ax.plot(run.gps_xy[w, 0], run.gps_xy[w, 1], "o", mfc="none", mec="tab:red", ms=5,
                    mew=1.0, label=f"GPS fixes withheld, scored ({w.sum()})")
        out, who = gps_outliers(run)
        if out.any():
            ax.plot(run.gps_xy[out, 0], run.gps_xy[out, 1], "x", color="tab:red", ms=4,
                    mew=0.8, label=f"GPS fixes rejected or taken for outliers by {who} "
                    f"({out.sum()})")
        # and the first EKF's, when the marks above are another estimator's: where a filter
        # and a smoother judged the fixes differently (docs/design/urban_gps.md)
        ekf = next((n for n in run.tracks if n.startswith("ekf") and n != who
                    and n in run.innovations), None)
        out_e = gps_outliers(run, only=ekf)[0] if ekf is not None else out[:0]
        if out_e.any():
            ax.plot(run.gps_xy[out_e, 0], run.gps_xy[out_e, 1], "+", color=cols[ekf], ms=6,
                    mew=0.8, label=f"GPS fixes rejected or taken for outliers by {ekf} "
                    f"({out_e.sum()})")
    if run.landmarks:
        xy = np.array(list(run.landmarks.values()))
        ax.plot(xy[:, 0], xy[:, 1], "^", mfc="none", mec="k", ms=8, label="landmarks")
    for name, tr in run.tracks.items():
        ax.plot(tr.pose[:, 0], tr.pose[:, 1], _STYLE.get(name, "-"), color=cols[name], lw=1.1,
                alpha=0.9, label=name)
    start = start_point(run)
    if start is not None:
        ax.plot(start[0], start[1], "o", color="k", ms=7,
                label=f"start: first {start[2]} position ({seconds(start[3])} s)")
    ax.set_aspect("equal", adjustable="datalim")
    xl, yl = _frame_labels(run)
    ax.set(xlabel=xl, ylabel=yl, title=f"Trajectories in {frame(run.summary)['short']}")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=9)
    return _finish(fig)


def trajectories_each(run: SavedRun) -> Figure:
    """One panel per track with the truth (or the GPS fixes) behind it, on common axes: the
    overview's lines overlap where the estimates agree; here each can be read alone."""
    cols = colors(list(run.tracks))
    names = [n for n, tr in run.tracks.items() if len(tr)]
    # Panels shaped like the path (equal axes): a tall path's side by side (up to 5 in a
    # row), each at most 5.5 in tall, so that the page-wide figure stays within a screen
    pts = [run.tracks[n].pose[:, :2] for n in names] + [run.gps_xy.reshape(-1, 2)]
    if run.truth is not None:
        pts.append(run.truth.pose[:, :2])
    xy = np.concatenate(pts)
    xy = xy[np.isfinite(xy).all(axis=1)]
    span = np.ptp(xy, axis=0) if len(xy) else np.ones(2)
    aspect = float(np.clip((span[0] + 1e-9) / (span[1] + 1e-9), 0.2, 5.0))
    ncol = min(5 if aspect < 0.8 else 3, max(len(names), 1))
    nrow = max(math.ceil(len(names) / ncol), 1)
    row_in = min((PAGE_W - 0.8) / ncol / aspect, 5.5) + 0.6
    fig, axes = subplots(nrow, ncol, figsize=(PAGE_W, row_in * nrow),
                             sharex=True, sharey=True, squeeze=False)
    for ax in axes.flat[len(names):]:
        ax.set_axis_off()
    xl, yl = _frame_labels(run)
    for ax, name in zip(axes.flat, names, strict=False):
        if run.truth is not None and len(run.truth):
            ax.plot(run.truth.pose[:, 0], run.truth.pose[:, 1], "-", color="k", lw=3.5,
                    alpha=0.2)
        elif len(run.gps_t):
            ax.plot(run.gps_xy[:, 0], run.gps_xy[:, 1], ".", color="0.6", ms=2)
        tr = run.tracks[name]
        ax.plot(tr.pose[:, 0], tr.pose[:, 1], "-", color=cols[name], lw=0.9)
        ax.set_title(name, fontsize=10)
        ax.set_aspect("equal", adjustable="box")  # shared axes: the boxes take the aspect
        ax.grid(True, alpha=0.3)
        ax.tick_params(labelsize=8)
    for c in range(ncol):
        # The lowest panel drawn in each column carries the x ticks and label (sharex hides
        # them on all but the last row, which may be empty in this column).
        rows = [r for r in range(nrow) if r * ncol + c < len(names)]
        if rows:
            ax = axes[rows[-1], c]
            ax.tick_params(labelbottom=True)
            ax.set_xlabel(xl, fontsize=8)
    for ax in axes[:, 0]:
        ax.set_ylabel(yl, fontsize=8)
    return _finish(fig)


def _envelope(ax, t, err, sigma3, color, label) -> float:
    """An error series with its ±3σ band; the half-height of the y range it needs: its errors'
    99.5th percentile or the settled envelope (the band's 90th percentile), set on ``ax``."""
    if np.isfinite(sigma3).any():  # no covariance (dead reckoning): no "±3σ" in the legend
        ax.fill_between(t, -sigma3, sigma3, color=color, alpha=0.18, lw=0, label="±3σ")
    ax.plot(t, err, "-", color=color, lw=0.9, label=label)
    ax.axhline(0.0, color="k", lw=0.5)
    # Scale to the errors and the settled envelope, not to the first seconds' huge sigma.
    e, s = np.abs(err[np.isfinite(err)]), sigma3[np.isfinite(sigma3)]
    lim = max(np.percentile(e, 99.5) if len(e) else 0.0, np.percentile(s, 90) if len(s) else 0.0)
    if lim > 0:
        ax.set_ylim(-1.15 * lim, 1.15 * lim)
    return float(lim)


# A track whose error panels need more than this many times the y range of the others' (dead
# reckoning beside fused estimates) keeps its own scale: on the shared one the others would be
# flat lines.
OWN_SCALE = 4.0


def _share_rows(axes, lims: dict[str, list[float]]) -> list[str]:
    """One y range per column for the rows of ``axes`` ({track: per-column half-heights}, in
    row order), but for the tracks that need over OWN_SCALE times the median row's: those keep
    their own, and are returned."""
    names = list(lims)
    need = {n: max(v) for n, v in lims.items()}
    mid = float(np.median(list(need.values())))
    own = [n for n in names if mid > 0 and need[n] > OWN_SCALE * mid] if len(names) > 2 else []
    shared = [k for k, n in enumerate(names) if n not in own]
    for c in range(axes.shape[1]):
        lim = max((lims[names[k]][c] for k in shared), default=0.0)
        if lim > 0:
            for k in shared:
                axes[k, c].set_ylim(-1.15 * lim, 1.15 * lim)
    return own


def _break_wraps(a: np.ndarray) -> np.ndarray:
    """A wrapped angle series (rad) with NaN at each sample where it wrapped, so that a line
    plot breaks there instead of drawing a vertical line across the panel."""
    out = np.array(a, float)
    out[1:][np.abs(np.diff(out)) > math.pi] = np.nan
    return out


def errors(run: SavedRun) -> tuple[Figure | None, str]:
    """Per track, the x (east), y (north) and heading errors against the truth over time with
    the track's own ±3σ envelope; without truth, the x and y differences to every GPS fix
    (envelope from the track's and the fix's covariance). Axes are named by the run's frame
    (``frame``). Returns the figure and its caption; without truth and without GPS fixes there
    is nothing to compare with: (None, the reason)."""
    names = [n for n, tr in run.tracks.items() if len(tr)]
    truth = run.truth is not None and len(run.truth) > 0
    if not names:
        return None, "No error figure: no estimator produced a track."
    if not truth and not len(run.gps_t):
        return None, ("No error figure: the bag has neither ground truth nor GPS fixes, so "
                      "there is nothing to compare the estimates with.")
    cols = colors(names)
    t0 = _t0(run)
    f = frame(run.summary)
    ex, ey = ("east", "north") if f["kind"] == "enu" else ("x", "y")
    where = {"enu": "", "map": " (map)", "truth": " (truth frame)"}.get(f["kind"], " (local)")
    ncol = 3 if truth else 2
    antenna = run.summary.gps_antenna
    lever = (antenna.lever_arm if antenna else None) or (0.0, 0.0)
    delay = float((antenna.delay_s if antenna else None) or 0.0)
    fig, axes = subplots(len(names), ncol, figsize=(PAGE_W, 2.1 * len(names) + 0.8),
                             sharex=True, squeeze=False)
    lims: dict[str, list[float]] = {}
    for r, name in enumerate(names):
        tr = run.tracks[name]
        if truth:
            err = metrics.pose_errors(tr, run.truth, 0.05)
            cov = tr.cov[err.i_est]
            t = err.t - t0
            comps = [(err.dxy[:, 0], cov[:, 0, 0], f"{ex} error{where} [m]", 1.0),
                     (err.dxy[:, 1], cov[:, 1, 1], f"{ey} error{where} [m]", 1.0),
                     (_break_wraps(err.dyaw), cov[:, 2, 2], "heading error [deg]",
                      math.degrees(1))]
        else:
            # the antenna where the fix was taken (its delay and lever arm), as the hold-out
            # score compares it (metrics.antenna_xy)
            xy, inside = metrics.antenna_xy(tr, run.gps_t, lever, delay)
            t = run.gps_t[inside] - t0
            d = xy[inside] - run.gps_xy[inside]
            p = np.stack([np.interp(run.gps_t[inside] - delay, tr.t, tr.cov[:, i, i])
                          for i in (0, 1)])
            r_fix = run.gps_cov[inside]
            comps = [(d[:, 0], p[0] + r_fix[:, 0, 0], f"{ex} − GPS [m]", 1.0),
                     (d[:, 1], p[1] + r_fix[:, 1, 1], f"{ey} − GPS [m]", 1.0)]
        for c, (e, var, ylabel, k) in enumerate(comps):
            ax = axes[r, c]
            with np.errstate(invalid="ignore"):
                s3 = 3.0 * np.sqrt(np.where(var >= 0, var, np.nan)) * k
            lims.setdefault(name, []).append(_envelope(ax, t, e * k, s3, cols[name], name))
            _shade_outages(ax, run)
            ax.set_ylabel(ylabel, fontsize=8)
            ax.grid(True, alpha=0.3)
            if c == 0:
                ax.set_title(name, loc="left", fontsize=10, fontweight="bold")
            if r == 0 and c == ncol - 1:
                ax.legend(loc="upper right", fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("time since the first measurement [s]")
    own = _share_rows(axes, lims)
    _finish(fig)
    outages = " Grey spans: GPS outages." if run.summary.gps_outages else ""
    # the envelope is promised only for the tracks that have one
    bare = [n for n in names if not has_covariance(run.tracks[n])]
    envelope = len(bare) < len(names)
    none = ""
    if bare:
        has = "has" if len(bare) == 1 else "have"
        none = (f" {_listed(bare)} {has} no covariance, so no envelope." if envelope
                else f" No envelope: {_listed(bare)} {has} no covariance.")
    scale = (" Each column's y axis is the same for every estimator" + (
        f", but for {_listed(own)}, whose errors need over {OWN_SCALE:g} times the others' "
        "range (on theirs the others would be flat lines): on its own scale." if own else ".")
        if len(names) > 1 else "")
    if truth:
        caption = (f"Errors against the ground truth (no alignment; x, y in {f['short']})"
                   + (" with each estimator's own ±3σ envelope: a consistent estimator stays "
                      "inside it about 99% of the time." if envelope else ".")
                   + f"{none}{outages}{scale}")
    else:
        which = ("used and withheld" if run.gps_withheld.any()
                 else "all of them fused by the estimators, so not an independent score")
        at = ("" if not delay and not any(lever) else
              ", the estimate taken as the hold-out score takes it: its GPS antenna"
              + (f" (lever arm {lever[0]:g}, {lever[1]:g} m)" if any(lever) else "")
              + (f" {delay:g} s before the fix's stamp (the GPS delay)" if delay else ""))
        caption = ("No ground truth: the difference between each estimate and every GPS fix "
                   f"({which}) in {f['short']}{at}"
                   + ("; the envelope is ±3σ of the estimate's and the fix's covariance "
                      "together." if envelope else ".")
                   + f"{none}{outages}{scale}")
    return fig, caption


def _listed(names: Sequence[str]) -> str:
    """'a', 'a and b', 'a, b and c'."""
    names = list(names)
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def nees(series: Mapping[str, Sequence[np.ndarray]], t: Mapping[str, np.ndarray],
         dof: Mapping[str, int], colours: Mapping[str, str] | None = None) -> Figure:
    """NEES over time per track with its 95% band.

    ``series[name]`` is a list of per-run NEES arrays on the same time grid ``t[name]`` (s); with
    several runs (Monte Carlo) their average is drawn with the band of an N-run average
    (``consistency.chi2_band(dof, N)``). ``dof[name]`` is the NEES dimension."""
    names = [n for n in series if series[n] and min(len(r) for r in series[n])]
    fig, axes = subplots(max(len(names), 1), 1, figsize=(PAGE_W, 1.9 * max(len(names), 1) + 0.8),
                             sharex=True, squeeze=False)
    cols = colours or colors(names)
    for ax, name in zip(axes[:, 0], names, strict=False):
        runs = series[name]
        avg = consistency.average_nees(runs)
        tt = np.asarray(t[name])[:len(avg)]
        lo, hi = consistency.chi2_band(dof[name], len(runs))
        ax.axhspan(lo, hi, color="tab:green", alpha=0.12)
        ax.axhline(dof[name], color="k", lw=0.8, ls="--")
        # The first samples (an exact initial pose) can be tiny, or 0: keep the band in view
        # and draw what lies below the axis on its floor (a 0 would be left out of a log
        # axis, a 1e-26 drawn from far below: the same start drawn two ways)
        bottom = max(min(float(np.nanmin(avg)), lo) * 0.8, lo / 100)
        ax.plot(tt, np.maximum(avg, bottom), "-", color=cols[name], lw=0.8)
        # Judged like the NIS: the fraction of time steps outside the band (of one value, or
        # of an N-run average) and the mean against its expectation.
        outside = float(np.mean((avg < lo) | (avg > hi)))
        verdict = consistency.verdict(outside, float(np.mean(avg)) / dof[name], len(avg))
        runs_txt = f" over {len(runs)} runs" if len(runs) > 1 else ""
        ax.set_title(f"{name}: mean NEES{runs_txt} {np.mean(avg):.2f} (expected {dof[name]}), "
                     f"95% band [{lo:.2f}, {hi:.2f}] shaded, {100 * outside:.0f}% outside: "
                     f"{verdict or 'too few to judge'}", loc="left", fontsize=9,
                     color={"Fail": "tab:red", "Warn": "tab:orange"}.get(verdict, "k"))
        ax.set_yscale("log")
        ax.set_ylim(bottom=bottom)
        ax.set_ylabel("NEES")
        ax.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel("time since the first measurement [s]")
    return _finish(fig)


def _nis_of(run: SavedRun, name: str) -> dict[str, consistency.SensorNis]:
    """Track ``name``'s NIS summary per sensor label (metrics.json ``nis``); {} without one."""
    e = run.summary.estimators.get(name)
    return (e.nis if e else None) or {}


def nis_rows(run: SavedRun) -> list[str]:
    """The tracks ``nis`` draws a row for: those that logged innovations of their own, less
    a track whose NIS summary is another's (the batch's is the smoother's: the same
    innovations, logged twice), as in the report's table."""
    owners = [n for n in run.tracks if run.log_owner.get(n, n) == n and len(run.innovations[n])]
    seen: set[str] = set()
    for n in list(owners):
        key = repr(sorted(_nis_of(run, n).items()))
        if key != repr([]) and key in seen:
            owners.remove(n)
        seen.add(key)
    return owners


def nis(run: SavedRun) -> Figure | None:
    """NIS of every innovation over time: a row per estimator, a panel per sensor and
    measurement kind, with the 95% band of its dimension (dashed); gate-rejected innovations
    marked x. Titles carry the verdict (``ddfuse.evaluation.consistency``). None when no estimator
    logged an innovation (dead reckoning alone)."""
    cols = colors(list(run.tracks))
    owners = nis_rows(run)
    if not owners:
        return None
    groups = {n: run.innovations[n].groups() for n in owners}
    ncol = max((len(g) for g in groups.values()), default=1)
    t0 = _t0(run)
    t_end = max((float(run.innovations[n].t.max()) - t0 for n in owners), default=1.0)
    fig = figure((PAGE_W, 2.6 * max(len(owners), 1) + 0.3))
    # a panel only where a row has a sensor: an empty cell of the grid is left blank
    grid = fig.add_gridspec(max(len(owners), 1), ncol)
    for r, name in enumerate(owners):
        table = run.innovations[name]
        nis_of = _nis_of(run, name)
        for c, (label, sel) in enumerate(groups[name].items()):
            ax = fig.add_subplot(grid[r, c])
            t, v, acc = table.t[sel] - t0, table.nis[sel], table.accepted[sel]
            v = np.maximum(v, 1e-6)  # log axis: an exact zero sits at the floor
            ax.plot(t[acc], v[acc], ".", ms=1.5, color=cols[name], alpha=0.6)
            if (~acc).any():
                ax.plot(t[~acc], v[~acc], "x", ms=4, color="tab:red", label="rejected")
                ax.legend(loc="lower right", fontsize=7)
            for dim in np.unique(table.dim[sel]):
                for b in consistency.chi2_band(int(dim)):
                    ax.axhline(b, color="k", lw=0.7, ls="--")
            ax.set_yscale("log")
            ax.set_xlim(0, t_end)
            sn = nis_of.get(label)
            s = sn.nis if sn else None
            verdict = (s.verdict if s else None) or "too few to judge"
            detail = (f", {100 * s.outside:.0f}% outside, mean/exp {s.ratio:.2f}"
                      if s and s.outside is not None and s.ratio is not None else "")
            # a long topic would run into the next panel's title: break it to the column
            head = fit_lines(f"{name}: {label}", 0.85 * 72 * PAGE_W / ncol, MIN_PT)
            ax.set_title(f"{head}\n{verdict}{detail}", fontsize=MIN_PT,
                         color={"Fail": "tab:red", "Warn": "tab:orange"}.get(verdict, "k"))
            ax.grid(True, alpha=0.3)
            ax.tick_params(labelsize=7)
            if c == 0:
                ax.set_ylabel("NIS")
            if r == len(owners) - 1:
                ax.set_xlabel("time since the first measurement [s]", fontsize=8)
    return _finish(fig)


def covariance(run: SavedRun) -> Figure | None:
    """Trace of each track's position covariance (m^2) and its heading sigma (deg) over time;
    tracks without one (``has_covariance``) are left out, and with none left: None."""
    cols = colors(list(run.tracks))
    t0 = _t0(run)
    drawn = {name: tr for name, tr in run.tracks.items() if has_covariance(tr)}
    if not drawn:
        return None
    fig, (a1, a2) = subplots(2, 1, figsize=(PAGE_W, 6.5), sharex=True)
    for name, tr in drawn.items():
        t = tr.t - t0
        a1.plot(t, tr.cov[:, 0, 0] + tr.cov[:, 1, 1], _STYLE.get(name, "-"), color=cols[name],
                lw=1.0, label=name)
        with np.errstate(invalid="ignore"):
            a2.plot(t, np.degrees(np.sqrt(tr.cov[:, 2, 2])), _STYLE.get(name, "-"),
                    color=cols[name], lw=1.0, label=name)
    a1.set(yscale="log", ylabel="trace of position covariance [m²]",
           title="Covariance over time (watch it converge, and grow in outages)")
    a2.set(yscale="log", ylabel="heading σ [deg]",
           xlabel="time since the first measurement [s]")
    for a in (a1, a2):
        a.grid(True, alpha=0.3, which="major")
        _shade_outages(a, run)
    a1.legend(loc="upper right", fontsize=8, ncol=3)
    return _finish(fig)


def latency(run: SavedRun) -> Figure | None:
    """Histogram of the wall time (ms) of each update (``process`` call) per estimator, one
    row each on a shared log axis, with the median and 99th percentile marked; None when no
    update was timed."""
    cols = colors(list(run.tracks))
    names = [n for n in run.tracks if run.log_owner.get(n, n) == n and len(run.update_s[n])]
    if not names:
        return None
    fig, axes = subplots(max(len(names), 1), 1, figsize=(PAGE_W, 1.5 * max(len(names), 1) + 1),
                             sharex=True, squeeze=False)
    all_ms = np.concatenate([run.update_s[n] * 1e3 for n in names])
    lo = max(float(all_ms[all_ms > 0].min()) if (all_ms > 0).any() else 1e-3, 1e-4)
    bins = np.logspace(math.log10(lo), math.log10(max(float(all_ms.max()), lo * 10)), 80)
    for ax, n in zip(axes[:, 0], names, strict=False):
        ms = run.update_s[n] * 1e3
        p50, p99 = np.percentile(ms, [50, 99])
        # One filled step outline, not a bar patch per bin (80 patches a row cost more than
        # the rest of the figure); it covers the same pixels.
        counts, _ = np.histogram(np.maximum(ms, lo), bins=bins)
        ax.stairs(counts, bins, fill=True, color=cols[n], alpha=0.75, lw=0)
        for q, ls in ((p50, "-"), (p99, "--")):
            ax.axvline(q, color="k", lw=0.9, ls=ls)
        ax.set_yscale("log")
        ax.set_title(f"{n}: p50 {p50:.3f} ms (solid), p99 {p99:.3f} ms (dashed), max "
                     f"{ms.max():.2f} ms, {len(ms)} updates", loc="left", fontsize=9)
        ax.set_ylabel("updates", fontsize=8)
        ax.grid(True, alpha=0.3)
    axes[-1, 0].set(xscale="log", xlabel="update wall time [ms]")
    return _finish(fig)


def nees_inputs(run: SavedRun) -> tuple[dict, dict, dict]:
    """(series, t, dof) for ``nees`` from one run against its truth: one run per track."""
    series, t, dof = {}, {}, {}
    if run.truth is None:
        return series, t, dof
    for name, tr in run.tracks.items():
        # in the estimator's own error coordinates, as metrics.json scores it (older runs: world)
        e = run.summary.estimators.get(name)
        pe = e.pose_error if e else "world"
        ns = metrics.nees_series(tr, run.truth, 0.05, pe)
        if len(ns.value):
            series[name], t[name] = [ns.value], ns.t - _t0(run)
            dof[name] = int(np.round(np.mean(ns.dof)))
    return series, t, dof
