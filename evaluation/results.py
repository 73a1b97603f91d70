"""A run's saved results: written by ``ddfuse run``, read back by ``ddfuse report``.

An output directory holds ``metrics.json`` (``ddfuse.evaluation.pipeline``), one ``<track>.tum`` and
``<track>.csv`` per estimator track (``evaluation.export``), ``ground_truth.tum``/``.csv`` when
there is truth, and ``run.npz`` with the rest of what the report shows:

* ``gps_t`` (G,) s, ``gps_xy`` (G, 2) m local ENU, ``gps_cov`` (G, 2, 2) m^2,
  ``gps_withheld`` (G,) bool: every GPS fix of the stream, marked if withheld from the estimators;
* ``landmark_ids`` (L,) str, ``landmark_xy`` (L, 2) m: the landmark map;
* ``update_s/<track>`` (U,) s: wall time of each ``process`` call;
* ``innov/<log>/{t, sensor, kind, nis, dim, accepted}`` (N,): each estimator's innovation log
  (``consistency.InnovationTable``), once per estimator (a lagged track shares its filter's);
  on a long run a thinned subset of the early entries (for the plots) and every recent one,
  with ``innov/<log>/folded`` (JSON: the exact counts of the thinned groups) and
  ``n_thinned``, so that ``consistency.nis_by_sensor`` of a loaded table is metrics.json's;
* ``meta``: JSON text: the tracks in order, which log each track's innovations are in, the
  config file's text.

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
from ddfuse.evaluation.export import read_csv, write_csv, write_tum
from ddfuse.evaluation.scores import DataFacts, RunSummary

RUN_FILE = "run.npz"
METRICS_FILE = "metrics.json"
TRUTH = "ground_truth"
_INNOV_FIELDS = ("t", "sensor", "kind", "nis", "dim", "accepted")


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
        return _from_arrays(None, metrics, _run_arrays(result, config_text), tracks,
                            result.truth)


def config_text_of(cfg) -> str | None:
    """The YAML ``cfg`` was parsed from (``Config.text``), else its file's text as it is now,
    else None (a config built in code, or parsed under a label that is no file)."""
    if getattr(cfg, "text", None) is not None:
        return cfg.text
    path = getattr(cfg, "path", None)
    return Path(path).read_text(errors="replace") if path and Path(path).is_file() else None


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


def _previous_tracks(outdir: Path) -> list[str]:
    """The track names an earlier run recorded in ``outdir``'s run.npz (none if unreadable)."""
    try:
        with np.load(outdir / RUN_FILE) as z:
            return list(json.loads(str(z["meta"]))["tracks"]) + [TRUTH]
    except (OSError, ValueError, KeyError, TypeError):
        return []


def save_run(result: RunResult, outdir: Path, config_text: str | None = None) -> None:
    """Write the trajectories and run.npz of ``result`` into ``outdir`` (which must exist).
    Track files that an earlier run into the same directory wrote (its run.npz lists them) and
    this one does not are removed, so the directory holds one run, not a mix."""
    now = {n for n, r in result.runs.items() if len(r.trajectory)}
    if result.truth is not None:
        now.add(TRUTH)
    for name in _previous_tracks(outdir):
        if name not in now:
            for ext in ("tum", "csv"):
                (outdir / f"{name}.{ext}").unlink(missing_ok=True)
    for name, r in result.runs.items():
        if len(r.trajectory):
            write_tum(outdir / f"{name}.tum", r.trajectory)
            write_csv(outdir / f"{name}.csv", r.trajectory)
    if result.truth is not None:
        write_tum(outdir / f"{TRUTH}.tum", result.truth)
        write_csv(outdir / f"{TRUTH}.csv", result.truth)
    np.savez_compressed(outdir / RUN_FILE, **_run_arrays(result, config_text))


def _run_arrays(result: RunResult, config_text: str | None) -> dict[str, np.ndarray]:
    """The arrays of run.npz for ``result`` (module docstring)."""
    gps = result.gps
    lm = result.stream.landmarks
    arrays: dict[str, np.ndarray] = {
        "gps_t": gps.t,
        "gps_xy": gps.xy.reshape(-1, 2),
        "gps_cov": gps.cov.reshape(-1, 2, 2),
        "gps_withheld": gps.withheld,
        "landmark_ids": np.array(list(lm), dtype=str),
        "landmark_xy": np.array(list(lm.values()), float).reshape(-1, 2),
    }
    owner: dict[str, str] = {}
    logs: dict[int, str] = {}  # id(log) -> first track using it
    for name, r in result.runs.items():
        key = logs.setdefault(id(r.log), name)
        owner[name] = key
        arrays[f"update_s/{name}"] = np.asarray(r.update_s, float)
        if key == name:
            table = InnovationTable.from_innovations(r.log.innovations)
            for f in _INNOV_FIELDS:
                arrays[f"innov/{name}/{f}"] = getattr(table, f)
            # a long run's log is thinned: the exact counts of what it no longer holds one by
            # one, so that NIS from a loaded run equals metrics.json's
            arrays[f"innov/{name}/folded"] = np.array(json.dumps(
                [[list(k), [float(x) for x in v]] for k, v in table.folded.items()]))
            arrays[f"innov/{name}/n_thinned"] = np.array(table.n_thinned)
    meta = {"tracks": list(result.runs), "log_owner": owner, "config_text": config_text}
    arrays["meta"] = np.array(json.dumps(meta))
    return arrays


def load_run(outdir: str | Path) -> SavedRun:
    """Read the results in ``outdir``; ResultsError naming the path if they are absent or
    unreadable."""
    outdir = Path(outdir)
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
    """A SavedRun from run.npz's arrays ``z`` (an NpzFile or the dictionary ``_run_arrays``
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
        tables[name] = InnovationTable(*(z[f"innov/{key}/{f}"] for f in _INNOV_FIELDS),
                                       folded=folded, n_thinned=n_thinned)
    return SavedRun(
        outdir, summary, tracks, truth, z["gps_t"], z["gps_xy"], z["gps_cov"],
        z["gps_withheld"],
        {str(i): (float(x), float(y)) for i, (x, y) in zip(z["landmark_ids"],
                                                            z["landmark_xy"], strict=True)},
        tables, owner, {name: z[f"update_s/{name}"] for name in meta["tracks"]},
        meta.get("config_text"))
