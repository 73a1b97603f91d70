"""A run's saved results read back: ``load_run`` (what ``ddfuse report`` renders) and
``SavedRun``, also built in memory from a ``RunResult``. The files and their layout:
``ddfuse.evaluation.run_files``, which writes them.

In a notebook, ``SavedRun.from_result(result)`` gives the same ``SavedRun`` for an in-memory
``RunResult`` (``ddfuse.estimation.runner.run``) without writing anything, so the figures of
``ddfuse.evaluation.plots`` come straight from it::

    from ddfuse.evaluation import plots
    from ddfuse.evaluation.results import SavedRun

    saved = SavedRun.from_result(result, cfg=cfg)   # scores it (pipeline.score) unless given
    plots.trajectories(saved)                       # a Figure: display(fig), or plots.save_png
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from ddfuse.estimation import heading_survey
from ddfuse.estimation.errors import DdfuseError
from ddfuse.estimation.runner import RunResult, Trajectory
from ddfuse.evaluation.consistency import InnovationTable
from ddfuse.evaluation.export import read_csv
from ddfuse.evaluation.run_files import (
    INCOMPLETE,
    INNOV_FIELDS,
    METRICS_FILE,
    RUN_FILE,
    TRUTH,
    config_text_of,
    incomplete_note,
    run_arrays,
)
from ddfuse.evaluation.scores import DataFacts, RunSummary


class ResultsError(DdfuseError):
    """An output directory that does not hold a run's results (or holds damaged ones)."""


@dataclass
class SavedRun:
    """A run's results as read back from its output directory (see module docstring), or
    built in memory from a RunResult (``from_result``; ``outdir`` None). ``summary``: the
    scores (metrics.json, ``scores.RunSummary``); ``metrics``: the same as metrics.json's
    dictionary."""

    outdir: Path | None
    summary: RunSummary  # a metrics.json dictionary given is read into one
    tracks: dict[str, Trajectory]
    truth: Trajectory | None
    gps_t: np.ndarray
    gps_xy: np.ndarray
    gps_cov: np.ndarray
    gps_withheld: np.ndarray
    landmarks: dict[str, tuple[float, float]] = field(default_factory=dict)
    innovations: dict[str, InnovationTable] = field(default_factory=dict)  # track -> table
    log_owner: dict[str, str] = field(default_factory=dict)  # track -> first track of its log
    update_s: dict[str, np.ndarray] = field(default_factory=dict)
    config_text: str | None = None

    def __post_init__(self):
        if isinstance(self.summary, dict):  # a metrics.json dictionary, e.g. a hand-built one
            self.summary = RunSummary.from_json(self.summary)

    @property
    def metrics(self) -> dict:
        """metrics.json's dictionary (``summary.to_json()``, built anew at each call)."""
        return self.summary.to_json()

    @classmethod
    def from_result(cls, result: RunResult, metrics: RunSummary | dict | None = None, *,
                    cfg=None, config_text: str | None = None) -> SavedRun:
        """What ``load_run`` would read back had ``result`` been saved, without touching disk:
        the arrays ``save_run`` would write into run.npz, read as ``load_run`` reads them, and
        the tracks and truth as they are (the saved CSV rounds to 10 digits). ``outdir`` is
        None.

        ``metrics``: the run's scores (a RunSummary, or the metrics.json dictionary ``ddfuse
        run`` writes); by default ``ddfuse.evaluation.pipeline.score(result)`` with the data
        facts the figures read (the local frame, t0): all of them with the run's config ``cfg``
        (``pipeline.data_facts``, and the initial pose), else the stream's start, datum and
        landmarks. ``config_text``: shown by the report (default: ``cfg``'s file)."""
        if metrics is None:
            metrics = _score(result, cfg)
        elif isinstance(metrics, dict):
            metrics = RunSummary.from_json(metrics)
        if config_text is None and cfg is not None:
            config_text = config_text_of(cfg)
        tracks = {name: r.trajectory for name, r in result.runs.items() if len(r.trajectory)}
        return _from_arrays(None, metrics, run_arrays(result, config_text), tracks,
                            result.truth)


