"""A run's output directory is complete or plainly marked incomplete (``INCOMPLETE``), whatever
stops the run (SIGKILL, a full disk); every file is written whole or not at all, an I/O error
names the file, and a new run leaves nothing of the previous one beside its own results."""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from ddfuse.evaluation import atomic_files
from ddfuse.evaluation.atomic_files import OutputError, replacing, write_text
from ddfuse.evaluation.cli import main
from ddfuse.evaluation.results import ResultsError, load_run
from ddfuse.evaluation.run_files import INCOMPLETE

ROOT = Path(__file__).resolve().parents[1]


def _run(out: Path, *extra: str) -> int:
    return main(["run", "-o", str(out), "--estimators", "dr", *extra])


def _partials(d: Path) -> list[Path]:
    return sorted(d.rglob(f"*{atomic_files.PARTIAL}*"))


def test_replacing_keeps_the_old_file_when_the_writer_fails(tmp_path):
    p = tmp_path / "a.csv"
    p.write_text("old\n")
    with pytest.raises(RuntimeError), replacing(p) as f:
        f.write("half a ne")
        raise RuntimeError("stopped")
    assert p.read_text() == "old\n" and not _partials(tmp_path)
    assert write_text(p, "new\n") == p and p.read_text() == "new\n"


def test_a_full_disk_names_the_file_and_leaves_no_truncated_one(tmp_path, monkeypatch):
    """Before: 'ddfuse: error: No space left on device', no file named, a truncated file."""
    p = tmp_path / "smoother.csv"
    p.write_text("old\n")

    class Full:
        def __init__(self, f):
            self.f = f

        def write(self, s):
            self.f.write(s[: len(s) // 2])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(OutputError) as e, replacing(p) as f:
        Full(f).write("x" * 1000)
    assert str(e.value) == f"cannot write {p}: No space left on device"
    assert isinstance(e.value, OSError) and e.value.filename == str(p)
    assert p.read_text() == "old\n" and not _partials(tmp_path)


def test_a_run_after_one_with_a_report_leaves_no_stale_report(tmp_path, capsys):
    """Issue 29: `run --no-report` after a run with a report left the old report.html and
    plots beside the new numbers; and a track of an estimator not run again stayed."""
    out = tmp_path / "out"
    out.mkdir()
    for name in ("report.html", "smoother.csv", "smoother.tum", "metrics.json"):
        (out / name).write_text("from an earlier run\n")
    (out / "plots").mkdir()
    (out / "plots" / "nees.png").write_bytes(b"old")
    (out / "metrics.json").write_text(json.dumps({"estimators": {"smoother": {}}}))
    assert _run(out, "--no-report") == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["dr.csv", "dr.tum", "estimates.mcap", "ground_truth.csv",
                     "ground_truth.tum", "metrics.json", "plots", "run.npz"]
    assert not list((out / "plots").iterdir())
    assert json.loads((out / "metrics.json").read_text())["estimators_run"] == ["dr"]
    assert load_run(out).tracks.keys() == {"dr"}


@pytest.mark.slow
def test_a_killed_run_leaves_its_directory_marked_incomplete(tmp_path):
    """SIGKILL while the results are written (here: as the second file is renamed into place).
    Before: new tracks beside the previous run's metrics.json, nothing to tell them apart."""
    out = tmp_path / "out"
    assert _run(out, "--no-report") == 0  # a complete earlier run
    script = textwrap.dedent(f"""
        import os, signal
        from ddfuse.evaluation import atomic_files
        from ddfuse.evaluation.cli import main
        calls = []
        real = os.replace
        def replace_then_die(a, b):
            calls.append(b)
            if len(calls) == 3:  # the marker, one track file, then killed
                os.kill(os.getpid(), signal.SIGKILL)
            real(a, b)
        atomic_files.os.replace = replace_then_die
        main(["run", "-o", {str(out)!r}, "--estimators", "dr", "--no-report"])
    """)
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == -9, r.stderr
    marker = (out / INCOMPLETE).read_text()
    assert marker.startswith("written by ddfuse run of ") and "which has not finished" in marker
    assert marker.splitlines()[-1] == "dr.tum"  # the files written, one a line
    assert not (out / "metrics.json").exists()  # the previous run's: removed first
    assert len(_partials(out)) == 1  # the file being written when it was killed
    with pytest.raises(ResultsError, match="incomplete run results"):
        load_run(out)
    # ddfuse report refuses in one line; the next run cleans up and completes the directory
    r = subprocess.run([sys.executable, "-m", "ddfuse.evaluation.cli", "report", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert r.stderr.startswith(f"ddfuse: error: {out}: incomplete run results (INCOMPLETE: "
                               "written by ddfuse run of ")
    assert _run(out, "--no-report") == 0
    assert not (out / INCOMPLETE).exists() and not _partials(out)
    assert load_run(out).tracks.keys() == {"dr"}


def test_a_run_into_a_full_file_system_says_which_file(tmp_path, capsys):
    """A 200 kB tmpfs (root only: skipped where mounting is not permitted). Before: 'ddfuse:
    error: No space left on device', metrics.json lost, a truncated track."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    if shutil.which("mount") is None or subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=200k", "tmpfs", str(mnt)],
            capture_output=True).returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root and mount)")
    try:
        out = mnt / "out"
        assert _run(out, "--no-report") == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"ddfuse: error: cannot write {out}/")
        assert err[0].endswith(": No space left on device")
        assert (out / INCOMPLETE).is_file() and not _partials(out)
        for p in out.glob("*.csv"):  # each track file whole: its last line complete
            assert p.read_text().endswith("\n") and len(p.read_text().splitlines()[-1]) > 40
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


def test_a_read_only_output_file_is_named(tmp_path, capsys, monkeypatch):
    """An output directory whose files cannot be replaced (a read-only file system, a
    permission): the error names the file, before any traceback could."""
    out = tmp_path / "out"

    def denied(path, mode="r", **kw):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))

    monkeypatch.setattr(atomic_files, "open", denied, raising=False)
    assert _run(out, "--no-report") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"ddfuse: error: cannot write {out / INCOMPLETE}: Permission denied"]
