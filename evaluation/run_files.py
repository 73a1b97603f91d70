"""Writing a run's results: the track files, run.npz and metrics.json of an output directory
(``ddfuse.evaluation.pipeline.run_bag`` writes them through ``writing_run``;
``ddfuse.evaluation.results`` reads them back).

A directory is complete or plainly marked incomplete, whatever stops the run (SIGKILL, a full
disk): ``writing_run`` first writes the marker file ``INCOMPLETE`` (which run, when it started,
then one line per file written) and removes what the previous run wrote that the new results
make stale (its metrics.json, report.html and plots/*.png, its track files that this run does
not write); each file is then written whole or not at all (``evaluation.atomic_files``),
metrics.json last, and only then is the marker removed. ``load_run`` and ``ddfuse report``
refuse a directory with the marker in one line. The report (report.html, plots/) is rendered
from the complete results afterwards: absent until then, never the previous run's.

An output directory holds ``metrics.json`` (``ddfuse.evaluation.pipeline``), one ``<track>.tum`` and
``<track>.csv`` per estimator track (``evaluation.export``), ``ground_truth.tum``/``.csv`` when
there is truth, ``estimates.mcap`` (the tracks, truth and GPS fixes as ROS 2 messages:
``evaluation.estimates_mcap``), and ``run.npz`` with the rest of what the report shows:

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

import datetime
import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from ddfuse.estimation.runner import RunResult
from ddfuse.evaluation.atomic_files import (
    OutputError,
    remove,
    remove_partials,
    replacing,
    write_text,
)
from ddfuse.evaluation.consistency import InnovationTable
from ddfuse.evaluation.estimates_mcap import ESTIMATES_FILE, write_estimates
from ddfuse.evaluation.export import write_csv, write_tum
from ddfuse.evaluation.latency_stats import blocks_of

__all__ = ["INCOMPLETE", "METRICS_FILE", "PLOTS_DIR", "REPORT_FILE", "RUN_FILE", "TRUTH",
           "config_text_of", "incomplete_note", "save_run", "write_metrics", "writing_run"]

RUN_FILE = "run.npz"
METRICS_FILE = "metrics.json"
REPORT_FILE = "report.html"
PLOTS_DIR = "plots"
INCOMPLETE = "INCOMPLETE"
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
    """The track names an earlier run recorded in ``outdir``'s run.npz, else in its
    metrics.json (none if neither can be read)."""
    try:
        with np.load(outdir / RUN_FILE) as z:
            return list(json.loads(str(z["meta"]))["tracks"]) + [TRUTH]
    except (OSError, ValueError, KeyError, TypeError):
        pass
    try:
        names = json.loads((outdir / METRICS_FILE).read_text())["estimators"]
        return [*(str(n) for n in names), TRUTH]
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return []


def incomplete_note(outdir: Path) -> str | None:
    """The first line of ``outdir``'s INCOMPLETE marker (which run, when it started), or None
    when the directory has no marker."""
    try:
        text = (Path(outdir) / INCOMPLETE).read_text(errors="replace")
    except FileNotFoundError:
        return None
    except OSError as e:
        return f"its marker cannot be read ({e.strerror or e})"
    return text.splitlines()[0] if text.strip() else "no details"


def track_names(result: RunResult) -> set[str]:
    """The tracks ``save_run`` writes for ``result``: those with samples, and the truth."""
    now = {n for n, r in result.runs.items() if len(r.trajectory)}
    if result.truth is not None:
        now.add(TRUTH)
    return now


def _remove_tracks(outdir: Path, names) -> None:
    for name in names:
        for ext in ("tum", "csv"):
            remove(outdir / f"{name}.{ext}")


@contextmanager
def writing_run(outdir: str | Path, what: str, result: RunResult) -> Iterator[Path]:
    """Write ``result`` (a run's results) into ``outdir`` (made if needed) inside this block,
    as the module docstring says: on entry the INCOMPLETE marker, naming ``what`` (e.g.
    'ddfuse run of BAG'), and the previous run's files that these results make stale removed
    (its metrics.json, report, plots, and its tracks that ``result`` has not); the marker
    removed when the block ends without an exception (a stop inside it leaves the marker, with
    the reason appended). The block writes through ``save_run`` and ``write_metrics`` (which
    note each file in the marker). Yields ``outdir`` as a Path. OSError -> ``OutputError``
    naming the path."""
    outdir = Path(outdir)
    try:
        outdir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError.of(outdir, e) from None
    marker = outdir / INCOMPLETE
    started = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    write_text(marker, f"written by {what} (pid {os.getpid()}, writing since {started}), "
               "which has not finished writing its results\n"
               "# until this file is gone the results here are incomplete; rerun to replace "
               "them. Files written so far:\n")
    remove_partials(outdir)
    _remove_tracks(outdir, set(_previous_tracks(outdir)) - track_names(result))
    for stale in (METRICS_FILE, REPORT_FILE, ESTIMATES_FILE):
        remove(outdir / stale)
    if (outdir / PLOTS_DIR).is_dir():
        for png in (outdir / PLOTS_DIR).glob("*.png"):
            remove(png)
    try:
        yield outdir
    except BaseException as e:
        _note(outdir, f"# stopped: {type(e).__name__}: {e}")
        raise
    remove(marker)


def _note(outdir: Path, line: str) -> None:
    """Append ``line`` to ``outdir``'s marker, if it is there and can be written."""
    try:
        if (outdir / INCOMPLETE).is_file():
            with open(outdir / INCOMPLETE, "a", encoding="utf-8") as f:
                f.write(line + "\n")
    except OSError:
        pass  # the marker's first line already says the results are incomplete


def save_run(result: RunResult, outdir: Path, config_text: str | None = None, *,
             frames: tuple[str, str] = ("map", "base_link"), tf: str | None = None) -> None:
    """Write the trajectories, estimates.mcap (``evaluation.estimates_mcap``, in ``frames``:
    the local and base frame ids; ``tf`` the config's ``node.tf``) and run.npz of ``result``
    into ``outdir`` (which must exist), each file whole or not at all; inside ``writing_run``,
    each is noted in the marker. Track files that an earlier run into the same directory wrote
    (its run.npz lists them) and this one does not are removed, so the directory holds one
    run, not a mix."""
    _remove_tracks(outdir, set(_previous_tracks(outdir)) - track_names(result))
    tracks = {name: r.trajectory for name, r in result.runs.items() if len(r.trajectory)}
    if result.truth is not None:
        tracks[TRUTH] = result.truth
    for name, tr in tracks.items():
        for ext, write in (("tum", write_tum), ("csv", write_csv)):
            write(outdir / f"{name}.{ext}", tr)
            tr.release()  # a spilled track's pages (runner.Trajectory.release)
            _note(outdir, f"{name}.{ext}")
    write_estimates(outdir / ESTIMATES_FILE, result, local_frame=frames[0],
                    base_frame=frames[1], tf=tf)
    _note(outdir, ESTIMATES_FILE)
    with replacing(outdir / RUN_FILE, "wb") as f:
        _write_npz(f, _run_entries(result, config_text))
    _note(outdir, RUN_FILE)


def write_metrics(outdir: Path, metrics_dict: dict) -> None:
    """``outdir``/metrics.json, whole or not at all: the last file of a run's results."""
    write_text(outdir / METRICS_FILE, json.dumps(metrics_dict, indent=2) + "\n")
    _note(outdir, METRICS_FILE)



_NPY_BLOCK = 1 << 16  # elements of a float32 column widened and written at a time


def _write_npz(f, entries: Iterator[tuple[str, np.ndarray, bool]]) -> None:
    """What ``np.savez_compressed`` writes for ``run_arrays``' dictionary (the same members,
    each the same .npy bytes) from ``_run_entries`` (key, array, widen), each entry written
    as it comes, so that only one is in memory at a time; one marked ``widen`` (the per-call
    timings, float32 in the run) written as float64, ``_NPY_BLOCK`` elements at a time."""
    import zipfile

    with zipfile.ZipFile(f, mode="w", compression=zipfile.ZIP_DEFLATED, allowZip64=True) as z:
        for key, a, widen in entries:
            with z.open(key + ".npy", "w", force_zip64=True) as out:
                if not widen:
                    np.lib.format.write_array(out, np.asanyarray(a), allow_pickle=False)
                    continue
                np.lib.format.write_array_header_1_0(out, {
                    "descr": np.lib.format.dtype_to_descr(np.dtype(float)),
                    "fortran_order": False, "shape": a.shape})
                for b in blocks_of(a, _NPY_BLOCK):  # a SpilledColumn's from its file
                    out.write(b.astype(float).tobytes())


def run_arrays(result: RunResult, config_text: str | None) -> dict[str, np.ndarray]:
    """The arrays of run.npz for ``result`` (module docstring)."""
    return {k: np.asarray(a, float) if widen else a
            for k, a, widen in _run_entries(result, config_text)}


def _run_entries(result: RunResult, config_text: str | None
                 ) -> Iterator[tuple[str, np.ndarray, bool]]:
    """run.npz's (key, array, widen) for ``result``, in its order, each made when asked for;
    ``widen``: the array is as the run holds it (the per-call timings, float32) and run.npz
    has it as float64."""
    gps = result.gps
    lm = result.stream.landmarks
    yield "gps_t", gps.t, False
    yield "gps_xy", gps.xy.reshape(-1, 2), False
    yield "gps_cov", gps.cov.reshape(-1, 2, 2), False
    yield "gps_withheld", gps.withheld, False
    yield "landmark_ids", np.array(list(lm), dtype=str), False
    yield "landmark_xy", np.array(list(lm.values()), float).reshape(-1, 2), False
    owner: dict[str, str] = {}
    logs: dict[int, str] = {}  # id(log) -> first track using it
    for name, r in result.runs.items():
        key = logs.setdefault(id(r.log), name)
        owner[name] = key
        upd = r.update_s  # an array or a SpilledColumn (runner.EstimatorRun)
        yield f"update_s/{name}", upd, upd.dtype != float
        if key == name:
            table = InnovationTable.from_innovations(r.log.innovations)
            for f in INNOV_FIELDS:
                yield f"innov/{name}/{f}", getattr(table, f), False
            # a long run's log is thinned: the exact counts of what it no longer holds one by
            # one, so that NIS from a loaded run equals metrics.json's
            yield f"innov/{name}/folded", np.array(json.dumps(
                [[list(k), [float(x) for x in v]] for k, v in table.folded.items()])), False
            yield f"innov/{name}/n_thinned", np.array(table.n_thinned), False
            del table
    meta = {"tracks": list(result.runs), "log_owner": owner, "config_text": config_text}
    yield "meta", np.array(json.dumps(meta)), False
