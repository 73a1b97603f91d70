"""The report's figures (``evaluation.plots``, ``close_ups``), their captions and their PNGs in
OUTDIR/plots/, drawn in this process and, where a ``figure_helper`` runs, part of them in it.

Which figures the helper draws is worked out in both processes from the run's files alone
(``split``): each figure's cost is estimated from its panel count, and of all the ways to deal
the figures to the two processes the one that ends soonest is taken. The page is the same
whichever process drew a figure."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

from ddfuse.evaluation import close_ups, plots
from ddfuse.evaluation.atomic_files import remove
from ddfuse.evaluation.results import SavedRun, load_run
from ddfuse.evaluation.run_files import PLOTS_DIR
from ddfuse.evaluation.scores import EstimatorScores
from ddfuse.evaluation.verdict import track_kind

# The report's figures, in page order.
FIGURES = ("trajectories", "trajectory_zooms", "trajectories_each", "errors", "nees", "nis",
           "covariance", "latency")

# Estimated CPU seconds of a figure: PER_FIGURE (canvas, PNG) plus PER_PANEL per panel drawn
# times the figure's weight (ticks, labels and titles dominate; the data's points hardly
# count). The weights are measured (docs/results/secondary_speed.md, session 23); only the
# ratios matter to ``split``.
PER_FIGURE = 0.05
PER_PANEL = 0.1
PANEL_WEIGHT = {"trajectories": 2.5, "trajectory_zooms": 1.8, "errors": 1.1, "nees": 2.0,
                "nis": 1.4, "covariance": 1.6, "latency": 1.5}


def panels(run: SavedRun, n_zooms: int) -> dict[str, int]:
    """How many panels each figure of ``run`` draws (0: none, the figure is left out)."""
    names = [n for n, tr in run.tracks.items() if len(tr)]
    truth = run.truth is not None and len(run.truth) > 0
    owners = plots.nis_rows(run)
    return {
        "trajectories": 1,
        "trajectory_zooms": n_zooms,
        "trajectories_each": len(names) if len(run.tracks) > 1 else 0,
        "errors": len(names) * (3 if truth else 2 if len(run.gps_t) else 0),
        "nees": (len([n for n in names if plots.has_covariance(run.tracks[n])])
                 if truth else 0),
        "nis": sum(len(run.innovations[n].groups()) for n in owners),
        "covariance": 2,
        "latency": len([n for n in run.tracks if run.log_owner.get(n, n) == n
                        and len(run.update_s[n])]),
    }


def split(run: SavedRun, n_zooms: int, lead_s: float) -> tuple[list[str], list[str]]:
    """(this process's figures, the helper's), each in page order: of all the ways to deal the
    figures to the two, the one that ends soonest by estimated cost, the helper starting
    ``lead_s`` seconds behind (ties: the first in a fixed order). Deterministic: both
    processes compute it."""
    cost = {name: PER_FIGURE + PER_PANEL * PANEL_WEIGHT.get(name, 1.0) * k
            for name, k in panels(run, n_zooms).items() if k}
    names = [n for n in FIGURES if n in cost]
    best, theirs = math.inf, frozenset()
    for mask in range(2 ** len(names)):  # eight figures at most: 256 ways
        helper = frozenset(n for i, n in enumerate(names) if mask >> i & 1)
        ends = max(sum(cost[n] for n in names if n not in helper),
                   lead_s + sum(cost[n] for n in helper) if helper else 0.0)
        if ends < best - 1e-9:
            best, theirs = ends, helper
    # a figure with no panels is only a note: this process writes it
    return [n for n in FIGURES if n not in theirs], [n for n in FIGURES if n in theirs]


def finish_seconds(e: EstimatorScores) -> float | None:
    """An offline track's seconds outside its per-message updates: its whole-run solve in
    finish() (``finish_s`` where ``ddfuse bench`` measured it; else its runtime less the
    updates' total, the solve and its output calls)."""
    if e.finish_s is not None:
        return e.finish_s
    u, rt = e.update_ms, e.runtime_s
    if rt is None or u is None or u.mean is None or u.n is None:
        return None
    return max(rt - u.mean * u.n / 1e3, 0.0)


def latency_note(name: str, e: EstimatorScores) -> str:
    """The footnote of an offline track's latencies (``ddfuse bench``'s '*')."""
    fin = finish_seconds(e)
    how = "" if fin is None else (
        f": {fin:.3f} s of its {e.runtime_s:.2f} s runtime" if e.finish_s is not None
        else f": {fin:.3f} s of its {e.runtime_s:.2f} s runtime lie outside its "
        "per-message updates")
    return (f"* {name}: the latencies are of its per-message updates; its whole-run solve "
            f"runs once in finish(), in no latency percentile{how}.")


def captions(run: SavedRun, zooms: list | None = None) -> dict[str, str]:
    """The caption of each figure, saying only what this run's figures hold. ``zooms``: the
    close-ups drawn (``close_ups.zoom_windows``)."""
    zooms = close_ups.zoom_windows(run) if zooms is None else zooms
    f = plots.frame(run.summary)
    truth = run.truth is not None and len(run.truth) > 0
    gps = len(run.gps_t) > 0
    withheld = bool(run.gps_withheld.any()) if gps else False
    behind = [w for w, ok in (("the ground truth (grey band)", truth),
                              ("the GPS fixes (grey dots" + ("; red circles: withheld from "
                               "the estimators and used to score them)" if withheld else ")"),
                               gps),
                              ("the landmarks (triangles)", bool(run.landmarks))) if ok]
    start = plots.start_point(run)
    overview = (f"Every estimate in {f['short']} (x, y in m)"
                + (f" with {', '.join(behind[:-1])} and {behind[-1]}" if len(behind) > 1
                   else f" with {behind[0]}" if behind else
                   ", with nothing to compare it with (no ground truth, GPS or landmarks)")
                + (f"; black dot: the start, the earliest position drawn (the first {start[2]} "
                   f"position, {plots.seconds(start[3])} s after the first measurement)"
                   if start else "")
                + "."
                + (" Dashed boxes: the close-ups below (" + ", ".join(z.label for z in zooms)
                   + ")." if zooms else ""))
    zoomed = ("Close-ups of the overview's dashed boxes, each showing only what lies in its "
              "time span: " + "; ".join(f"{z.label}, {z.t0:.0f}-{z.t1:.0f} s: {z.why}"
                                       for z in zooms)
              + ". Grey dots: GPS fixes used; red circles: withheld." if zooms else "")
    each = ("Each estimate on its own, on common axes, "
            + ("over the ground truth (grey band)." if truth else "over the GPS fixes (grey "
               "dots)." if gps else "with no ground truth or GPS to draw behind it."))
    outages = " Grey spans: GPS outages." if run.summary.gps_outages else ""
    bare = plots.without_covariance(run)
    not_drawn = (f" Not drawn: {', '.join(bare)} ({'it has' if len(bare) == 1 else 'they have'}"
                 " no covariance)." if bare else "")
    return {
        "trajectories": overview,
        "trajectory_zooms": zoomed,
        "trajectories_each": each,
        "nees": "Pose NEES against the truth with its 95% chi-square band: a consistent "
                "estimator stays inside about 95% of the time around the dashed expected value; "
                f"above it, the estimator is over-confident, below it, pessimistic.{not_drawn}",
        "nis": "NIS of each innovation per estimator and sensor with the 95% band of its "
               "dimension (dashed)" + ("; red x: rejected by the gate." if any(
                   (~run.innovations[n].accepted).any() for n in run.innovations
                   if len(run.innovations[n])) else "; the gate rejected none."),
        "covariance": "Trace of the position covariance [m²] and heading sigma [deg] of each "
                      f"estimate over time, log scales.{not_drawn}{outages}",
        "latency": "Wall time of each process() call (one per measurement), per estimator."
                   + "".join(" " + latency_note(n, e)
                             for n, e in run.summary.estimators.items()
                             if track_kind(n) == "offline" and e.update_ms
                             and n in run.update_s and len(run.update_s[n])),
    }


def why_no_figure(run: SavedRun, name: str) -> str:
    """The note the report shows in place of figure ``name`` when the run holds nothing for it
    (its plots function returned None)."""
    names = [n for n, tr in run.tracks.items() if len(tr)]
    if not names:
        return f"No {name} figure: no estimator produced a track."
    bare = plots.without_covariance(run)
    dr = "; dead reckoning (dr) fuses none" if "dr" in names else ""
    return {
        "trajectories_each": f"No per-estimator trajectory figure: {names[0]} is the only "
                             "estimate, drawn above.",
        "trajectory_zooms": "No close-ups: no stretch of the tracks to zoom on.",
        "nees": "No NEES figure: the bag has no ground truth to score the covariance against."
                if run.truth is None or not len(run.truth) else
                f"No NEES figure: {', '.join(bare)} {'has' if len(bare) == 1 else 'have'} no "
                "covariance." if len(bare) == len(names) else
                "No NEES figure: no estimate overlaps the ground truth in time.",
        "nis": f"No NIS figure: no estimator logged an innovation, a measurement compared with "
               f"its prediction{dr}.",
        "covariance": f"No covariance figure: {', '.join(bare)} "
                      f"{'has' if len(bare) == 1 else 'have'} no covariance.",
        "latency": "No update-latency figure: no update was timed.",
    }.get(name, f"No {name} figure: nothing to draw.")


def _makers(run: SavedRun, zooms: list, cap: dict[str, str]
            ) -> dict[str, Callable[[], tuple[object, str]]]:
    """Per figure: a function drawing it, returning (Figure or None, caption)."""
    cols = plots.colors(list(run.tracks))

    def nees():
        series, t, dof = plots.nees_inputs(run)
        return plots.nees(series, t, dof, cols) if series else None

    makers = {
        "trajectories": lambda: close_ups.mark_zooms(plots.trajectories(run), run, zooms),
        "trajectory_zooms": lambda: close_ups.trajectory_zooms(run, zooms),
        "trajectories_each": lambda: (plots.trajectories_each(run) if len(run.tracks) > 1
                                      else None),
        "nees": nees,
        "nis": lambda: plots.nis(run),
        "covariance": lambda: plots.covariance(run),
        "latency": lambda: plots.latency(run),
    }
    out: dict[str, Callable[[], tuple[object, str]]] = {
        name: (lambda make=make, name=name: (make(), cap[name]))
        for name, make in makers.items()}
    out["errors"] = lambda: plots.errors(run)  # its caption says what its panels compare
    return out


def draw(run: SavedRun, names: list[str], zooms: list, cap: dict[str, str],
         done: Callable[[str], None] | None = None) -> dict[str, tuple[bytes | None, str]]:
    """{name: (PNG bytes, caption)} of the figures ``names``, each also written to
    OUTDIR/plots/NAME.png; a figure with nothing to show is (None, why not: ``why_no_figure``,
    or the error figure's own reason) and its PNG of an earlier rendering is removed.
    ``done(name)`` after each."""
    pdir = run.outdir / PLOTS_DIR
    pdir.mkdir(exist_ok=True)
    makers = _makers(run, zooms, cap)
    out: dict[str, tuple[bytes | None, str]] = {}
    for name in names:
        fig, caption = makers[name]()
        if fig is not None:
            out[name] = (plots.save_png(fig, pdir / f"{name}.png"), caption)
        else:
            remove(pdir / f"{name}.png")
            out[name] = (None, caption if name == "errors" else why_no_figure(run, name))
        if done:
            done(name)
    return out


def render_helper_share(outdir: Path, lead_s: float) -> dict[str, tuple[bytes | None, str]]:
    """In the helper process (``figure_helper``): its share of ``outdir``'s figures."""
    run = load_run(outdir)
    zooms = close_ups.zoom_windows(run)
    _, theirs = split(run, len(zooms), lead_s)
    return draw(run, theirs, zooms, captions(run, zooms))


def make_figures(run: SavedRun, progress: Callable[[float], None] | None = None,
                 helper=None) -> list[tuple[str, bytes | None, str]]:
    """(name, PNG bytes, caption) of every figure in page order (``draw``), the share
    (``split``) of ``helper`` (a ``figure_helper.Helper`` for this run, or None) drawn by it;
    what it does not deliver is drawn here."""
    zooms = close_ups.zoom_windows(run)
    cap = captions(run, zooms)
    mine, theirs = (split(run, len(zooms), helper.lead_s) if helper is not None
                    else (list(FIGURES), []))
    n = 0

    def done(_name: str) -> None:
        nonlocal n
        n += 1
        if progress:
            progress(n / len(FIGURES))

    got = draw(run, mine, zooms, cap, done)
    if theirs:
        sent = helper.results() or {}
        for name in theirs:
            if name in sent:
                got[name] = sent[name]
                done(name)
        got.update(draw(run, [m for m in theirs if m not in sent], zooms, cap, done))
    return [(name, *got[name]) for name in FIGURES]
