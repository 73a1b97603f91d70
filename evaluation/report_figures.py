"""The report's figures (``evaluation.plots``, ``close_ups``), their captions and their PNGs in
OUTDIR/plots/, drawn in this process and, where a ``figure_helper`` runs, part of them in it.

Which figures the helper draws is worked out in both processes from the run's files alone
(``split``): each figure's cost is estimated from its panel count, and the figures are dealt,
largest first, to the process that would finish first. The page is the same whichever process
drew a figure."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ddfuse.evaluation import close_ups, plots
from ddfuse.evaluation.atomic_files import remove
from ddfuse.evaluation.figure_helper import Helper
from ddfuse.evaluation.results import SavedRun, load_run
from ddfuse.evaluation.run_files import PLOTS_DIR

# The report's figures, in page order.
FIGURES = ("trajectories", "trajectory_zooms", "trajectories_each", "errors", "nees", "nis",
           "covariance", "latency")

# Estimated CPU seconds of a figure: PER_FIGURE (canvas, layout, PNG) plus PER_PANEL per panel
# drawn (ticks, labels and titles dominate; the data's points hardly count:
# docs/results/secondary_speed.md). Only their ratios matter to ``split``.
PER_FIGURE = 0.1
PER_PANEL = 0.1
PANEL_WEIGHT = {"trajectories": 2.0, "covariance": 1.5, "latency": 2.0, "nis": 1.4}


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
    """(this process's figures, the helper's), each in page order: the figures dealt largest
    estimated cost first (ties in page order) to whichever process has the least so far,
    the helper starting ``lead_s`` seconds behind. Deterministic: both processes compute it."""
    cost = {name: PER_FIGURE + PER_PANEL * PANEL_WEIGHT.get(name, 1.0) * k
            for name, k in panels(run, n_zooms).items() if k}
    load = [0.0, lead_s]
    share: list[list[str]] = [[], []]
    for name in sorted(cost, key=lambda n: (-cost[n], FIGURES.index(n))):
        i = 0 if load[0] <= load[1] else 1
        share[i].append(name)
        load[i] += cost[name]
    # a figure with no panels is only a note: this process writes it
    none = [n for n in FIGURES if n not in cost]
    return ([n for n in FIGURES if n in share[0] or n in none],
            [n for n in FIGURES if n in share[1]])


def _captions(run: SavedRun, zooms: list) -> dict[str, str]:
    # imported here: report imports this module (the helper needs only the captions)
    from ddfuse.evaluation.report import captions

    return captions(run, zooms)


def _why_not(run: SavedRun, name: str) -> str:
    from ddfuse.evaluation.report import why_no_figure

    return why_no_figure(run, name)


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
            out[name] = (None, caption if name == "errors" else _why_not(run, name))
        if done:
            done(name)
    return out


def render_helper_share(outdir: Path, lead_s: float) -> dict[str, tuple[bytes | None, str]]:
    """In the helper process (``figure_helper``): its share of ``outdir``'s figures."""
    run = load_run(outdir)
    zooms = close_ups.zoom_windows(run)
    _, theirs = split(run, len(zooms), lead_s)
    return draw(run, theirs, zooms, _captions(run, zooms))


def make_figures(run: SavedRun, progress: Callable[[float], None] | None = None,
                 helper: Helper | None = None) -> list[tuple[str, bytes | None, str]]:
    """(name, PNG bytes, caption) of every figure in page order (``draw``), the ``helper``'s
    share (``split``) drawn by it; what it does not deliver is drawn here."""
    zooms = close_ups.zoom_windows(run)
    cap = _captions(run, zooms)
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
