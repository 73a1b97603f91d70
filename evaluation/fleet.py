"""``ddfuse fleet``: many bags through ``pipeline.run_bag`` on the engine, one summary of them.

``find_bags(paths)`` lists the bags given or found under directories (a ROS1 ``.bag``, a ROS 2
bag directory with ``metadata.yaml``, an ``.mcap`` file); ``output_names`` gives each its own
folder under OUTDIR (two ``x.bag`` in different folders: ``a__x`` and ``b__x``);
``run_fleet`` runs each bag as ``ddfuse run BAG`` would (its config found by
``shipped.config_for``; its results and, unless told not to, its report.html in its folder,
written by the worker) on an ``engine.Engine`` and writes ``OUTDIR/fleet.json`` and
``OUTDIR/fleet.html`` (``evaluation.fleet_page``).

The driver keeps per bag its rows (one per estimator: score, NEES/NIS verdicts, real-time
factor, error), never a track, so its memory does not grow with the bags' length. The score
is the verdict's: position ATE (m, no alignment) where any estimator has one, else the RMS
distance to the withheld GPS fixes (``--gps-holdout``); lower is better, and two scores within
``verdict.TIE`` tie. fleet.json's timing fields (``TIMING_KEYS``) differ between runs, every
other value does not, whichever backend ran the bags. docs/design/fleet.md: layout, reasons.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from ddfuse.estimation.errors import DdfuseError
from ddfuse.evaluation.atomic_files import write_text
from ddfuse.evaluation.engine import Engine
from ddfuse.evaluation.fleet_page import write_fleet_page

__all__ = ["TIMING_KEYS", "BagJob", "find_bags", "output_names", "run_fleet", "run_one",
           "standings"]

FLEET_JSON = "fleet.json"
TIMING_KEYS = frozenset({"rtf", "wall_s", "engine"})  # differ between runs of the same bags
ATE, HOLDOUT = "ate", "holdout"


def _is_ros2_dir(p: Path) -> bool:
    return p.is_dir() and (p / "metadata.yaml").is_file()


def find_bags(paths: Iterable[str | Path]) -> list[Path]:
    """The bags in ``paths``: a path that is a bag as it is (a file, or a ROS 2 directory),
    a directory walked (sorted, depth first) for ``.bag`` and ``.mcap`` files and ROS 2 bag
    directories (not entered). DdfuseError naming the path for one that does not exist or
    holds no bag."""
    bags: list[Path] = []
    for path in map(Path, paths):
        if not path.exists():
            raise DdfuseError(f"{path}: no such bag or directory")
        if path.is_file() or _is_ros2_dir(path):
            bags.append(path)
            continue
        found = []
        for root, dirs, files in os.walk(path):
            here = Path(root)
            bag_dirs = [d for d in dirs if _is_ros2_dir(here / d)]
            found += [here / d for d in bag_dirs]
            dirs[:] = sorted(d for d in dirs if d not in bag_dirs)
            found += [here / f for f in files if f.endswith((".bag", ".mcap"))]
        if not found:
            raise DdfuseError(f"{path}: no bags in it (ROS1 .bag, .mcap, ROS 2 bag "
                              "directories with metadata.yaml)")
        bags += sorted(found)
    return list(dict.fromkeys(bags))


def output_names(bags: Sequence[Path]) -> list[str]:
    """A distinct folder name per bag: its stem, or where stems repeat its path from the
    repeats' common folder with '/' as '__' (``a/x.bag``, ``b/x.bag``: ``a__x``, ``b__x``),
    with the suffix kept where even that repeats (``x.bag``, ``x.mcap``: ``x_bag``,
    ``x_mcap``)."""
    stems = [b.stem for b in bags]
    names = list(stems)
    for stem in set(stems):
        same = [i for i, s in enumerate(stems) if s == stem]
        if len(same) < 2:
            continue
        resolved = [bags[i].resolve() for i in same]
        base = Path(os.path.commonpath([p.parent for p in resolved]))
        for i, p in zip(same, resolved, strict=True):
            names[i] = "__".join(p.relative_to(base).with_suffix("").parts)
    for name in set(names):
        same = [i for i, n in enumerate(names) if n == name]
        if len(same) > 1:
            for i in same:
                names[i] = f"{name}_{bags[i].suffix.lstrip('.') or 'dir'}"
    return names


@dataclass(frozen=True)
class BagJob:
    """One bag's run as a worker receives it (paths, not bytes: the worker reads the bag where
    the driver found it): the bag, its config (None: ``error`` says why), its output folder,
    the estimators (None: the config's default), the GPS hold-out spec and whether the
    worker renders the bag's report.html after its run."""

    name: str
    bag: str
    config: str | None
    outdir: str
    names: tuple[str, ...] | None = None
    holdout: str | None = None
    error: str | None = None
    report: bool = True


def _verdict_of(c) -> str | None:
    return None if c is None else c.verdict


def score_kind(m) -> str | None:
    """What a run is ranked on (as ``verdict`` ranks): ATE where any estimator has one, else
    the GPS hold-out RMSE where any has one, else nothing."""
    ests = m.estimators.values()
    if any(e.ate_rmse_m is not None for e in ests):
        return ATE
    if any(e.gps_holdout_rmse_m is not None for e in ests):
        return HOLDOUT
    return None


def rows_of(m) -> list[dict]:
    """A run's summary (``scores.RunSummary``) as fleet rows, one per estimator."""
    kind = score_kind(m)
    rows = []
    for name, e in m.estimators.items():
        score = (e.ate_rmse_m if kind == ATE else e.gps_holdout_rmse_m if kind == HOLDOUT
                 else None)
        rows.append({"estimator": name, "score": kind, "score_m": score,
                     "ate_rmse_m": e.ate_rmse_m, "gps_holdout_rmse_m": e.gps_holdout_rmse_m,
                     "nees_mean": e.nees_mean, "nees_verdict": _verdict_of(e.nees),
                     "gps_holdout_nees_mean": e.gps_holdout_nees.mean if e.gps_holdout_nees
                     else None, "gps_holdout_nees_verdict": _verdict_of(e.gps_holdout_nees),
                     "nis_verdicts": {k: _verdict_of(s.nis) for k, s in (e.nis or {}).items()},
                     "rtf": e.rtf if e.samples != 0 else None, "error": e.error})
    return rows


def run_one(job: BagJob) -> dict:
    """Run one bag (on a worker): ``{"rows": [...], "error": None | one line, "wall_s",
    "report": True when report.html was rendered}``; the bag's results (metrics.json, tracks,
    run.npz) and report go to ``job.outdir``. An error in the input (no config, a damaged bag,
    a bad config) is the result's ``error``, not an exception; so is a report that could not
    be rendered after a run that could (its rows are kept)."""
    from ddfuse.estimation.config import load_config
    from ddfuse.estimation.errors import BagError
    from ddfuse.evaluation.pipeline import run_bag

    t0 = time.perf_counter()
    if job.error:
        return {"rows": [], "error": job.error, "wall_s": 0.0, "report": False}
    try:
        cfg = load_config(Path(job.config))
        if job.holdout and not cfg.of_kind("gps"):
            raise DdfuseError(f"--gps-holdout {job.holdout}: {job.config} has no gps sensor")
        m = run_bag(job.bag, cfg, job.outdir, names=list(job.names) if job.names else None,
                    holdout=job.holdout)
    except (DdfuseError, BagError, ValueError, OSError) as e:
        return {"rows": [], "error": " ".join(str(e).split()),
                "wall_s": time.perf_counter() - t0, "report": False}
    rows, error = rows_of(m), None
    del m  # the summary is not held while the report renders from the files
    if job.report:
        from ddfuse.evaluation.report import render_report

        try:
            render_report(job.outdir)
        except (DdfuseError, ValueError, OSError) as e:
            error = "report not rendered: " + " ".join(str(e).split())
    return {"rows": rows, "error": error, "wall_s": time.perf_counter() - t0,
            "report": job.report and error is None}


def _tie(a: float, b: float) -> bool:
    from ddfuse.evaluation.verdict import tie

    return tie(a, b)


def bag_standing(rows: list[dict]) -> dict:
    """One bag's ranking by score (best first) and its winner: the best estimator, None where
    the best two tie (``verdict.tie``), with its margin over the runner-up (m and % of the
    runner-up's score)."""
    scored = sorted((r for r in rows if r["score_m"] is not None and not r["error"]),
                    key=lambda r: (r["score_m"], r["estimator"]))
    out = {"ranking": [r["estimator"] for r in scored], "winner": None, "tied": [],
           "margin_m": None, "margin_pct": None}
    if len(scored) < 2:
        out["winner"] = scored[0]["estimator"] if scored else None
        return out
    best, second = scored[0]["score_m"], scored[1]["score_m"]
    if _tie(best, second):
        out["tied"] = [r["estimator"] for r in scored if _tie(best, r["score_m"])]
        return out
    margin = second - best
    out.update(winner=scored[0]["estimator"], margin_m=round(margin, 6),
               margin_pct=round(100.0 * margin / second, 3) if second > 0 else None)
    return out


def standings(bags: list[dict]) -> dict[str, dict]:
    """Across bags, per estimator: the bags it was scored on, those it won outright, those it
    tied for first, and its mean and largest margin (m, %) where it won."""
    table: dict[str, dict] = {}
    for b in bags:
        for name in b.get("ranking", []):
            table.setdefault(name, {"scored": 0, "wins": 0, "tied_first": 0, "margins_m": [],
                                    "margins_pct": []})["scored"] += 1
        for name in b.get("tied", []):
            table[name]["tied_first"] += 1
        if b.get("winner") and b.get("margin_m") is not None:
            t = table[b["winner"]]
            t["wins"] += 1
            t["margins_m"].append(b["margin_m"])
            if b["margin_pct"] is not None:
                t["margins_pct"].append(b["margin_pct"])
    out = {}
    for name in sorted(table, key=lambda n: (-table[n]["wins"], n)):
        t = table[name]
        mm, mp = t.pop("margins_m"), t.pop("margins_pct")
        out[name] = {**t, "mean_margin_m": round(sum(mm) / len(mm), 6) if mm else None,
                     "max_margin_m": max(mm) if mm else None,
                     "mean_margin_pct": round(sum(mp) / len(mp), 3) if mp else None}
    return out


def plan(paths: Iterable[str | Path], outdir: Path, config: Path | None = None,
         names: Sequence[str] | None = None, holdout: str | None = None,
         report: bool = True) -> list[BagJob]:
    """The jobs for the bags in ``paths``: each bag's config (``config`` for all, else
    ``shipped.config_for``'s rule; a bag without one is a job carrying that error), its
    output folder ``outdir/<name>`` and whether its report is rendered."""
    from ddfuse.evaluation.shipped import config_for

    bags = find_bags(paths)
    jobs = []
    for bag, name in zip(bags, output_names(bags), strict=True):
        try:
            cfg, err = str(config_for(bag, config)), None
        except DdfuseError as e:
            cfg, err = None, str(e)
        jobs.append(BagJob(name, str(bag), cfg, str(outdir / name),
                           tuple(names) if names else None, holdout, err, report))
    return jobs


Progress = Callable[[int, int, float | None, str, str | None], None]


def run_fleet(jobs: list[BagJob], outdir: Path, engine: Engine,
              progress: Progress | None = None) -> dict:
    """Run ``jobs`` on ``engine`` (entered by the caller), write ``outdir/fleet.json`` and
    ``outdir/fleet.html`` and return fleet.json's content. ``progress(done, total,
    seconds_left, bag, error)`` after each bag (seconds left: None until a bag is done; the
    mean so far times those left, divided over the workers as they share them)."""
    from ddfuse.evaluation.run_files import REPORT_FILE  # numpy and the writers: not at import

    t0 = time.perf_counter()
    results: dict[int, dict] = {}
    total = len(jobs)
    for o in engine.map(run_one, jobs):
        r = o.value if o.error is None else {"rows": [], "error": o.error, "wall_s": None,
                                             "report": False}
        results[o.index] = r
        if progress is not None:
            done = len(results)
            left = (time.perf_counter() - t0) / done * (total - done)
            progress(done, total, left, jobs[o.index].name, r["error"])
    bags, rows = [], []
    for i, job in enumerate(jobs):
        r = results[i]
        rows += [{"bag": job.name, **row} for row in r["rows"]]
        if r["error"]:
            rows.append({"bag": job.name, "estimator": None, "error": r["error"]})
        bags.append({"bag": job.name, "path": job.bag, "config": job.config,
                     "outdir": job.outdir, "error": r["error"],
                     "report": f"{job.name}/{REPORT_FILE}" if r["report"] else None,
                     "score": next((x["score"] for x in r["rows"]), None),
                     **bag_standing(r["rows"]),
                     "wall_s": None if r["wall_s"] is None else round(r["wall_s"], 3)})
    ran = sum(1 for b in bags if not b["error"])
    doc = {"engine": engine.backend, "bags_total": total, "bags_ran": ran,
           "bags_failed": total - ran, "estimators": standings(bags), "bags": bags,
           "rows": rows, "wall_s": round(time.perf_counter() - t0, 3)}
    outdir.mkdir(parents=True, exist_ok=True)
    write_text(outdir / FLEET_JSON, json.dumps(doc, indent=1) + "\n")
    write_fleet_page(doc, outdir)
    return doc
