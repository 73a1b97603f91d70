"""Writing a run's results: the track files and run.npz of an output directory
(``ddfuse.evaluation.pipeline.run_bag`` writes metrics.json beside them;
``ddfuse.evaluation.results`` reads them back).

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
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from ddfuse.estimation.runner import RunResult
from ddfuse.evaluation.consistency import InnovationTable
from ddfuse.evaluation.export import write_csv, write_tum

__all__ = ["METRICS_FILE", "RUN_FILE", "TRUTH", "config_text_of", "save_run"]

RUN_FILE = "run.npz"
METRICS_FILE = "metrics.json"
TRUTH = "ground_truth"
INNOV_FIELDS = ("t", "sensor", "kind", "nis", "dim", "accepted")


def config_text_of(cfg) -> str | None:
    """The YAML ``cfg`` was parsed from (``Config.text``), else its file's text as it is now,
    else None (a config built in code, or parsed under a label that is no file)."""
    if getattr(cfg, "text", None) is not None:
        return cfg.text
    path = getattr(cfg, "path", None)
    return Path(path).read_text(errors="replace") if path and Path(path).is_file() else None



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
    np.savez_compressed(outdir / RUN_FILE, **run_arrays(result, config_text))



def run_arrays(result: RunResult, config_text: str | None) -> dict[str, np.ndarray]:
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
            for f in INNOV_FIELDS:
                arrays[f"innov/{name}/{f}"] = getattr(table, f)
            # a long run's log is thinned: the exact counts of what it no longer holds one by
            # one, so that NIS from a loaded run equals metrics.json's
            arrays[f"innov/{name}/folded"] = np.array(json.dumps(
                [[list(k), [float(x) for x in v]] for k, v in table.folded.items()]))
            arrays[f"innov/{name}/n_thinned"] = np.array(table.n_thinned)
    meta = {"tracks": list(result.runs), "log_owner": owner, "config_text": config_text}
    arrays["meta"] = np.array(json.dumps(meta))
    return arrays