def _score(result: RunResult, cfg) -> RunSummary:
    """The scores of an in-memory run, as far as ``SavedRun.from_result`` needs them (see
    there)."""
    from ddfuse.evaluation import pipeline  # it imports this module

    m = pipeline.score(result, cfg=cfg)  # the GPS antenna (lever arm, delay) as run scores it
    if cfg is not None:
        surveys = pipeline.offset_surveys(result, cfg)
        ip = cfg.initial_pose
        return replace(m, data=pipeline.data_facts(result, cfg, surveys),
                       warnings=heading_survey.config_warnings(surveys, cfg),
                       initial_pose=("first ground-truth pose" if ip == "ground_truth"
                                     else list(ip) if ip else None))
    st = result.stream
    return replace(m, data=DataFacts(t0=st.t0, t1=st.t1, landmarks=len(st.landmarks),
                                     datum=list(st.datum) if st.datum else None))


def load_run(outdir: str | Path) -> SavedRun:
    """Read the results in ``outdir``; ResultsError naming the path if they are absent,
    unreadable, or incomplete (the INCOMPLETE marker of a run that did not finish writing
    them: ``run_files.writing_run``)."""
    outdir = Path(outdir)
    note = incomplete_note(outdir)
    if note is not None:
        raise ResultsError(f"{outdir}: incomplete run results ({INCOMPLETE}: {note}); "
                           f"run 'ddfuse run -o {outdir}' again")
    mpath, npath = outdir / METRICS_FILE, outdir / RUN_FILE
    for p in (mpath, npath):
        if not p.is_file():
            what = "not a directory" if not outdir.is_dir() else f"no {p.name}"
            raise ResultsError(f"{p}: no saved run results ({what}; 'ddfuse run -o {outdir}' "
                               f"writes them)")
    try:
        summary = RunSummary.from_json(json.loads(mpath.read_text()))
        z = np.load(npath, allow_pickle=False)
        meta = json.loads(str(z["meta"]))
        tracks = {}
        for name in meta["tracks"]:
            p = outdir / f"{name}.csv"
            if p.is_file():
                tracks[name] = read_csv(p)
        tpath = outdir / f"{TRUTH}.csv"
        truth = read_csv(tpath) if tpath.is_file() else None
        return _from_arrays(outdir, summary, z, tracks, truth)
    except (OSError, EOFError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as e:
        raise ResultsError(f"{outdir}: damaged run results ({type(e).__name__}: {e})") from None


def _from_arrays(outdir: Path | None, summary: RunSummary, z, tracks: dict[str, Trajectory],
                 truth: Trajectory | None) -> SavedRun:
    """A SavedRun from run.npz's arrays ``z`` (an NpzFile or the dictionary ``run_arrays``
    gives) and the tracks and truth."""
    meta = json.loads(str(z["meta"]))
    owner = meta["log_owner"]
    tables = {}
    for name in meta["tracks"]:
        key = owner[name]
        folded = {}
        if f"innov/{key}/folded" in z:  # absent from results written before they were saved
            folded = {(str(a), str(b), int(c)): v
                      for (a, b, c), v in json.loads(str(z[f"innov/{key}/folded"]))}
        n_thinned = int(z[f"innov/{key}/n_thinned"]) if f"innov/{key}/n_thinned" in z else 0
        tables[name] = InnovationTable(*(z[f"innov/{key}/{f}"] for f in INNOV_FIELDS),
                                       folded=folded, n_thinned=n_thinned)
    return SavedRun(
        outdir, summary, tracks, truth, z["gps_t"], z["gps_xy"], z["gps_cov"],
        z["gps_withheld"],
        {str(i): (float(x), float(y)) for i, (x, y) in zip(z["landmark_ids"],
                                                            z["landmark_xy"], strict=True)},
        tables, owner, {name: z[f"update_s/{name}"] for name in meta["tracks"]},
        meta.get("config_text"))
